//! Frame files in the order of the number in their name (`frame9` before `frame10`), as the
//! release sorts them (`int(name[5:11])`, `int(name[:3])`, a regex on the digits): a plain text
//! sort puts `frame10` before `frame9` whenever names are not zero-padded.

use std::cmp::Ordering;

/// The last run of ASCII digits in the file-name part of `path`, as a number.
pub fn frame_number(path: &str) -> Option<u64> {
    let name = path.rsplit('/').next().unwrap_or(path);
    let bytes = name.as_bytes();
    let end = bytes.iter().rposition(u8::is_ascii_digit)? + 1;
    let start = bytes[..end]
        .iter()
        .rposition(|b| !b.is_ascii_digit())
        .map_or(0, |i| i + 1);
    name[start..end].parse().ok()
}

/// Numbered names first, by number; names without a number after them, by text; ties by text.
pub fn compare_frames(a: &str, b: &str) -> Ordering {
    match (frame_number(a), frame_number(b)) {
        (Some(x), Some(y)) => x.cmp(&y).then_with(|| a.cmp(b)),
        (Some(_), None) => Ordering::Less,
        (None, Some(_)) => Ordering::Greater,
        (None, None) => a.cmp(b),
    }
}

/// Sorts frame paths by the number in their names.
pub fn sort_frames<S: AsRef<str>>(frames: &mut [S]) {
    frames.sort_by(|a, b| compare_frames(a.as_ref(), b.as_ref()));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_sort_by_the_number_in_their_name() {
        let mut frames = vec![
            "seq/images/frame10.jpg",
            "seq/images/frame9.jpg",
            "seq/images/frame100.jpg",
            "seq/images/frame000001.jpg",
        ];
        sort_frames(&mut frames);
        assert_eq!(
            frames,
            vec![
                "seq/images/frame000001.jpg",
                "seq/images/frame9.jpg",
                "seq/images/frame10.jpg",
                "seq/images/frame100.jpg",
            ]
        );
        assert_eq!(frame_number("a7/b/00012.png"), Some(12));
        assert_eq!(frame_number("a7/b/cover.png"), None);
    }
}

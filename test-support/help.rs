//! What a binary's clap `--help` says, for the crates' command-line tests. Not a crate: each
//! test that needs it includes this file with `#[path = "../../test-support/help.rs"] mod help;`.

use std::collections::BTreeMap;
use std::process::Command;

/// Every `--flag` a `--help` text defines, with the default it shows (`None`: no default).
/// Only definition lines count (`--flag <VALUE>`, `-h, --help`), not flags named in prose.
pub fn flags(help: &str) -> BTreeMap<String, Option<String>> {
    let mut flags = BTreeMap::new();
    let mut current: Option<String> = None;
    for line in help.lines() {
        let trimmed = line.trim_start();
        let defines = trimmed.starts_with("--")
            || (trimmed.starts_with('-') && trimmed.get(2..4) == Some(", "));
        if defines {
            current = trimmed
                .split([' ', ',', '='])
                .find(|word| word.starts_with("--"))
                .map(str::to_string);
            if let Some(flag) = &current {
                flags.insert(flag.clone(), None);
            }
        } else if !line.is_empty() && !line.starts_with(' ') {
            // A heading (`Options:`, `Commands:`) ends the flag's entry.
            current = None;
        }
        if let (Some(flag), Some(start)) = (&current, line.find("[default: ")) {
            let rest = &line[start + "[default: ".len()..];
            let value = rest.find(']').map(|end| rest[..end].to_string());
            flags.insert(flag.clone(), value);
        }
    }
    flags
}

/// The `--help` of `binary arguments...` (which must succeed).
pub fn help(binary: &str, arguments: &[&str]) -> String {
    let output = Command::new(binary)
        .args(arguments)
        .arg("--help")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "{binary} {arguments:?} --help: {text}"
    );
    text
}

/// Checks that `binary arguments... --help` defines exactly `expected` (besides `--help` and
/// `--version`), each with the default given (`None`: no default shown).
pub fn assert_flags(binary: &str, arguments: &[&str], expected: &[(&str, Option<&str>)]) {
    let text = help(binary, arguments);
    let mut found = flags(&text);
    found.remove("--help");
    found.remove("--version");
    let expected: BTreeMap<String, Option<String>> = expected
        .iter()
        .map(|(flag, default)| (flag.to_string(), default.map(str::to_string)))
        .collect();
    assert_eq!(found, expected, "{binary} {arguments:?} --help:\n{text}");
}

/// Checks that `binary arguments...` is refused by the parser (exit status 2) with an error
/// that names `flag`.
pub fn assert_refused(binary: &str, arguments: &[&str], flag: &str) {
    assert_fails(binary, arguments, 2, flag);
}

/// Checks that `binary arguments...` exits with `code` and an error that contains `text`.
pub fn assert_fails(binary: &str, arguments: &[&str], code: i32, text: &str) {
    let output = Command::new(binary).args(arguments).output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(code), "{arguments:?}: {stderr}");
    assert!(
        stderr.contains(text),
        "{arguments:?} failed without naming {text}: {stderr}"
    );
}

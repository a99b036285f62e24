//! Pixels, lines, colour swatches and small digits on an RGB canvas: what the PNG figures of
//! [`crate::curves`] and [`crate::bars`] draw with, so they need no font or plotting crate.

use image::{Rgb, RgbImage};

/// Colours of successive series.
pub(crate) const PALETTE: [Rgb<u8>; 4] = [
    Rgb([31, 119, 180]),
    Rgb([214, 39, 40]),
    Rgb([44, 160, 44]),
    Rgb([148, 103, 189]),
];

/// The canvas as PNG bytes.
pub(crate) fn encode_png(canvas: &RgbImage) -> Result<Vec<u8>, image::ImageError> {
    let mut bytes = Vec::new();
    canvas.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )?;
    Ok(bytes)
}

/// Sets one pixel; points off the canvas are dropped.
pub(crate) fn put(canvas: &mut RgbImage, (x, y): (i64, i64), colour: Rgb<u8>) {
    if x >= 0 && y >= 0 && (x as u32) < canvas.width() && (y as u32) < canvas.height() {
        canvas.put_pixel(x as u32, y as u32, colour);
    }
}

/// Bresenham's line.
pub(crate) fn line(canvas: &mut RgbImage, from: (i64, i64), to: (i64, i64), colour: Rgb<u8>) {
    let (mut x, mut y) = from;
    let (dx, dy) = ((to.0 - x).abs(), -(to.1 - y).abs());
    let (sx, sy) = (if x < to.0 { 1 } else { -1 }, if y < to.1 { 1 } else { -1 });
    let mut error = dx + dy;
    loop {
        put(canvas, (x, y), colour);
        if (x, y) == to {
            return;
        }
        let doubled = 2 * error;
        if doubled >= dy {
            error += dy;
            x += sx;
        }
        if doubled <= dx {
            error += dx;
            y += sy;
        }
    }
}

/// An 8x8 square of `colour` with its top-left corner at `(x, y)`.
pub(crate) fn swatch(canvas: &mut RgbImage, (x, y): (i64, i64), colour: Rgb<u8>) {
    for dy in 0..8 {
        for dx in 0..8 {
            put(canvas, (x + dx, y + dy), colour);
        }
    }
}

/// 3x5 glyphs for the characters numbers need; each row is three bits, top row first.
fn glyph(character: char) -> Option<[u8; 5]> {
    Some(match character {
        '0' => [0b111, 0b101, 0b101, 0b101, 0b111],
        '1' => [0b010, 0b110, 0b010, 0b010, 0b111],
        '2' => [0b111, 0b001, 0b111, 0b100, 0b111],
        '3' => [0b111, 0b001, 0b111, 0b001, 0b111],
        '4' => [0b101, 0b101, 0b111, 0b001, 0b001],
        '5' => [0b111, 0b100, 0b111, 0b001, 0b111],
        '6' => [0b111, 0b100, 0b111, 0b101, 0b111],
        '7' => [0b111, 0b001, 0b010, 0b010, 0b010],
        '8' => [0b111, 0b101, 0b111, 0b101, 0b111],
        '9' => [0b111, 0b101, 0b111, 0b001, 0b111],
        '.' => [0b000, 0b000, 0b000, 0b000, 0b010],
        '-' => [0b000, 0b000, 0b111, 0b000, 0b000],
        'e' => [0b000, 0b111, 0b111, 0b100, 0b111],
        _ => return None,
    })
}

/// `label` in the 3x5 glyphs, 4 pixels per character; characters without a glyph are skipped.
pub(crate) fn text(canvas: &mut RgbImage, (x, y): (i64, i64), label: &str, colour: Rgb<u8>) {
    for (index, character) in label.chars().enumerate() {
        let Some(rows) = glyph(character) else {
            continue;
        };
        let origin = x + index as i64 * 4;
        for (row, bits) in rows.iter().enumerate() {
            for bit in 0..3 {
                if bits & (0b100 >> bit) != 0 {
                    put(canvas, (origin + bit, y + row as i64), colour);
                }
            }
        }
    }
}

//! Sheets of small images for people: every tile scaled up (nearest neighbour) to a side a
//! reader can see, each row named on the left, each column named on top, under a title. The
//! evaluation's render grids of 32-pixel frames were unreadable at 1:1 without labels.

use plotters::coord::Shift;
use plotters::prelude::*;

use crate::plot::{Chart, DrawResult, FAMILY, boxed};

/// Gap between tiles, in pixels.
const GAP: u32 = 4;
/// Width of the row labels' column, in pixels.
const LABEL_WIDTH: u32 = 230;
/// Height of the title and of the column labels' row, in pixels.
const HEADER: u32 = 34;

/// One image: `width` x `height` pixels of 8-bit RGB, row by row.
#[derive(Debug, Clone, PartialEq)]
pub struct Tile {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height * 3` bytes.
    pub rgb: Vec<u8>,
}

/// One named row of tiles.
#[derive(Debug, Clone, PartialEq)]
pub struct TileRow {
    /// What the row shows, drawn on its left.
    pub label: String,
    /// Its tiles, left to right (a row may be shorter than others).
    pub tiles: Vec<Tile>,
}

/// Rows of tiles under a title and column labels, every tile scaled up by the same whole
/// factor to at least `min_side` pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct TileSheet {
    /// What the sheet shows.
    pub title: String,
    /// Each column's name, drawn above it.
    pub columns: Vec<String>,
    /// The rows, top to bottom.
    pub rows: Vec<TileRow>,
    /// The least side of a tile as drawn.
    pub min_side: u32,
}

impl TileSheet {
    /// The whole factor every tile is scaled by.
    pub fn scale(&self) -> u32 {
        let side = self
            .tiles()
            .map(|t| t.width.max(t.height))
            .max()
            .unwrap_or(1)
            .max(1);
        self.min_side.div_ceil(side).max(1)
    }

    fn tiles(&self) -> impl Iterator<Item = &Tile> {
        self.rows.iter().flat_map(|row| row.tiles.iter())
    }

    /// A drawn cell's width and height.
    fn cell(&self) -> (u32, u32) {
        let scale = self.scale();
        let width = self.tiles().map(|t| t.width).max().unwrap_or(0) * scale;
        let height = self.tiles().map(|t| t.height).max().unwrap_or(0) * scale;
        (width, height)
    }

    fn column_count(&self) -> u32 {
        let widest = self.rows.iter().map(|r| r.tiles.len()).max().unwrap_or(0);
        widest.max(self.columns.len()) as u32
    }
}

impl Chart for TileSheet {
    fn title(&self) -> &str {
        &self.title
    }

    fn size(&self) -> (u32, u32) {
        let (cell_w, cell_h) = self.cell();
        let width = LABEL_WIDTH + self.column_count() * (cell_w + GAP) + GAP;
        let height = 2 * HEADER + self.rows.len() as u32 * (cell_h + GAP) + GAP;
        (width, height)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> DrawResult
    where
        DB::ErrorType: 'static,
    {
        root.fill(&WHITE).map_err(boxed)?;
        let text = |size: u32| (FAMILY, size).into_font().color(&BLACK);
        root.draw(&Text::new(self.title.clone(), (GAP as i32, 6), text(20)))
            .map_err(boxed)?;
        let (cell_w, cell_h) = self.cell();
        let left = |column: u32| (LABEL_WIDTH + GAP + column * (cell_w + GAP)) as i32;
        let top = |row: u32| (2 * HEADER + GAP + row * (cell_h + GAP)) as i32;
        for (column, name) in self.columns.iter().enumerate() {
            let at = (left(column as u32), HEADER as i32 + 10);
            root.draw(&Text::new(name.clone(), at, text(14)))
                .map_err(boxed)?;
        }
        let scale = self.scale() as i32;
        for (r, row) in self.rows.iter().enumerate() {
            let at = (GAP as i32, top(r as u32) + cell_h as i32 / 2 - 8);
            root.draw(&Text::new(row.label.clone(), at, text(14)))
                .map_err(boxed)?;
            for (c, tile) in row.tiles.iter().enumerate() {
                draw_tile(root, tile, (left(c as u32), top(r as u32)), scale)?;
            }
        }
        Ok(())
    }
}

/// `tile` with its top left corner at `at`, every pixel a `scale` x `scale` square.
fn draw_tile<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    tile: &Tile,
    at: (i32, i32),
    scale: i32,
) -> DrawResult
where
    DB::ErrorType: 'static,
{
    for (index, pixel) in tile.rgb.chunks_exact(3).enumerate() {
        let (x, y) = (
            (index as u32 % tile.width) as i32,
            (index as u32 / tile.width) as i32,
        );
        let corner = (at.0 + x * scale, at.1 + y * scale);
        let colour = RGBColor(pixel[0], pixel[1], pixel[2]).filled();
        root.draw(&Rectangle::new(
            [corner, (corner.0 + scale, corner.1 + scale)],
            colour,
        ))
        .map_err(boxed)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tile(value: u8) -> Tile {
        Tile {
            width: 32,
            height: 32,
            rgb: vec![value; 32 * 32 * 3],
        }
    }

    #[test]
    fn tiles_are_scaled_to_the_least_side_and_named() {
        let sheet = TileSheet {
            title: "renders".into(),
            columns: vec!["frame 0".into(), "frame 1".into()],
            rows: vec![
                TileRow {
                    label: "source video".into(),
                    tiles: vec![tile(0), tile(0)],
                },
                TileRow {
                    label: "our render".into(),
                    tiles: vec![tile(200)],
                },
            ],
            min_side: 96,
        };
        assert_eq!(sheet.scale(), 3);
        let (width, height) = sheet.size();
        assert_eq!(width, LABEL_WIDTH + 2 * (96 + GAP) + GAP);
        assert_eq!(height, 2 * HEADER + 2 * (96 + GAP) + GAP);
        let png = sheet.to_png().expect("drawn");
        let image = image::load_from_memory(&png).expect("a PNG").to_rgb8();
        let (x, y) = (LABEL_WIDTH + GAP + 50, 2 * HEADER + GAP + 50);
        assert_eq!(
            image.get_pixel(x, y).0,
            [0, 0, 0],
            "a source tile, scaled up"
        );
        let below = y + 96 + GAP;
        assert_eq!(
            image.get_pixel(x, below).0,
            [200, 200, 200],
            "the render below it"
        );
        let label_ink = (0..LABEL_WIDTH)
            .flat_map(|x| (2 * HEADER..height).map(move |y| (x, y)))
            .filter(|&(x, y)| image.get_pixel(x, y).0 != [255, 255, 255])
            .count();
        assert!(label_ink > 100, "row labels drawn: {label_ink}");
    }
}

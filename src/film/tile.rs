//! A rectangle of the frame: the unit of pixels a task renders and a film accumulates.

use serde::{Deserialize, Serialize};

/// A rectangle of pixels [x0, x1) x [y0, y1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Hash)]
pub struct Tile {
    /// First column.
    pub x0: u32,
    /// First row.
    pub y0: u32,
    /// One past the last column.
    pub x1: u32,
    /// One past the last row.
    pub y1: u32,
}

impl Tile {
    /// Columns.
    pub fn width(&self) -> usize {
        (self.x1 - self.x0) as usize
    }
    /// Rows.
    pub fn height(&self) -> usize {
        (self.y1 - self.y0) as usize
    }
    /// Pixels.
    pub fn pixels(&self) -> usize {
        self.width() * self.height()
    }
    /// Row-major index in the tile of frame pixel (x, y), when the tile holds it.
    #[inline]
    pub fn index_of(&self, x: u32, y: u32) -> Option<usize> {
        (x >= self.x0 && x < self.x1 && y >= self.y0 && y < self.y1)
            .then(|| (y - self.y0) as usize * self.width() + (x - self.x0) as usize)
    }
}

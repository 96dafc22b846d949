//! A rectangle of pixels: a frame's footprint, and the area a resolve must visit.

/// A rectangle of pixels: columns `x0..x1`, rows `y0..y1`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(crate) struct PixelRect {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl PixelRect {
    pub const EMPTY: PixelRect = PixelRect {
        x0: 0,
        y0: 0,
        x1: 0,
        y1: 0,
    };

    /// The whole of a `width` x `height` image.
    pub fn full(width: u32, height: u32) -> Self {
        PixelRect {
            x0: 0,
            y0: 0,
            x1: width,
            y1: height,
        }
    }

    pub fn width(&self) -> u32 {
        self.x1.saturating_sub(self.x0)
    }

    pub fn height(&self) -> u32 {
        self.y1.saturating_sub(self.y0)
    }

    pub fn pixels(&self) -> u64 {
        u64::from(self.width()) * u64::from(self.height())
    }

    pub fn is_empty(&self) -> bool {
        self.pixels() == 0
    }

    /// The smallest rectangle that holds both.
    pub fn union(self, other: PixelRect) -> PixelRect {
        if self.is_empty() {
            return other;
        }
        if other.is_empty() {
            return self;
        }
        PixelRect {
            x0: self.x0.min(other.x0),
            y0: self.y0.min(other.y0),
            x1: self.x1.max(other.x1),
            y1: self.y1.max(other.y1),
        }
    }

    /// This rectangle widened by `margin` pixels on every side, within a `width` x `height`
    /// image; empty stays empty.
    pub fn grown(self, margin: u32, width: u32, height: u32) -> PixelRect {
        if self.is_empty() {
            return self;
        }
        PixelRect {
            x0: self.x0.saturating_sub(margin),
            y0: self.y0.saturating_sub(margin),
            x1: self.x1.saturating_add(margin).min(width),
            y1: self.y1.saturating_add(margin).min(height),
        }
    }

    #[cfg(test)]
    pub fn contains(&self, x: u32, y: u32) -> bool {
        (self.x0..self.x1).contains(&x) && (self.y0..self.y1).contains(&y)
    }
}

/// Where rectangles of pixels landed in an image, in cells of [`PixelCoverage::CELL`] pixels:
/// their union rectangle, and how many pixels the cells they touch hold, which follows a
/// frame's points more closely than the union rectangle does (a cube's corner covers a
/// triangle of its rectangle).
pub(crate) struct PixelCoverage {
    width: u32,
    height: u32,
    union: PixelRect,
    marked: Vec<bool>,
}

impl PixelCoverage {
    pub const CELL: u32 = 64;

    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            union: PixelRect::EMPTY,
            marked: vec![
                false;
                (width.div_ceil(Self::CELL) * height.div_ceil(Self::CELL)) as usize
            ],
        }
    }

    /// Adds a rectangle within the image.
    pub fn add(&mut self, rect: PixelRect) {
        if rect.is_empty() {
            return;
        }
        self.union = self.union.union(rect);
        let across = self.width.div_ceil(Self::CELL);
        let x1 = rect.x1.min(self.width).div_ceil(Self::CELL);
        let y1 = rect.y1.min(self.height).div_ceil(Self::CELL);
        for y in rect.y0 / Self::CELL..y1 {
            for x in rect.x0 / Self::CELL..x1 {
                self.marked[(y * across + x) as usize] = true;
            }
        }
    }

    /// Adds what `other`, a coverage of the same image, holds.
    pub fn merge(&mut self, other: &PixelCoverage) {
        debug_assert_eq!((self.width, self.height), (other.width, other.height));
        self.union = self.union.union(other.union);
        for (mine, theirs) in self.marked.iter_mut().zip(&other.marked) {
            *mine |= *theirs;
        }
    }

    /// The union of the rectangles added.
    pub fn union(&self) -> PixelRect {
        self.union
    }

    /// Pixels of the image in the cells a rectangle touched.
    pub fn pixels(&self) -> u64 {
        let across = self.width.div_ceil(Self::CELL);
        self.marked
            .iter()
            .enumerate()
            .filter(|(_, &marked)| marked)
            .map(|(i, _)| {
                let (x, y) = (i as u32 % across, i as u32 / across);
                let w = Self::CELL.min(self.width - x * Self::CELL);
                let h = Self::CELL.min(self.height - y * Self::CELL);
                u64::from(w) * u64::from(h)
            })
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn union_spans_both_rectangles_and_ignores_empty_ones() {
        let a = PixelRect {
            x0: 2,
            y0: 3,
            x1: 5,
            y1: 4,
        };
        let b = PixelRect {
            x0: 4,
            y0: 0,
            x1: 9,
            y1: 2,
        };
        assert_eq!(
            a.union(b),
            PixelRect {
                x0: 2,
                y0: 0,
                x1: 9,
                y1: 4
            }
        );
        // An empty rectangle anywhere adds nothing.
        let empty_far_away = PixelRect {
            x0: 100,
            y0: 100,
            x1: 100,
            y1: 140,
        };
        assert!(empty_far_away.is_empty());
        assert_eq!(a.union(empty_far_away), a);
        assert_eq!(PixelRect::EMPTY.union(b), b);
        assert_eq!((a.width(), a.height(), a.pixels()), (3, 1, 3));
        assert_eq!(PixelRect::full(640, 480).pixels(), 640 * 480);
        assert!(a.contains(2, 3) && !a.contains(5, 3) && !a.contains(2, 4));
    }

    #[test]
    fn growing_stays_inside_the_image_and_keeps_empty_rectangles_empty() {
        let rect = PixelRect {
            x0: 2,
            y0: 10,
            x1: 20,
            y1: 30,
        };
        assert_eq!(
            rect.grown(4, 22, 100),
            PixelRect {
                x0: 0,
                y0: 6,
                x1: 22,
                y1: 34
            }
        );
        assert!(PixelRect::EMPTY.grown(4, 22, 100).is_empty());
    }

    #[test]
    fn coverage_counts_the_pixels_of_the_cells_rectangles_touch() {
        let mut coverage = PixelCoverage::new(200, 100);
        assert_eq!(coverage.pixels(), 0);
        // Two cells in the first row, one of them marked twice.
        coverage.add(PixelRect {
            x0: 10,
            y0: 10,
            x1: 70,
            y1: 20,
        });
        coverage.add(PixelRect {
            x0: 65,
            y0: 0,
            x1: 66,
            y1: 1,
        });
        assert_eq!(coverage.pixels(), 2 * 64 * 64);
        // The clipped cells at the image's right and bottom edges hold fewer pixels.
        coverage.add(PixelRect {
            x0: 199,
            y0: 99,
            x1: 200,
            y1: 100,
        });
        assert_eq!(coverage.pixels(), 2 * 64 * 64 + 8 * 36);
        assert_eq!(
            coverage.union(),
            PixelRect {
                x0: 10,
                y0: 0,
                x1: 200,
                y1: 100
            }
        );
    }
}

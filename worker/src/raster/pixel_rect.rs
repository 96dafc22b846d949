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

    #[cfg(test)]
    pub fn contains(&self, x: u32, y: u32) -> bool {
        (self.x0..self.x1).contains(&x) && (self.y0..self.y1).contains(&y)
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
}

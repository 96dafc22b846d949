//! How well a rendered frame shows its subject, from the image alone: how much of the frame the
//! subject spans and where, and how much of its silhouette is actually lit by points.
//!
//! A pixel is *drawn* when its RGBA differs from the background color; the renderer writes the
//! background exactly wherever no point landed, so equality is the test. The *subject's box* is
//! the bounding box of the drawn pixels. The *silhouette* is the drawn mask closed
//! morphologically with a disc of radius [`closing_radius`] (1% of the image height), then with
//! its interior holes filled (background not connected to the image's border). The *lit share*
//! is drawn pixels over silhouette pixels: 1 for a closed surface, low for sparse points with
//! the background showing between them. `deploy/gallery-figures.sh` prints these per file.

use image::RgbaImage;

/// A binary image, row-major.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Mask {
    pub width: u32,
    pub height: u32,
    pub bits: Vec<bool>,
}

impl Mask {
    pub fn new(width: u32, height: u32) -> Mask {
        Mask {
            width,
            height,
            bits: vec![false; width as usize * height as usize],
        }
    }

    /// The pixels of `image` that are not exactly `background`.
    pub fn drawn(image: &RgbaImage, background: [u8; 4]) -> Mask {
        let bits = image.pixels().map(|p| p.0 != background).collect();
        Mask {
            width: image.width(),
            height: image.height(),
            bits,
        }
    }

    pub fn get(&self, x: u32, y: u32) -> bool {
        self.bits[y as usize * self.width as usize + x as usize]
    }

    pub fn set(&mut self, x: u32, y: u32, value: bool) {
        self.bits[y as usize * self.width as usize + x as usize] = value;
    }

    pub fn count(&self) -> u64 {
        self.bits.iter().filter(|&&b| b).count() as u64
    }

    /// Inclusive pixel bounds of the set pixels, `None` when none is set.
    pub fn bounds(&self) -> Option<PixelBox> {
        let mut found: Option<PixelBox> = None;
        for y in 0..self.height {
            for x in 0..self.width {
                if self.get(x, y) {
                    let b = found.get_or_insert(PixelBox {
                        x0: x,
                        y0: y,
                        x1: x,
                        y1: y,
                    });
                    b.x0 = b.x0.min(x);
                    b.x1 = b.x1.max(x);
                    b.y1 = y;
                }
            }
        }
        found
    }
}

/// Inclusive pixel bounds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelBox {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

/// The radius of the closing disc for an image `height` pixels high: 1% of it, at least 1.
pub fn closing_radius(height: u32) -> u32 {
    ((f64::from(height) / 100.0).round() as u32).max(1)
}

/// Half-widths of a disc of `radius` row by row, from `-radius` to `radius`.
fn disc_rows(radius: u32) -> Vec<(i64, i64)> {
    let r = i64::from(radius);
    (-r..=r)
        .map(|dy| {
            let half = ((r * r - dy * dy) as f64).sqrt().floor() as i64;
            (dy, half)
        })
        .collect()
}

/// Per-row prefix sums of set pixels, each row `width + 1` long.
fn row_prefix_sums(mask: &Mask) -> Vec<u32> {
    let w = mask.width as usize;
    let mut sums = vec![0u32; (w + 1) * mask.height as usize];
    for y in 0..mask.height as usize {
        let row = &mut sums[y * (w + 1)..(y + 1) * (w + 1)];
        for x in 0..w {
            row[x + 1] = row[x] + u32::from(mask.bits[y * w + x]);
        }
    }
    sums
}

/// Dilation (`erode == false`) or erosion with a disc. Outside the mask counts as unset.
fn morph(mask: &Mask, radius: u32, erode: bool) -> Mask {
    let (w, h) = (i64::from(mask.width), i64::from(mask.height));
    let sums = row_prefix_sums(mask);
    let rows = disc_rows(radius);
    let mut out = Mask::new(mask.width, mask.height);
    for y in 0..h {
        for x in 0..w {
            let mut any = false;
            let mut all = true;
            for &(dy, half) in &rows {
                let yy = y + dy;
                let (xa, xb) = (x - half, x + half);
                if yy < 0 || yy >= h || xa < 0 || xb >= w {
                    all = false;
                }
                if yy < 0 || yy >= h {
                    continue;
                }
                let (ca, cb) = (xa.clamp(0, w), (xb + 1).clamp(0, w));
                let base = (yy * (w + 1)) as usize;
                let set = sums[base + cb as usize] - sums[base + ca as usize];
                any |= set > 0;
                all &= i64::from(set) == cb - ca;
            }
            out.set(x as u32, y as u32, if erode { all } else { any });
        }
    }
    out
}

/// Morphological closing with a disc of `radius`, computed on a canvas padded by the radius so
/// that a subject touching the frame's edge is not eaten there.
pub fn close(mask: &Mask, radius: u32) -> Mask {
    let mut padded = Mask::new(mask.width + 2 * radius, mask.height + 2 * radius);
    for y in 0..mask.height {
        for x in 0..mask.width {
            padded.set(x + radius, y + radius, mask.get(x, y));
        }
    }
    let closed = morph(&morph(&padded, radius, false), radius, true);
    let mut out = Mask::new(mask.width, mask.height);
    for y in 0..mask.height {
        for x in 0..mask.width {
            out.set(x, y, closed.get(x + radius, y + radius));
        }
    }
    out
}

/// Sets every unset pixel not 4-connected through unset pixels to the image's border.
pub fn fill_holes(mask: &Mask) -> Mask {
    let (w, h) = (mask.width, mask.height);
    let mut outside = Mask::new(w, h);
    let mut stack = Vec::new();
    for y in 0..h {
        for x in 0..w {
            if (x == 0 || y == 0 || x + 1 == w || y + 1 == h) && !mask.get(x, y) {
                outside.set(x, y, true);
                stack.push((x, y));
            }
        }
    }
    while let Some((x, y)) = stack.pop() {
        let neighbours = [
            (x.wrapping_sub(1), y),
            (x + 1, y),
            (x, y.wrapping_sub(1)),
            (x, y + 1),
        ];
        for (nx, ny) in neighbours {
            if nx < w && ny < h && !mask.get(nx, ny) && !outside.get(nx, ny) {
                outside.set(nx, ny, true);
                stack.push((nx, ny));
            }
        }
    }
    let bits = outside.bits.iter().map(|&o| !o).collect();
    Mask {
        width: w,
        height: h,
        bits,
    }
}

/// The silhouette of a drawn mask: closed with a disc of `radius`, interior holes filled.
pub fn silhouette(drawn: &Mask, radius: u32) -> Mask {
    fill_holes(&close(drawn, radius))
}

/// A frame's figures.
#[derive(Debug, Clone, PartialEq)]
pub struct Figures {
    pub width: u32,
    pub height: u32,
    /// Pixels that differ from the background.
    pub drawn: u64,
    pub silhouette: u64,
    pub closing_radius: u32,
    /// The subject's box, `None` for an empty frame.
    pub bounds: Option<PixelBox>,
}

impl Figures {
    /// The subject's box as fractions of the frame's width and height.
    pub fn span(&self) -> Option<(f64, f64)> {
        self.bounds.map(|b| {
            (
                f64::from(b.x1 - b.x0 + 1) / f64::from(self.width),
                f64::from(b.y1 - b.y0 + 1) / f64::from(self.height),
            )
        })
    }

    /// The centre of the subject's box as fractions of the frame's width and height, from the
    /// top left; (0.5, 0.5) is centred.
    pub fn centre(&self) -> Option<(f64, f64)> {
        self.bounds.map(|b| {
            (
                f64::from(b.x0 + b.x1 + 1) / 2.0 / f64::from(self.width),
                f64::from(b.y0 + b.y1 + 1) / 2.0 / f64::from(self.height),
            )
        })
    }

    /// Drawn pixels over silhouette pixels, `None` for an empty frame.
    pub fn lit_share(&self) -> Option<f64> {
        (self.silhouette > 0).then(|| self.drawn as f64 / self.silhouette as f64)
    }
}

/// The figures of a rendered frame whose background is `background`.
pub fn frame_figures(image: &RgbaImage, background: [u8; 4]) -> Figures {
    let drawn = Mask::drawn(image, background);
    let radius = closing_radius(image.height());
    let silhouette = silhouette(&drawn, radius);
    Figures {
        width: image.width(),
        height: image.height(),
        drawn: drawn.count(),
        silhouette: silhouette.count(),
        closing_radius: radius,
        bounds: drawn.bounds(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Rgba;

    const BG: [u8; 4] = [24, 24, 28, 255];

    /// A 200x100 frame: a ring of dots every 3 pixels (x 40..=99, y 20..=79) with a 20x20
    /// empty hole in its middle, and one pixel that is almost but not exactly background.
    fn synthetic() -> RgbaImage {
        let mut image = RgbaImage::from_pixel(200, 100, Rgba(BG));
        for y in (20..80).step_by(3) {
            for x in (40..100).step_by(3) {
                let in_hole = (60..80).contains(&x) && (40..60).contains(&y);
                if !in_hole {
                    image.put_pixel(x, y, Rgba([200, 180, 160, 255]));
                }
            }
        }
        image.put_pixel(99, 79, Rgba([24, 24, 29, 255]));
        image
    }

    #[test]
    fn box_span_and_centre() {
        let f = frame_figures(&synthetic(), BG);
        assert_eq!(
            f.bounds,
            Some(PixelBox {
                x0: 40,
                y0: 20,
                x1: 99,
                y1: 79
            })
        );
        let (sw, sh) = f.span().expect("a subject");
        assert!((sw - 60.0 / 200.0).abs() < 1e-12 && (sh - 60.0 / 100.0).abs() < 1e-12);
        let (cx, cy) = f.centre().expect("a subject");
        assert!((cx - 70.0 / 200.0).abs() < 1e-12 && (cy - 0.5).abs() < 1e-12);
    }

    #[test]
    fn silhouette_closes_gaps_and_fills_the_hole() {
        let image = synthetic();
        let drawn = Mask::drawn(&image, BG);
        assert_eq!(closing_radius(100), 1);
        // Radius 1 cannot bridge 2-pixel gaps: the silhouette is the dots themselves.
        assert_eq!(silhouette(&drawn, 1).count(), drawn.count());
        // Radius 2 bridges them, and the 20x20 hole is filled.
        let s = silhouette(&drawn, 2);
        assert!(drawn.bits.iter().zip(&s.bits).all(|(&d, &s)| !d || s));
        assert!(s.get(70, 50) && s.get(41, 21) && s.get(42, 22) && !s.get(30, 50));
        assert!(
            (56 * 56..=60 * 60).contains(&s.count()),
            "silhouette {}",
            s.count()
        );
    }

    #[test]
    fn lit_share_of_a_rectangle_with_gaps_and_a_hole() {
        // 30x20 solid but for 1-pixel gaps along row 15 (14 pixels) and a 6x6 hole.
        let mut image = RgbaImage::from_pixel(64, 48, Rgba(BG));
        for y in 10..30 {
            for x in 10..40 {
                let gap = y == 15 && x % 2 == 1 && x < 38;
                let hole = (20..26).contains(&x) && (18..24).contains(&y);
                if !gap && !hole {
                    image.put_pixel(x, y, Rgba([90, 90, 90, 255]));
                }
            }
        }
        let drawn = Mask::drawn(&image, BG);
        assert_eq!(drawn.count(), 600 - 36 - 14);
        assert_eq!(silhouette(&drawn, 1).count(), 600);
        let f = frame_figures(&image, BG);
        assert_eq!((f.closing_radius, f.drawn, f.silhouette), (1, 550, 600));
        assert!((f.lit_share().expect("a subject") - 550.0 / 600.0).abs() < 1e-12);
    }

    #[test]
    fn closing_keeps_a_subject_cut_by_the_frame() {
        let mut drawn = Mask::new(20, 10);
        for y in 0..10 {
            for x in 0..5 {
                drawn.set(x, y, true);
            }
        }
        assert_eq!(close(&drawn, 3), drawn);
    }

    #[test]
    fn empty_frame() {
        let f = frame_figures(&RgbaImage::from_pixel(64, 36, Rgba(BG)), BG);
        assert_eq!(
            (f.drawn, f.silhouette, f.bounds, f.lit_share()),
            (0, 0, None, None)
        );
    }
}

//! Exposure after Eye-Dome Lighting: the shading darkens depth edges, and on noisy or
//! vegetated scans it darkens most pixels a little, which dims the whole picture. The EDL
//! pass counts the luma of every surface pixel before and after shading
//! (`shaders/edl.wgsl`); a gain brings the shaded median back to the unshaded one, so edges
//! stay darker than their surroundings and the picture keeps its brightness
//! (docs/perf/edl-exposure.md). A frame's settings may instead hold a gain measured on
//! another frame ([`Exposure::Held`](super::Exposure::Held)), so that the frames of a job share
//! one; a frame reports the gain it applied. The GPU and the CPU reference share this code.

use std::ops::RangeInclusive;

use image::RgbaImage;

/// Luma bins per histogram: one per 8-bit level.
pub const LUMA_BINS: usize = 256;

/// The largest gain: a frame shaded almost black is not stretched into noise.
pub const MAX_GAIN: f32 = 4.0;

/// The gains a frame is exposed with, measured or held: at least 1, since the shading never
/// brightens.
pub const GAIN_RANGE: RangeInclusive<f32> = 1.0..=MAX_GAIN;

/// The luma of an RGB pixel, 0 to 255, as the shader bins it (Rec. 709 weights).
pub fn luma_bin(r: u8, g: u8, b: u8) -> usize {
    let luma = 0.2126 * f32::from(r) + 0.7152 * f32::from(g) + 0.0722 * f32::from(b);
    (luma as usize).min(LUMA_BINS - 1)
}

/// Surface pixels counted by luma, before and after shading.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LumaHistograms {
    pub before: [u32; LUMA_BINS],
    pub after: [u32; LUMA_BINS],
}

impl Default for LumaHistograms {
    fn default() -> Self {
        Self {
            before: [0; LUMA_BINS],
            after: [0; LUMA_BINS],
        }
    }
}

impl LumaHistograms {
    /// The histograms as the shader leaves them: `before` then `after`, one word a bin.
    pub fn from_words(words: &[u32]) -> Option<Self> {
        let (before, after) = words.get(..2 * LUMA_BINS)?.split_at(LUMA_BINS);
        Some(Self {
            before: before.try_into().ok()?,
            after: after.try_into().ok()?,
        })
    }

    /// Counts one surface pixel's color before and after shading.
    pub fn count(&mut self, before: [u8; 3], after: [u8; 3]) {
        self.before[luma_bin(before[0], before[1], before[2])] += 1;
        self.after[luma_bin(after[0], after[1], after[2])] += 1;
    }

    /// The gain that brings the shaded median luma back to the unshaded one, within
    /// [`GAIN_RANGE`]; 1 for a frame without surface.
    pub fn gain(&self) -> f32 {
        match (median_bin(&self.before), median_bin(&self.after)) {
            (Some(before), Some(after)) => {
                // Half a level up on both sides: bins hold the levels from their lower edge.
                ((before as f32 + 0.5) / (after as f32 + 0.5))
                    .clamp(*GAIN_RANGE.start(), *GAIN_RANGE.end())
            }
            _ => 1.0,
        }
    }
}

/// The bin holding the median of a histogram; `None` when it is empty.
fn median_bin(histogram: &[u32; LUMA_BINS]) -> Option<usize> {
    let total: u64 = histogram.iter().map(|&count| u64::from(count)).sum();
    if total == 0 {
        return None;
    }
    let half = total.div_ceil(2);
    let mut seen = 0u64;
    histogram.iter().position(|&count| {
        seen += u64::from(count);
        seen >= half
    })
}

/// Multiplies the color of every surface pixel (finite `depth`) by `gain`, saturating.
pub fn expose(image: &mut RgbaImage, depth: &[f32], gain: f32) {
    if gain == 1.0 {
        return;
    }
    for (pixel, depth) in image.pixels_mut().zip(depth) {
        if depth.is_finite() {
            for channel in &mut pixel.0[..3] {
                *channel = (f32::from(*channel) * gain).round().min(255.0) as u8;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_gain_brings_the_shaded_median_back_within_its_bounds() {
        let mut histograms = LumaHistograms::default();
        for level in 0..100u8 {
            histograms.count([level + 100; 3], [(level + 100) / 2; 3]);
        }
        let gain = histograms.gain();
        assert!((gain - 149.5 / 74.5).abs() < 1e-5, "{gain}");

        let mut brighter = LumaHistograms::default();
        brighter.count([10; 3], [200; 3]);
        assert_eq!(brighter.gain(), 1.0, "shading never brightens");
        let mut black = LumaHistograms::default();
        black.count([200; 3], [0; 3]);
        assert_eq!(black.gain(), MAX_GAIN);
        assert_eq!(LumaHistograms::default().gain(), 1.0, "no surface");
    }

    #[test]
    fn exposure_brightens_surface_pixels_only_and_saturates() {
        let mut image = RgbaImage::from_raw(
            3,
            1,
            vec![100, 50, 10, 255, 200, 200, 200, 255, 24, 24, 28, 255],
        )
        .expect("image");
        expose(&mut image, &[1.0, 2.0, f32::INFINITY], 2.0);
        assert_eq!(image.get_pixel(0, 0).0, [200, 100, 20, 255]);
        assert_eq!(image.get_pixel(1, 0).0, [255, 255, 255, 255]);
        assert_eq!(
            image.get_pixel(2, 0).0,
            [24, 24, 28, 255],
            "background untouched"
        );
    }

    #[test]
    fn histograms_read_from_the_shaders_words() {
        let mut words = vec![0u32; 2 * LUMA_BINS];
        words[3] = 7;
        words[LUMA_BINS + 1] = 7;
        let histograms = LumaHistograms::from_words(&words).expect("512 words");
        assert_eq!((histograms.before[3], histograms.after[1]), (7, 7));
        assert!(LumaHistograms::from_words(&words[..10]).is_none());
    }
}

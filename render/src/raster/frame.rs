//! A rendered frame: its pixels, its depth image when asked for, and the timings of its
//! stages. Encoding it is `crate::encode`'s job.

use image::RgbaImage;

use super::{AtomicsPath, StageTimings};

#[derive(Debug, Clone)]
pub struct Frame {
    pub image: RgbaImage,
    /// Linear depth per pixel, row-major; +infinity where no point landed. Present when
    /// [`FrameSettings::read_depth`](super::FrameSettings::read_depth) was set.
    pub depth: Option<Vec<f32>>,
    pub timings: StageTimings,
    pub atomics: AtomicsPath,
    /// The gain the frame was exposed with after Eye-Dome Lighting, measured or held: a
    /// caller holds it for the frames that follow. `None` when the frame is not shaded
    /// with EDL.
    pub gain: Option<f32>,
}

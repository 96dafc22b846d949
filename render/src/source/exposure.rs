//! One exposure per job. The gain after Eye-Dome Lighting (`raster::exposure`) measured per
//! frame follows what each frame sees, so a turntable's brightness drifts as it turns and
//! two workers' frames of a job differ by their own gains. A job's gain is instead the one
//! measured on its first frame (index 0 of its camera path) at the final quality, and every
//! frame of the job is exposed with it held (docs/perf/edl-exposure.md):
//!
//! - [`FrameSource::render`] holds the gain of the first final frame it renders of a view and
//!   exposes the view's later frames with it: a sequence rendered in order from frame 0 (a
//!   local turntable or keyframe path) gets frame 0's gain without its caller knowing.
//! - [`FrameSource::render_job_frame`] renders frame `index` of a request with the job's gain
//!   whatever frame comes first: the caller's when it holds it, else frame 0's, measured on
//!   frame 0 rendered first (its image discarded) when `index` is not 0. A worker keeps the
//!   gain per job, so it renders at most one extra frame per job, and every worker exposes a
//!   job's frames as a local render of the job does.
//!
//! Previews (a partial sample while a store builds, or coarse cuts) measure each frame's own
//! gain: their points are not the final frames', and they are replaced by those.

use super::{FrameSource, SourceError, SourceEvent, SourceFrame};
use crate::color::Coloring;
use crate::filter::PointFilter;
use crate::raster::{Exposure, FrameSettings, Shading};
use crate::request::RenderRequest;

/// What decides a frame's pixels but its camera and what follows from it (a path may turn
/// and zoom, and adaptive points are sized by the focal length): the frames of one view share
/// a gain.
#[derive(Debug, Clone, PartialEq)]
struct View {
    /// The frame's settings with its exposure and depth readback left out.
    settings: FrameSettings,
    coloring: Coloring,
    filter: PointFilter,
    /// A cut's pixel error; `None` for a resident cloud.
    lod_error: Option<f64>,
}

impl View {
    /// Whether a frame of `other` is of this view: all but the cameras and point sizes are
    /// the same.
    fn holds(&self, other: &View) -> bool {
        let camera_aside = View {
            settings: FrameSettings {
                camera: self.settings.camera,
                point_size: self.settings.point_size,
                adaptive_size: self.settings.adaptive_size,
                ..other.settings
            },
            ..other.clone()
        };
        *self == camera_aside
    }
}

/// The gain a frame source holds for the view it renders.
#[derive(Debug, Default, Clone)]
pub struct HeldExposure(Option<(View, f32)>);

impl FrameSource {
    /// The gain this source holds, for another source of the same frames (the next stage of
    /// a store built camera first) to expose its frames with.
    pub fn held_exposure(&self) -> HeldExposure {
        self.exposure.clone()
    }

    /// Holds `held`, another source's gain of the same frames, unless this one holds its own.
    pub fn hold_exposure_of(&mut self, held: HeldExposure) {
        if self.exposure.0.is_none() {
            self.exposure = held;
        }
    }
}

impl FrameSource {
    /// The view of a frame of `settings` from this source; `None` when the frame measures its
    /// own gain: it is not shaded with EDL, it holds a gain already, or it is a preview's.
    fn exposure_view(&self, settings: &FrameSettings) -> Option<View> {
        let Shading::Edl { .. } = settings.shading else {
            return None;
        };
        if settings.exposure != Exposure::Measured || self.is_preview() {
            return None;
        }
        Some(View {
            settings: FrameSettings {
                read_depth: false,
                ..*settings
            },
            coloring: self.coloring,
            filter: self.filter,
            lod_error: self.lod_error(),
        })
    }

    /// `settings` with the gain this source holds for their view, when it holds one; else as
    /// they are.
    pub(super) fn with_held_exposure(&self, settings: &FrameSettings) -> FrameSettings {
        match (&self.exposure.0, self.exposure_view(settings)) {
            (Some((held, gain)), Some(view)) if held.holds(&view) => FrameSettings {
                exposure: Exposure::Held(*gain),
                ..*settings
            },
            _ => *settings,
        }
    }

    /// Holds the gain `rendered` measured for the frames of its view that follow, when it is
    /// a final EDL frame that measured its own.
    pub(super) fn hold_exposure(&mut self, settings: &FrameSettings, rendered: &SourceFrame) {
        if let (Some(view), Some(gain)) = (self.exposure_view(settings), rendered.frame.gain) {
            tracing::debug!(gain, "exposure held for the frames of this view");
            self.exposure.0 = Some((view, gain));
        }
    }

    /// Renders frame `index` of `request` with its job's gain: `gain` when the caller holds
    /// it, else the one measured on frame 0 (this frame, or frame 0 rendered first and its
    /// image discarded). The frame's [`gain`](crate::raster::Frame::gain) is the job's, for
    /// the caller to hold for the job's other frames; a preview's is its own.
    pub fn render_job_frame(
        &mut self,
        request: &RenderRequest,
        index: u32,
        gain: Option<f32>,
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<SourceFrame, SourceError> {
        let settings = self.frame_settings(request, index);
        if self.exposure_view(&settings).is_none() {
            return self.draw(&settings, events);
        }
        let gain = match gain {
            Some(gain) => gain,
            None if index == 0 => return self.draw(&settings, events),
            None => {
                let first = self.draw(&self.frame_settings(request, 0), events)?;
                // What opening the source took is reported with the frame the caller keeps.
                self.unreported = first.opened;
                // Every EDL frame reports its gain; were one not to, this frame measures its own.
                let Some(gain) = first.frame.gain else {
                    return self.draw(&settings, events);
                };
                tracing::debug!(gain, index, "the job's exposure measured on its frame 0");
                gain
            }
        };
        let held = FrameSettings {
            exposure: Exposure::Held(gain),
            ..settings
        };
        self.draw(&held, events)
    }
}

#[cfg(test)]
#[path = "exposure_tests.rs"]
mod tests;

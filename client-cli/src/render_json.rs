//! The JSON of `render --json`: a local render's object per frame, and the camera that it and
//! the depth sidecars (`FRAME.depth.json`) report, which no API message describes, are the
//! CLI's own objects with the lowerCamelCase keys of the API's JSON mapping; a render through
//! a server reports each frame as the API's `FrameFinished`, beside the file it was written to.

use std::path::Path;

use pointfarm_bench::json::camel_case_keys;
use pointfarm_proto::v1 as pb;
use pointfarm_render::camera::{Camera, Projection};
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::cut::CutReport;
use pointfarm_render::raster::FrameSettings;
use serde::Serialize;

use pointfarm_render::source::SourceFrame;

/// One frame as `render --json` reports it: its file and size, the points the point passes
/// read after culling, each stage's milliseconds, the camera, the dataset's bounds and, for a
/// frame from a level-of-detail store, its cut.
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
pub struct FrameJson {
    pub frame: u32,
    pub path: String,
    pub width: u32,
    pub height: u32,
    pub points_total: u64,
    pub points_rendered: u64,
    /// Whether the frame is a preview of the files' chunk starts, drawn while their levels of
    /// detail build (`render --preview`); a final frame follows it.
    pub preview: bool,
    /// How complete the data drawn was: `pointsRendered / pointsTotal`, the points of the
    /// files.
    pub completeness: f64,
    /// Milliseconds by stage name (`upload`, `rasterize`, ...).
    pub timings_ms: serde_json::Map<String, serde_json::Value>,
    /// The side of a point's square in pixels; with adaptive sizes, the largest.
    pub point_size: u32,
    pub adaptive_point_size: bool,
    pub camera: CameraJson,
    pub bounds: BoundsJson,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cut: Option<serde_json::Value>,
}

impl FrameJson {
    pub fn new(
        index: u32,
        path: &Path,
        settings: &FrameSettings,
        bounds: &WorldBounds,
        rendered: &SourceFrame,
    ) -> Self {
        Self {
            frame: index,
            path: path.display().to_string(),
            width: settings.width,
            height: settings.height,
            points_total: rendered.points_total,
            points_rendered: rendered.points_rendered,
            preview: rendered.preview.is_some(),
            completeness: pointfarm_render::cut::completeness(
                rendered.points_rendered,
                rendered.points_total,
            ),
            timings_ms: rendered
                .frame
                .timings
                .stages
                .iter()
                .map(|t| (t.stage.name().to_string(), serde_json::json!(t.ms)))
                .collect(),
            point_size: settings.point_size,
            adaptive_point_size: settings.adaptive_size.is_some(),
            camera: CameraJson::of(&settings.camera),
            bounds: BoundsJson {
                min: bounds.min.to_array(),
                max: bounds.max.to_array(),
            },
            cut: rendered.cut.as_ref().map(cut_json),
        }
    }
}

/// One frame of `render --server --json`: its file, as a local render reports it, and the
/// frame as the API reports it (its stage timings and, from levels of detail, its cut).
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
pub struct ServerFrameJson<'a> {
    pub frame: u32,
    pub path: String,
    pub job_id: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub finished: Option<&'a pb::FrameFinished>,
}

impl<'a> ServerFrameJson<'a> {
    /// Frame `index` of `job`, written to `path`.
    pub fn new(index: u32, path: &Path, job: &'a pb::Job) -> Self {
        Self {
            frame: index,
            path: path.display().to_string(),
            job_id: &job.id,
            finished: job.frames.iter().find(|f| f.index == index),
        }
    }

    /// `frame` of job `job_id`, as reported while the job runs, written to `path`.
    pub fn of_frame(path: &Path, job_id: &'a str, frame: &'a pb::FrameFinished) -> Self {
        Self {
            frame: frame.index,
            path: path.display().to_string(),
            job_id,
            finished: Some(frame),
        }
    }
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
pub struct BoundsJson {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

/// A camera in the file's coordinates.
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
pub struct CameraJson {
    pub position: [f64; 3],
    pub target: [f64; 3],
    pub up: [f64; 3],
    pub near: f64,
    pub far: f64,
    /// `{"perspective": {"fovYDeg": ...}}` or `{"orthographic": {"height": ...}}`.
    pub projection: ProjectionJson,
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase", rename_all_fields = "camelCase")]
pub enum ProjectionJson {
    Perspective { fov_y_deg: f64 },
    Orthographic { height: f64 },
}

impl CameraJson {
    pub fn of(camera: &Camera) -> Self {
        Self {
            position: camera.position.to_array(),
            target: camera.target.to_array(),
            up: camera.up.to_array(),
            near: camera.near,
            far: camera.far,
            projection: match camera.projection {
                Projection::Perspective { fov_y_deg } => ProjectionJson::Perspective { fov_y_deg },
                Projection::Orthographic { height } => ProjectionJson::Orthographic { height },
            },
        }
    }
}

/// What a frame's cut drew and loaded: the render crate's `CutReport` as it encodes itself,
/// every field, with its keys in lowerCamelCase.
pub fn cut_json(report: &CutReport) -> serde_json::Value {
    camel_case_keys(serde_json::to_value(report).unwrap_or_default())
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::*;

    #[test]
    fn cameras_and_cuts_have_lower_camel_case_keys() {
        let camera = Camera {
            position: DVec3::new(1.0, 2.0, 3.0),
            target: DVec3::ZERO,
            up: DVec3::Z,
            projection: Projection::Perspective { fov_y_deg: 45.0 },
            near: 0.5,
            far: 100.0,
        };
        let json = serde_json::to_value(CameraJson::of(&camera)).expect("encodes");
        assert_eq!(json["projection"]["perspective"]["fovYDeg"], 45.0, "{json}");
        let cut = cut_json(&CutReport::default());
        for key in [
            "pointsRendered",
            "limitedByBudget",
            "readAheadBytes",
            "selectMs",
        ] {
            assert!(cut.get(key).is_some(), "{key} missing from {cut}");
        }
    }
}

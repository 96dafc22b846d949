//! Camera animations from a Potree project (`potree.json5`, what Potree's "save project"
//! writes, or its JSON): the control points of an animation become a keyframed camera path
//! in the same world coordinates, its duration the frame count at the render's frame rate.
//!
//! ```json5
//! {type: 'Potree', settings: {fov: 60},
//!  cameraAnimations: [{name: 'flight', duration: 5, curveType: 'centripetal',
//!    controlPoints: [{position: [x, y, z], target: [x, y, z]}, ...]}]}
//! ```

use anyhow::{bail, Result};
use pointfarm_render::request::{CameraPath, Interpolation, Keyframe, Point3, DEFAULT_UP};
use serde::Deserialize;

/// Potree's default vertical field of view, for projects that do not save theirs.
const POTREE_DEFAULT_FOV_Y_DEG: f64 = 60.0;

#[derive(Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct PotreeProject {
    #[serde(default)]
    settings: Settings,
    #[serde(default)]
    camera_animations: Vec<Animation>,
}

#[derive(Deserialize, Default)]
struct Settings {
    fov: Option<f64>,
}

#[derive(Deserialize)]
#[serde(rename_all = "camelCase")]
struct Animation {
    #[serde(default)]
    name: String,
    duration: f64,
    control_points: Vec<ControlPoint>,
}

#[derive(Deserialize)]
struct ControlPoint {
    position: [f64; 3],
    target: [f64; 3],
}

impl PotreeProject {
    /// Whether a JSON document is a Potree project rather than a camera path file.
    pub fn is_one(document: &serde_json::Value) -> bool {
        document.get("type").and_then(|t| t.as_str()) == Some("Potree")
            || document.get("cameraAnimations").is_some()
    }

    /// The project's first camera animation as a path of `fps` frames a second (Potree's
    /// curves through the control points are Catmull-Rom splines, as pointfarm's).
    pub fn camera_path(self, fps: u32) -> Result<(CameraPath, String)> {
        if fps == 0 {
            bail!("--fps must be at least 1 to time a Potree animation");
        }
        let count = self.camera_animations.len();
        let Some(animation) = self.camera_animations.into_iter().next() else {
            bail!("the Potree project has no camera animation");
        };
        if !(animation.duration.is_finite() && animation.duration > 0.0) {
            bail!(
                "the Potree animation '{}' has a duration of {} s; it must be positive",
                animation.name,
                animation.duration
            );
        }
        let frames = (animation.duration * f64::from(fps)).round().max(1.0);
        if frames > f64::from(u32::MAX) {
            bail!("the Potree animation '{}' is too long", animation.name);
        }
        let fov_y_deg = self.settings.fov.unwrap_or(POTREE_DEFAULT_FOV_Y_DEG);
        let point = |[x, y, z]: [f64; 3]| Point3 { x, y, z };
        let keyframes: Vec<Keyframe> = animation
            .control_points
            .iter()
            .map(|c| Keyframe {
                position: point(c.position),
                target: point(c.target),
                up: DEFAULT_UP,
                fov_y_deg,
            })
            .collect();
        let mut words = format!(
            "Potree animation '{}': {} control points, {} s at {fps} frames a second",
            animation.name,
            keyframes.len(),
            animation.duration
        );
        if count > 1 {
            words.push_str(&format!(" (the first of {count} in the project)"));
        }
        let path = CameraPath::Keyframes {
            keyframes,
            frames: frames as u32,
            interpolation: Interpolation::Spline,
        };
        Ok((path, words))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A project as Potree 1.8's "save project" writes it (JSON5), trimmed.
    const SAVED: &str = r#"{
	type: 'Potree',
	version: 1.7,
	settings: {
		pointBudget: 1000000,
		fov: 55,
		edlEnabled: true,
	},
	view: {position: [637100.1, 849400.2, 650], target: [636600, 849200, 450]},
	pointclouds: [],
	cameraAnimations: [
		{
			uuid: '5C1D0C8E-8E9B-4F5B-9C63-0A4E55C1C0D2',
			name: 'flight',
			duration: 4,
			t: 0,
			curveType: 'centripetal',
			visible: true,
			controlPoints: [
				{position: [636200, 848900, 700], target: [636600, 849200, 450]},
				{position: [636700, 848800, 680], target: [636600, 849200, 450]},
				{position: [637100, 849400, 650], target: [636600, 849200, 450]},
			],
		},
		{name: 'second', duration: 2, controlPoints: []},
	],
}"#;

    #[test]
    fn a_saved_project_gives_its_first_animation() {
        let document: serde_json::Value = json5::from_str(SAVED).expect("json5");
        assert!(PotreeProject::is_one(&document));
        let project: PotreeProject = serde_json::from_value(document).expect("project");
        let (path, words) = project.camera_path(24).expect("a path");
        assert!(
            words.contains("'flight': 3 control points, 4 s at 24"),
            "{words}"
        );
        assert!(words.contains("the first of 2"), "{words}");
        let CameraPath::Keyframes {
            keyframes,
            frames,
            interpolation,
        } = path
        else {
            panic!("keyframes")
        };
        assert_eq!((frames, interpolation), (96, Interpolation::Spline));
        assert_eq!(keyframes.len(), 3);
        assert_eq!(keyframes[1].position.x, 636700.0);
        assert_eq!(keyframes[2].target.y, 849200.0);
        assert!(keyframes
            .iter()
            .all(|k| k.fov_y_deg == 55.0 && k.up == DEFAULT_UP));
    }

    #[test]
    fn a_project_without_a_usable_animation_is_refused() {
        for (text, says) in [
            ("{type: 'Potree'}", "has no camera animation"),
            (
                "{cameraAnimations: [{name: 'a', duration: 0, controlPoints: []}]}",
                "must be positive",
            ),
        ] {
            let document: serde_json::Value = json5::from_str(text).expect("json5");
            let project: PotreeProject = serde_json::from_value(document).expect("project");
            let error = project.camera_path(30).expect_err("refused").to_string();
            assert!(error.contains(says), "{error}");
        }
    }
}

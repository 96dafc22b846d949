//! `render --camera-path FILE`: a keyframed camera path written as JSON or TOML, the same path
//! the API's `CameraPath.keyframes` carries, or the first camera animation of a Potree project
//! (`potree.json5`, what Potree's "save project" writes, or its JSON), whose control points
//! become a keyframed path in the same world coordinates and whose duration becomes the frame
//! count at the render's frame rate.
//!
//! ```toml
//! frames = 120
//! interpolation = "spline"   # or "linear"
//!
//! [[keyframes]]
//! position = [636200.0, 848900.0, 700.0]
//! target = [636600.0, 849200.0, 450.0]
//! # up = [0, 0, 1], fov_y_deg = 50: optional
//! ```
//!
//! ```json5
//! {type: 'Potree', settings: {fov: 60},
//!  cameraAnimations: [{name: 'flight', duration: 5, curveType: 'centripetal',
//!    controlPoints: [{position: [x, y, z], target: [x, y, z]}, ...]}]}
//! ```

use std::path::Path;

use anyhow::{bail, Context, Result};
use pointfarm_render::camera::DEFAULT_FOV_Y_DEG;
use pointfarm_render::request::{CameraPath, Interpolation, Keyframe, Point3, DEFAULT_UP};
use serde::Deserialize;

/// The largest camera-path file read: a path of many thousand keyframes is far smaller.
const MAX_FILE_BYTES: u64 = 16 << 20;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PathFile {
    frames: u32,
    #[serde(default)]
    interpolation: InterpolationName,
    keyframes: Vec<KeyframeFile>,
}

#[derive(Deserialize, Default)]
#[serde(rename_all = "lowercase")]
enum InterpolationName {
    Linear,
    #[default]
    Spline,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct KeyframeFile {
    position: [f64; 3],
    target: [f64; 3],
    up: Option<[f64; 3]>,
    fov_y_deg: Option<f64>,
}

fn point([x, y, z]: [f64; 3]) -> Point3 {
    Point3 { x, y, z }
}

/// Reads the camera path in `path` (`.json`, `.json5` or `.toml`); a Potree project's
/// animation runs at `fps` frames a second. Its values are checked with the rest of the
/// request (`RenderRequest::validate`).
pub fn read(path: &Path, fps: u32) -> Result<CameraPath> {
    let size = std::fs::metadata(path)
        .with_context(|| format!("reading {}", path.display()))?
        .len();
    if size > MAX_FILE_BYTES {
        bail!(
            "{} is {size} bytes; a camera path file is at most {MAX_FILE_BYTES}",
            path.display()
        );
    }
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let extension = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    let not_a_path = || format!("{} is not a camera path", path.display());
    let file: PathFile = match extension.as_deref() {
        Some(json @ ("json" | "json5")) => {
            let document: serde_json::Value = if json == "json" {
                serde_json::from_str(&text).with_context(not_a_path)?
            } else {
                json5::from_str(&text).with_context(not_a_path)?
            };
            if PotreeProject::is_one(&document) {
                let project: PotreeProject = serde_json::from_value(document)
                    .with_context(|| format!("{} is not a Potree project", path.display()))?;
                let (camera_path, words) = project.camera_path(fps)?;
                eprintln!("camera path: {words}");
                return Ok(camera_path);
            }
            serde_json::from_value(document).with_context(not_a_path)?
        }
        Some("toml") => toml::from_str(&text).with_context(not_a_path)?,
        _ => bail!(
            "--camera-path {}: give a .json, .json5 (a Potree project) or .toml file",
            path.display()
        ),
    };
    Ok(CameraPath::Keyframes {
        keyframes: file
            .keyframes
            .into_iter()
            .map(|k| Keyframe {
                position: point(k.position),
                target: point(k.target),
                up: k.up.map_or(DEFAULT_UP, point),
                fov_y_deg: k.fov_y_deg.unwrap_or(DEFAULT_FOV_Y_DEG),
            })
            .collect(),
        frames: file.frames,
        interpolation: match file.interpolation {
            InterpolationName::Linear => Interpolation::Linear,
            InterpolationName::Spline => Interpolation::Spline,
        },
    })
}

/// Potree's default vertical field of view, for projects that do not save theirs.
const POTREE_DEFAULT_FOV_Y_DEG: f64 = 60.0;

#[derive(Deserialize)]
#[serde(rename_all = "camelCase")]
struct PotreeProject {
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
    fn is_one(document: &serde_json::Value) -> bool {
        document.get("type").and_then(|t| t.as_str()) == Some("Potree")
            || document.get("cameraAnimations").is_some()
    }

    /// The project's first camera animation as a path of `fps` frames a second (Potree's
    /// curves through the control points are Catmull-Rom splines, as pointfarm's).
    fn camera_path(self, fps: u32) -> Result<(CameraPath, String)> {
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

    fn written(name: &str, text: &str) -> (tempfile::TempDir, std::path::PathBuf) {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join(name);
        std::fs::write(&path, text).expect("write");
        (dir, path)
    }

    #[test]
    fn json_and_toml_give_the_same_path() {
        let (_a, json) = written(
            "path.json",
            r#"{"frames": 24, "interpolation": "linear", "keyframes": [
                {"position": [10, 0, 5], "target": [0, 0, 0]},
                {"position": [0, 10, 5], "target": [0, 0, 1], "up": [0, 0, 1], "fov_y_deg": 40}
            ]}"#,
        );
        let (_b, toml) = written(
            "path.TOML",
            "frames = 24\ninterpolation = \"linear\"\n\
             [[keyframes]]\nposition = [10, 0, 5]\ntarget = [0, 0, 0]\n\
             [[keyframes]]\nposition = [0, 10, 5]\ntarget = [0, 0, 1]\nup = [0, 0, 1]\nfov_y_deg = 40\n",
        );
        let from_json = read(&json, 30).expect("json");
        assert_eq!(from_json, read(&toml, 30).expect("toml"));
        let CameraPath::Keyframes {
            keyframes,
            frames,
            interpolation,
        } = from_json
        else {
            panic!("keyframes");
        };
        assert_eq!((frames, interpolation), (24, Interpolation::Linear));
        assert_eq!(keyframes[0].fov_y_deg, DEFAULT_FOV_Y_DEG);
        assert_eq!(keyframes[1].fov_y_deg, 40.0);
        assert_eq!(keyframes[1].target, point([0.0, 0.0, 1.0]));
    }

    #[test]
    fn a_file_that_is_not_a_camera_path_is_named() {
        for (name, text, says) in [
            ("p.json", "{\"frames\": 2}", "not a camera path"),
            (
                "p.toml",
                "frames = 2\nkeyframes = []\nspeed = 3\n",
                "not a camera path",
            ),
            ("p.yaml", "frames: 2", "or .toml file"),
        ] {
            let (_dir, path) = written(name, text);
            let error = format!("{:#}", read(&path, 30).expect_err(name));
            assert!(error.contains(says), "{name}: {error}");
            assert!(error.contains(name) || says == "or .toml file", "{error}");
        }
    }

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

//! `render --camera-path FILE`: a keyframed camera path written as JSON or TOML, the same path
//! the API's `CameraPath.keyframes` carries, or the first camera animation of a Potree project
//! (`.json5` or `.json`, see `potree_animation`).
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

use std::path::Path;

use anyhow::{bail, Context, Result};
use pointfarm_render::camera::DEFAULT_FOV_Y_DEG;
use pointfarm_render::request::{CameraPath, Interpolation, Keyframe, Point3, DEFAULT_UP};
use serde::Deserialize;

use crate::potree_animation::PotreeProject;

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
}

//! What a worker can render and what a job asks of its workers, and the one test of the two
//! that leasing and `jobs show` share.
//!
//! A worker sends its capabilities with every lease request (no registration to lose when the
//! daemon restarts): its adapter (GPU or software, name, 64-bit atomics, binding and buffer
//! limits), the largest image side it draws and the operator's tags. A job may require tags
//! and a GPU. Which frames an adapter can draw is decided by the image's size alone: frames
//! whose per-pixel buffers exceed the binding limit are drawn in tiles, so every adapter with
//! wgpu's default limits draws every image up to the renderer's `MAX_IMAGE_SIDE`
//! ([`largest_drawn_side`]); the binding and buffer limits are reported, not routed on. An
//! operator who wants large frames kept off a slow adapter says so (`worker --max-frame-side`,
//! or a job's `--require-gpu`).

use std::collections::BTreeSet;

use pointfarm_render::gpu::GpuContext;
use pointfarm_render::raster::largest_drawn_side;
use pointfarm_render::request::RenderRequest;
use serde::{Deserialize, Serialize};

use crate::error::DaemonError;

/// Longest tag, in bytes.
pub const MAX_TAG_BYTES: usize = 64;
/// Most tags a worker advertises or a job requires.
pub const MAX_TAGS: usize = 32;

/// The kind of a worker's adapter.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum AdapterKind {
    /// Not said (a worker that predates capabilities): not known to be a GPU.
    #[default]
    Unknown,
    Hardware,
    Software,
}

/// What one worker can render, as it says with each lease request.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct WorkerCapabilities {
    pub adapter: AdapterKind,
    pub adapter_name: String,
    /// None: unknown (wgpu does not report an adapter's memory).
    pub device_memory_bytes: Option<u64>,
    pub int64_atomics: bool,
    pub max_storage_binding_bytes: u64,
    pub max_buffer_bytes: u64,
    /// The largest side of an image it draws (width or height times supersampling); None: no
    /// limit stated.
    pub max_frame_side: Option<u32>,
    pub tags: BTreeSet<String>,
    /// The video encoders its ffmpeg has; none when it makes no videos (`encodes`).
    pub video_encoders: Vec<String>,
}

impl WorkerCapabilities {
    /// The capabilities of a worker rendering on `gpu` with the operator's `tags` and frame
    /// limit (`max_frame_side`, at most what the adapter draws).
    pub fn of(gpu: &GpuContext, tags: BTreeSet<String>, max_frame_side: Option<u32>) -> Self {
        let capabilities = &gpu.capabilities;
        let drawn = largest_drawn_side(capabilities.max_storage_binding_bytes);
        Self {
            adapter: if gpu.is_software() {
                AdapterKind::Software
            } else {
                AdapterKind::Hardware
            },
            adapter_name: gpu.adapter_info.name.clone(),
            device_memory_bytes: None,
            int64_atomics: capabilities.int64_atomics,
            max_storage_binding_bytes: capabilities.max_storage_binding_bytes,
            max_buffer_bytes: capabilities.max_buffer_bytes,
            max_frame_side: Some(max_frame_side.map_or(drawn, |side| side.min(drawn))),
            tags,
            video_encoders: Vec::new(),
        }
    }

    /// Why this worker cannot render the frames of a job with `requirements` and `request`;
    /// None when it can. Every frame of a job has the same size, so the answer holds for all.
    pub fn refusal(
        &self,
        requirements: &WorkerRequirements,
        request: &RenderRequest,
    ) -> Option<String> {
        if requirements.gpu && self.adapter != AdapterKind::Hardware {
            let adapter = match self.adapter {
                AdapterKind::Software => format!("a software adapter ({})", self.adapter_name),
                _ => "no known GPU".to_string(),
            };
            return Some(format!("the job requires a GPU; the worker has {adapter}"));
        }
        let missing: Vec<&str> = requirements
            .tags
            .iter()
            .filter(|tag| !self.tags.contains(*tag))
            .map(String::as_str)
            .collect();
        if !missing.is_empty() {
            return Some(format!("no tag {}", missing.join(", ")));
        }
        if let Some(limit) = self.max_frame_side {
            let side = drawn_side(request);
            if side > u64::from(limit) {
                return Some(format!(
                    "the job draws {side} pixels a side ({}x{} at {}x supersampling); the \
                     worker draws at most {limit}",
                    request.width, request.height, request.render.supersample
                ));
            }
        }
        None
    }
}

/// The larger side of the image a frame of `request` draws: its size times its supersampling.
pub fn drawn_side(request: &RenderRequest) -> u64 {
    u64::from(request.width.max(request.height)) * u64::from(request.render.supersample.max(1))
}

/// What a job asks of the workers that render it.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct WorkerRequirements {
    /// Tags the worker must all have; sorted, each once.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub tags: Vec<String>,
    /// A hardware GPU, not a software rasterizer.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub gpu: bool,
}

impl WorkerRequirements {
    pub fn is_empty(&self) -> bool {
        self.tags.is_empty() && !self.gpu
    }

    /// "a GPU and tags a, b", for messages.
    pub fn describe(&self) -> String {
        let mut parts = Vec::new();
        if self.gpu {
            parts.push("a GPU".to_string());
        }
        if !self.tags.is_empty() {
            parts.push(format!(
                "tag{} {}",
                if self.tags.len() == 1 { "" } else { "s" },
                self.tags.join(", ")
            ));
        }
        if parts.is_empty() {
            "nothing".into()
        } else {
            parts.join(" and ")
        }
    }
}

/// `tags` (the request's `field`) checked, sorted and each kept once: 1 to [`MAX_TAG_BYTES`]
/// bytes of ASCII letters, digits and `-_.:/` each, at most [`MAX_TAGS`] of them.
pub fn checked_tags<'a>(
    field: &str,
    tags: impl IntoIterator<Item = &'a str>,
) -> Result<BTreeSet<String>, DaemonError> {
    let mut checked = BTreeSet::new();
    for tag in tags {
        check_tag(field, tag)?;
        checked.insert(tag.to_owned());
    }
    if checked.len() > MAX_TAGS {
        return Err(DaemonError::invalid(
            field,
            format!("{} tags; at most {MAX_TAGS}", checked.len()),
        ));
    }
    Ok(checked)
}

fn check_tag(field: &str, tag: &str) -> Result<(), DaemonError> {
    if tag.is_empty() || tag.len() > MAX_TAG_BYTES {
        return Err(DaemonError::invalid(
            field,
            format!("a tag has 1 to {MAX_TAG_BYTES} bytes, got {}", tag.len()),
        ));
    }
    let allowed = |c: char| c.is_ascii_alphanumeric() || "-_.:/".contains(c);
    if let Some(bad) = tag.chars().find(|c| !allowed(*c)) {
        return Err(DaemonError::invalid(
            field,
            format!("tag {tag:?} has {bad:?}; tags are letters, digits and -_.:/"),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use pointfarm_render::request::{CameraPath, Lens, RenderOptions, Turntable};

    fn request(width: u32, height: u32, supersample: u32) -> RenderRequest {
        RenderRequest {
            width,
            height,
            camera_path: CameraPath::Turntable(Turntable::around_the_cloud(1)),
            lens: Lens::default(),
            render: RenderOptions {
                supersample,
                ..RenderOptions::default()
            },
        }
    }

    fn worker(adapter: AdapterKind, tags: &[&str], side: Option<u32>) -> WorkerCapabilities {
        WorkerCapabilities {
            adapter,
            adapter_name: "llvmpipe".into(),
            max_frame_side: side,
            tags: tags.iter().map(|t| t.to_string()).collect(),
            ..WorkerCapabilities::default()
        }
    }

    #[test]
    fn a_worker_renders_a_job_only_with_its_gpu_its_tags_and_its_frame_size() {
        let none = WorkerRequirements::default();
        let gpu = WorkerRequirements {
            gpu: true,
            tags: Vec::new(),
        };
        let tagged = WorkerRequirements {
            gpu: false,
            tags: vec!["a100".into(), "site-x".into()],
        };
        let small = request(640, 480, 1);
        let lavapipe = worker(AdapterKind::Software, &["site-x"], Some(4096));
        let old = worker(AdapterKind::Unknown, &[], None);
        let a100 = worker(AdapterKind::Hardware, &["a100", "site-x", "z"], None);
        assert_eq!(lavapipe.refusal(&none, &small), None);
        assert_eq!(old.refusal(&none, &request(16384, 16384, 1)), None);
        assert_eq!(
            lavapipe.refusal(&gpu, &small).as_deref(),
            Some("the job requires a GPU; the worker has a software adapter (llvmpipe)")
        );
        assert!(old
            .refusal(&gpu, &small)
            .is_some_and(|r| r.contains("no known GPU")));
        assert_eq!(a100.refusal(&gpu, &small), None);
        assert_eq!(
            lavapipe.refusal(&tagged, &small).as_deref(),
            Some("no tag a100")
        );
        assert_eq!(a100.refusal(&tagged, &small), None);
        // The drawn side counts: 2048 at 2x supersampling is 4096, 2049 is not.
        assert_eq!(lavapipe.refusal(&none, &request(2048, 100, 2)), None);
        let refused = lavapipe.refusal(&none, &request(100, 2049, 2));
        assert!(
            refused
                .as_deref()
                .is_some_and(|r| r.contains("4098 pixels a side")),
            "{refused:?}"
        );
    }

    #[test]
    fn tags_are_checked_sorted_and_kept_once() {
        let tags = checked_tags("tags", ["site-x", "gpu:a100", "site-x"]).expect("valid");
        assert_eq!(
            tags.into_iter().collect::<Vec<_>>(),
            vec!["gpu:a100".to_string(), "site-x".to_string()]
        );
        for bad in [
            "",
            "has space",
            "comma,",
            "é",
            &"x".repeat(MAX_TAG_BYTES + 1),
        ] {
            let error = checked_tags("required_tags", [bad]).expect_err(bad);
            assert!(error.to_string().contains("required_tags"), "{error}");
        }
        let many: Vec<String> = (0..=MAX_TAGS).map(|i| format!("t{i}")).collect();
        assert!(checked_tags("tags", many.iter().map(String::as_str)).is_err());
    }
}

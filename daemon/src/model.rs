//! The daemon's domain types: what is stored in sled and what the gRPC layer converts to and
//! from. Nothing here knows about protobuf. What a job renders is the render crate's
//! [`RenderRequest`], stored as it is.

use std::collections::{BTreeMap, BTreeSet};

use pointfarm_render::encode::video::VideoSettings;
use pointfarm_render::request::RenderRequest;
use pointfarm_render::source::BuildUnseen;
use serde::{Deserialize, Serialize};

use crate::capabilities::WorkerRequirements;
use crate::error::DaemonError;

pub type DatasetId = String;
pub type JobId = String;

/// Point cloud files rendered as one: a scan, or the tiles or scan positions of a campaign.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Dataset {
    pub id: DatasetId,
    pub name: String,
    /// Bytes of all its files.
    pub size_bytes: u64,
    /// The content's SHA-256: the file's own for one file, else that of its files' hashes in
    /// order ([`content_sha256`]). For a dataset by URL, whose content is never read whole,
    /// the SHA-256 of its URL, version and size ([`RemoteSource::key`]): it keys the stores
    /// and caches as a content hash does, and clients are not shown it.
    pub sha256: String,
    /// The first file; empty for a dataset by URL.
    pub path: std::path::PathBuf,
    /// Every file, in order. Empty in records written when a dataset was one file: that file
    /// is then `path` (see [`Dataset::files`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub files: Vec<DatasetFile>,
    pub created_unix_ms: i64,
    /// The object a dataset by URL is read from; none for files on the server.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub remote: Option<RemoteSource>,
    /// The LAS/LAZ objects of a dataset of tiles by URL, in order; empty otherwise.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub tiles: Vec<RemoteTile>,
}

/// One LAS/LAZ object of a dataset of tiles by URL, as its registration found it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RemoteTile {
    /// A checked `s3://` or `http(s)://` URL, which never holds credentials.
    pub url: String,
    pub size_bytes: u64,
    /// The ETag or version id its reads are pinned to.
    pub version: String,
}

/// What identifies these versions of `tiles`, in place of a content hash: the SHA-256 (hex)
/// of each one's URL, version and size, length-prefixed, in order.
pub fn tiles_key(tiles: &[RemoteTile]) -> String {
    use sha2::{Digest, Sha256};
    let mut hasher = Sha256::new();
    hasher.update(b"tiles\0");
    for tile in tiles {
        for part in [tile.url.as_bytes(), tile.version.as_bytes()] {
            hasher.update((part.len() as u64).to_le_bytes());
            hasher.update(part);
        }
        hasher.update(tile.size_bytes.to_le_bytes());
    }
    hex(&hasher.finalize())
}

/// A dataset's level-of-detail store published to object storage (`stores/publish.rs`):
/// where it lies and the versions of its objects, never credentials.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct PublishedStore {
    /// The store's prefix, `STORE_URL/SHA256/`.
    pub url: String,
    pub hierarchy_version: String,
    pub payload_version: String,
}

/// The object of a dataset by URL, as its registration found it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RemoteSource {
    /// A checked `s3://` or `http(s)://` URL, which never holds credentials.
    pub url: String,
    /// The ETag or version id its reads are pinned to.
    pub version: String,
}

impl RemoteSource {
    /// What identifies this version of the object, in place of a content hash that would
    /// need the whole object read: the SHA-256 (hex) of the URL, the version and the size.
    pub fn key(&self, size_bytes: u64) -> String {
        use sha2::{Digest, Sha256};
        let mut hasher = Sha256::new();
        for part in [self.url.as_bytes(), self.version.as_bytes()] {
            hasher.update((part.len() as u64).to_le_bytes());
            hasher.update(part);
        }
        hasher.update(size_bytes.to_le_bytes());
        hex(&hasher.finalize())
    }
}

/// One file of a dataset.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DatasetFile {
    pub name: String,
    pub path: std::path::PathBuf,
    pub size_bytes: u64,
    pub sha256: String,
}

/// Dataset ids are derived from the content, so the same file always has the same id.
pub fn dataset_id(sha256: &str) -> String {
    format!("ds-{}", &sha256[..sha256.len().min(16)])
}

impl Dataset {
    /// Whether the dataset is read by URL (one COPC object, or tiles) rather than from files
    /// on the server.
    pub fn is_by_url(&self) -> bool {
        self.remote.is_some() || !self.tiles.is_empty()
    }

    /// Refuses `work` that reads a dataset's files on the server (a store build from files, a
    /// composition) for a dataset by URL, which has none, saying why.
    pub fn check_local(&self, work: &str) -> Result<(), DaemonError> {
        let url = match (&self.remote, self.tiles.first()) {
            (Some(remote), _) => &remote.url,
            (None, Some(tile)) => &tile.url,
            (None, None) => return Ok(()),
        };
        Err(DaemonError::FailedPrecondition(format!(
            "dataset {} is read by URL ({url}): {work} a dataset by URL is not supported yet",
            self.id
        )))
    }

    /// Every file of the dataset, in order.
    pub fn files(&self) -> Vec<DatasetFile> {
        if self.files.is_empty() {
            vec![DatasetFile {
                name: self.name.clone(),
                path: self.path.clone(),
                size_bytes: self.size_bytes,
                sha256: self.sha256.clone(),
            }]
        } else {
            self.files.clone()
        }
    }
}

/// Lower-case hex of `bytes` (hashes, random ids).
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The content hash of files with these hashes, in this order: a single file's own hash, so
/// a one-file dataset keeps the id it always had.
pub fn content_sha256(files: &[DatasetFile]) -> String {
    let hashes: Vec<&str> = files.iter().map(|file| file.sha256.as_str()).collect();
    content_sha256_of(&hashes)
}

/// [`content_sha256`] of files known by their SHA-256s alone (a client's, before it uploads).
pub fn content_sha256_of(file_sha256s: &[&str]) -> String {
    use sha2::{Digest, Sha256};
    match file_sha256s {
        [one] => (*one).to_owned(),
        many => {
            let mut hasher = Sha256::new();
            for sha256 in many {
                hasher.update(sha256.as_bytes());
                hasher.update(b"\n");
            }
            hex(&hasher.finalize())
        }
    }
}

/// The part of a dataset a job's frames see, whose store the daemon builds first
/// (`stores::camera_first`), as the state records it so that a restart knows it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraFirstPart {
    /// The files the frames see, as a dataset of its own content (never a stored dataset).
    pub part: Dataset,
    /// The content of the whole dataset.
    pub whole_sha256: String,
    /// The box of all the dataset's files, its least then its greatest corner, which the
    /// part's store is built within.
    pub bounds: [[f64; 3]; 2],
    /// Whether the whole store is grown from the part: a job that read the part left the
    /// unseen files to after ([`JobSpec::build_unseen`]).
    pub whole_wanted: bool,
}

/// What a client asked for, validated.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobSpec {
    pub request_id: String,
    pub dataset_id: DatasetId,
    /// Flattened: stored jobs keep their `camera_path`, `width`, `height` and `render` fields
    /// at the top level, as before the request had a type of its own.
    #[serde(flatten)]
    pub request: RenderRequest,
    pub priority: i32,
    /// What a worker must offer to be leased the job's frames.
    #[serde(default, skip_serializing_if = "WorkerRequirements::is_empty")]
    pub requirements: WorkerRequirements,
    /// While the dataset's store is being built, render every frame from the preview sample
    /// first (kept as the frame's preview), again each time the build has stored another
    /// tenth of the points, then as a final frame once it is ready.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub preview: bool,
    /// Jobs that must each succeed before a frame of this one is leased, once each in the
    /// order given; empty in jobs stored before chains, which wait for nothing.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub after: Vec<JobId>,
    /// What users call the job (`job_control::check_name`); empty when unnamed.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub name: String,
    /// Labels to find the job by, by key (`job_control::check_labels`).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub labels: BTreeMap<String, String>,
    /// A video of the frames, made by a worker once every frame is final (`encodes`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub video: Option<VideoSettings>,
    /// The object-storage prefix the job's outputs are also written under (`outputs`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub output_url: Option<String>,
    /// When the job's frames see part of a dataset whose store is built for them first
    /// (`stores::camera_first`), whether the files they do not see are built after that part
    /// (the dataset's whole store grown from it) or never for this job. The render crate's
    /// option, which a local render takes too.
    #[serde(default, skip_serializing_if = "is_after", with = "build_unseen_name")]
    pub build_unseen: BuildUnseen,
}

fn is_after(unseen: &BuildUnseen) -> bool {
    *unseen == BuildUnseen::After
}

/// [`BuildUnseen`] stored by its name (`after`, `never`).
mod build_unseen_name {
    use pointfarm_render::source::BuildUnseen;
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(unseen: &BuildUnseen, to: S) -> Result<S::Ok, S::Error> {
        to.serialize_str(unseen.name())
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(from: D) -> Result<BuildUnseen, D::Error> {
        let name = String::deserialize(from)?;
        BuildUnseen::parse(&name).map_err(serde::de::Error::custom)
    }
}

impl JobSpec {
    /// A job of `request` on `dataset_id` as scheduled by default: priority 0, no worker
    /// requirements, no preview, and no job to wait for.
    pub fn new(request_id: String, dataset_id: DatasetId, request: RenderRequest) -> Self {
        Self {
            request_id,
            dataset_id,
            request,
            priority: 0,
            requirements: WorkerRequirements::default(),
            preview: false,
            after: Vec::new(),
            name: String::new(),
            labels: BTreeMap::new(),
            video: None,
            output_url: None,
            build_unseen: BuildUnseen::default(),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum JobState {
    Queued,
    Running,
    Succeeded,
    Failed,
    Cancelled,
    /// Leased no frames until resumed; frames being rendered when it was paused finish.
    Paused,
}

impl JobState {
    /// The state as users read it: `queued`, `running`, `succeeded`, `failed`, `cancelled`,
    /// `paused`.
    pub fn name(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Succeeded => "succeeded",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
            JobState::Paused => "paused",
        }
    }

    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobState::Succeeded | JobState::Failed | JobState::Cancelled
        )
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Job {
    pub id: JobId,
    pub spec: JobSpec,
    pub state: JobState,
    pub frames_total: u32,
    pub frames_done: u32,
    pub error: Option<String>,
    pub created_unix_ms: i64,
    pub updated_unix_ms: i64,
    /// Frames of this job each worker (by name) failed: reported failures and leases that
    /// ran out.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub worker_failures: BTreeMap<String, u32>,
    /// The workers leased no more of its frames: each failed the daemon's
    /// `worker_failures_before_blocklist` of them.
    #[serde(default, skip_serializing_if = "BTreeSet::is_empty")]
    pub blocklist: BTreeSet<String>,
    /// Of a job with a video: its encode lease, attempts and the stored video (`encodes`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub encode: Option<crate::encode_record::EncodeState>,
    /// What was written to `spec.output_url` (`outputs`).
    #[serde(
        default,
        skip_serializing_if = "crate::output_queue::JobOutputs::is_empty"
    )]
    pub outputs: crate::output_queue::JobOutputs,
}

impl Job {
    /// Counts a failed frame for `worker`; it joins the blocklist at `limit` failures (never
    /// when `limit` is 0). Returns whether it joined it now.
    pub fn count_worker_failure(&mut self, worker: &str, limit: u32) -> bool {
        let failed = self.worker_failures.entry(worker.to_owned()).or_default();
        *failed += 1;
        limit > 0 && *failed >= limit && self.blocklist.insert(worker.to_owned())
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageTiming {
    pub stage: String,
    pub ms: f64,
    pub gpu_clock: bool,
}

/// What the worker reports of a finished frame.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameReport {
    pub index: u32,
    pub timings: Vec<StageTiming>,
    /// Set when the worker loaded the dataset for this frame: from its cache or not.
    pub dataset_cache_hit: Option<bool>,
    /// Attempts that ended without a result before this one (failed, or the worker was lost).
    #[serde(default)]
    pub failed_attempts: u32,
    /// The frame's cut when it was rendered from levels of detail.
    #[serde(default)]
    pub cut: Option<FrameCut>,
    /// The worker that rendered it; empty in frames stored before it was recorded.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub worker: String,
    /// Set on a preview drawn from the dataset's chunk starts: its completeness, the points
    /// drawn over the points of the dataset's files. The frame's final report replaces it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub preview: Option<f64>,
    /// Set on a preview: the version of the preview sample it was leased to be drawn from (the
    /// whole tenths of the points the build had stored); previews stored before versions
    /// were kept read as 0, the chunk starts alone.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub preview_version: u32,
}

fn is_zero(n: &u32) -> bool {
    *n == 0
}

/// What a frame rendered from levels of detail drew and loaded: the render crate's counts,
/// stored with the frame as they are.
pub use pointfarm_render::cut::CutCounts as FrameCut;

/// One frame of a job. A frame of a job with `preview` may also have a preview (kept apart,
/// see `StateDb::preview`) while it is pending; it is done only when final.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum FrameState {
    Pending { attempts: u32 },
    Done(FrameReport),
}

/// Something that happened to a job, for watchers.
#[derive(Debug, Clone, PartialEq)]
pub struct JobEvent {
    pub job: Job,
    /// Set when a frame finished.
    pub frame: Option<FrameReport>,
}

pub fn now_unix_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use pointfarm_render::raster::{FillSettings, Quality, Shading};
    use pointfarm_render::request::{CameraPath, Interpolation, Lens, Point3, PointSize};

    use super::*;

    /// A job record exactly as the daemon stored it before the render request moved into
    /// the render crate.
    const STORED_JOB: &str = r#"{"id":"job-1","spec":{"request_id":"r1","dataset_id":"ds-1",
        "camera_path":{"Keyframes":{"keyframes":[
            {"position":{"x":1.0,"y":0.0,"z":10.0},"target":{"x":0.0,"y":1.0,"z":0.0},
             "up":{"x":0.0,"y":0.0,"z":1.0},"fov_y_deg":40.0},
            {"position":{"x":5.0,"y":0.0,"z":10.0},"target":{"x":0.0,"y":1.0,"z":0.0},
             "up":{"x":0.0,"y":0.0,"z":1.0},"fov_y_deg":40.0}],
            "frames":7,"interpolation":"Spline"}},
        "width":64,"height":48,
        "render":{"point_size":3,"quality":{"High":{"depth_band":0.02}},
            "shading":{"Pintus":{"levels":8,"exponent":1.5}},"color_mode":{"Fixed":[16,32,48]},
            "background":[1,2,3,4],"fill":{"kernel":5}},
        "priority":2},
        "state":"Queued","frames_total":7,"frames_done":0,"error":null,
        "created_unix_ms":1,"updated_unix_ms":2}"#;

    #[test]
    fn jobs_stored_before_the_render_request_moved_still_read() {
        let job: Job = serde_json::from_str(STORED_JOB).expect("the stored shape reads");
        let request = &job.spec.request;
        assert_eq!(
            (request.width, request.height, job.spec.priority),
            (64, 48, 2)
        );
        let CameraPath::Keyframes {
            keyframes,
            frames,
            interpolation,
        } = &request.camera_path
        else {
            panic!("not keyframes: {:?}", request.camera_path);
        };
        assert_eq!(
            (*frames, *interpolation, keyframes.len()),
            (7, Interpolation::Spline, 2)
        );
        assert_eq!(
            keyframes[1].position,
            Point3 {
                x: 5.0,
                y: 0.0,
                z: 10.0
            }
        );
        assert_eq!(request.lens, Lens::default());
        let render = &request.render;
        assert_eq!(render.point_size, PointSize::Fixed(3));
        assert_eq!(render.quality, Quality::High { depth_band: 0.02 });
        assert_eq!(render.shading, Shading::PINTUS);
        assert_eq!(
            render.color_mode,
            pointfarm_render::color::ColorMode::Fixed([16, 32, 48])
        );
        assert_eq!(render.background, [1, 2, 3, 4]);
        assert_eq!(render.fill, Some(FillSettings { kernel: 5 }));
        assert_eq!((render.supersample, render.depth), (1, false));
        // And what is written now reads back the same.
        let written = serde_json::to_string(&job).expect("encodes");
        assert_eq!(serde_json::from_str::<Job>(&written).expect("decodes"), job);
    }

    #[test]
    fn a_job_keeps_whether_it_builds_the_files_its_frames_do_not_see() {
        let mut job: Job = serde_json::from_str(STORED_JOB).expect("the stored shape reads");
        assert_eq!(job.spec.build_unseen, BuildUnseen::After);
        job.spec.build_unseen = BuildUnseen::Never;
        let written = serde_json::to_string(&job).expect("encodes");
        assert!(written.contains(r#""build_unseen":"never""#), "{written}");
        assert_eq!(serde_json::from_str::<Job>(&written).expect("decodes"), job);
        let later = written.replace(r#""build_unseen":"never""#, r#""build_unseen":"later""#);
        assert!(serde_json::from_str::<Job>(&later).is_err());
    }
}

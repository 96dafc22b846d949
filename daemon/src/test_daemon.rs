//! A daemon on a folder for the daemon's own tests: one registered file that is never
//! decoded, and jobs submitted through the conversion the gRPC layer uses.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use pointfarm_proto::v1 as pb;

use crate::capabilities::WorkerCapabilities;
use crate::lease::{FrameOutcome, FrameTask};
use crate::model::{Job, JobSpec};
use crate::service::{Daemon, DaemonConfig};

/// The file under every test daemon's data root; registering hashes it, nothing decodes it.
const FILE: &str = "a.las";

/// A daemon whose data lie in `dir/data`, with [`FILE`] under its root `dir/roots` and leases
/// that last `lease_timeout`.
pub fn open(dir: &Path, lease_timeout: Duration) -> Arc<Daemon> {
    open_with(dir, |config| config.lease_timeout = lease_timeout)
}

/// [`open`] with the configuration changed by `configure`.
pub fn open_with(dir: &Path, configure: impl FnOnce(&mut DaemonConfig)) -> Arc<Daemon> {
    std::fs::create_dir_all(dir.join("roots")).expect("roots");
    std::fs::write(dir.join("roots").join(FILE), b"points").expect("file");
    let mut config = DaemonConfig::new(dir.join("data"));
    config.data_roots = vec![dir.join("roots")];
    configure(&mut config);
    Daemon::open(config).expect("open")
}

/// Submits a turntable of `frames` frames of 8 x 6 pixels on the dataset of [`FILE`]
/// (registered on first use), after `adjust` has changed the request.
pub fn submit(daemon: &Daemon, frames: u32, adjust: impl FnOnce(&mut pb::SubmitJobRequest)) -> Job {
    let listed = daemon.list_datasets(1, "").expect("datasets").items;
    let dataset = match listed.into_iter().next() {
        Some(dataset) => dataset,
        None => daemon
            .register_dataset(&[FILE.to_string()], "")
            .expect("register"),
    };
    let mut request = pb::SubmitJobRequest {
        dataset_id: dataset.id,
        camera_path: Some(pb::CameraPath::turntable(pb::Turntable::of_frames(frames))),
        width: 8,
        height: 6,
        ..Default::default()
    };
    adjust(&mut request);
    daemon
        .submit_job(JobSpec::try_from(&request).expect("spec"))
        .expect("submit")
}

/// A blank PNG of `width` x `height`, a frame's result as a worker sends it.
pub fn png(width: u32, height: u32) -> Vec<u8> {
    let mut bytes = Vec::new();
    image::RgbaImage::new(width, height)
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .expect("encode");
    bytes
}

/// The next frame a worker named `w`, of no particular capabilities, is leased.
pub fn lease(daemon: &Daemon) -> Option<FrameTask> {
    daemon
        .lease_frame("w", false, &WorkerCapabilities::default())
        .expect("lease")
}

/// Hands in a blank final frame of 8 x 6 pixels (the size of [`submit`]'s jobs) for `task`;
/// its job as it is then.
pub fn render(daemon: &Daemon, task: &FrameTask) -> Job {
    let outcome = FrameOutcome {
        timings: Vec::new(),
        dataset_cache_hit: None,
        cut: None,
        preview: None,
    };
    daemon
        .complete_frame(&task.lease.id, &png(8, 6), outcome)
        .expect("complete")
}

//! Why a job waits: for a job it runs after to succeed, for a worker connected now that can
//! be leased its frames, with why each that cannot cannot (requirements, frame size,
//! blocklist), or, for a job whose final frames are held, for the store they read to be
//! built, for `jobs show` and the submission's answer. More `Daemon` methods; the test is the one `lease_frame` makes.

use crate::capabilities::{drawn_side, AdapterKind};
use crate::model::{Job, JobState};
use crate::service::Daemon;
use crate::worker_presence::ConnectedWorker;

/// Why a job whose final frames are held waits.
pub const STORE_BUILDING: &str =
    "waiting for the store of its dataset to be built: no final frame is leased before";

/// Whether the frames of an unfinished job can be leased to a worker connected now.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct JobAvailability {
    /// Why no connected worker can be leased a frame of it; None while one can, and for a job
    /// that has ended.
    pub waiting: Option<String>,
    /// Each connected worker that cannot, by name, with why not.
    pub refusals: Vec<(String, String)>,
}

impl Daemon {
    /// Whether a worker connected now can be leased frames of `job`, and why each that cannot
    /// cannot: the test `lease_frame` makes, against the workers `WorkerPresence` knows.
    pub fn job_availability(&self, job: &Job) -> JobAvailability {
        if job.state.is_terminal() {
            return JobAvailability::default();
        }
        if job.state == JobState::Paused {
            return JobAvailability {
                waiting: Some("paused: no frame of it is leased until it is resumed".into()),
                refusals: Vec::new(),
            };
        }
        if let Some(prerequisite) = self.unmet_prerequisite(job) {
            return JobAvailability {
                waiting: Some(format!("waiting for job {prerequisite} to succeed")),
                refusals: Vec::new(),
            };
        }
        if job.awaits_video() {
            return self.video_availability(job);
        }
        let connected = self.workers.connected(self.config.lease_timeout);
        let refusal = |worker: &ConnectedWorker| {
            if job.blocklist.contains(&worker.name) {
                let failed = job.worker_failures.get(&worker.name).copied().unwrap_or(0);
                return Some(format!(
                    "blocklisted: it failed {failed} frames of this job"
                ));
            }
            worker
                .capabilities
                .refusal(&job.spec.requirements, &job.spec.request)
        };
        let refusals: Vec<(String, String)> = connected
            .iter()
            .filter_map(|worker| refusal(worker).map(|why| (worker.name.clone(), why)))
            .collect();
        let waiting = if connected.is_empty() {
            Some("no worker is connected".to_string())
        } else if refusals.len() == connected.len() {
            Some(why_none_can(job, &connected))
        } else if self.store_holds_final_frames(job) {
            Some(STORE_BUILDING.to_string())
        } else {
            None
        };
        JobAvailability { waiting, refusals }
    }
}

/// Why none of `connected` (each of which cannot) can render `job`: the one reason they
/// share where there is one.
fn why_none_can(job: &Job, connected: &[ConnectedWorker]) -> String {
    let requirements = &job.spec.requirements;
    let none = |lacks: &dyn Fn(&ConnectedWorker) -> bool| connected.iter().all(lacks);
    if none(&|w| job.blocklist.contains(&w.name)) {
        return "every connected worker is blocklisted for this job".into();
    }
    if requirements.gpu && none(&|w| w.capabilities.adapter != AdapterKind::Hardware) {
        return "no connected worker has a GPU".into();
    }
    if let Some(tag) = requirements
        .tags
        .iter()
        .find(|tag| none(&|w| !w.capabilities.tags.contains(*tag)))
    {
        return format!("no connected worker has tag {tag}");
    }
    let side = drawn_side(&job.spec.request);
    if none(&|w| {
        w.capabilities
            .max_frame_side
            .is_some_and(|m| side > u64::from(m))
    }) {
        return format!("no connected worker draws images of {side} pixels a side");
    }
    "no connected worker can render it (each for a reason of its own)".into()
}

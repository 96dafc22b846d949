//! Why a job at its video stage waits: no connected worker's ffmpeg has the encoder its video
//! needs, as each worker says in its capabilities. The encode is leased by the same test
//! ([`encode_refusal`]), so what `jobs show` says is what leasing does.

use super::encode_refusal;
use crate::availability::JobAvailability;
use crate::model::Job;
use crate::service::Daemon;

impl Daemon {
    /// Whether a connected worker can make the video of `job`, whose frames are all final,
    /// and why each that cannot cannot; nothing waits while its encode is leased.
    pub fn video_availability(&self, job: &Job) -> JobAvailability {
        let Some(video) = job.spec.video else {
            return JobAvailability::default();
        };
        if job.encode.as_ref().is_some_and(|e| e.video.lease.is_some()) {
            return JobAvailability::default();
        }
        let connected = self.workers.connected(self.config.lease_timeout);
        let refusals: Vec<(String, String)> = connected
            .iter()
            .filter_map(|worker| {
                encode_refusal(&worker.capabilities.video_encoders, &video)
                    .map(|why| (worker.name.clone(), why))
            })
            .collect();
        let waiting = if connected.is_empty() {
            Some("no worker is connected".to_string())
        } else if refusals.len() == connected.len() {
            Some(format!(
                "waiting for a worker whose ffmpeg has {} to make the video",
                video.encoder()
            ))
        } else {
            None
        };
        JobAvailability { waiting, refusals }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use pointfarm_proto::v1 as pb;

    use crate::capabilities::WorkerCapabilities;
    use crate::test_daemon;

    #[test]
    fn a_video_no_connected_worker_can_make_says_which_encoder_it_waits_for() {
        let dir = tempfile::tempdir().expect("tempdir");
        let timeout = Duration::from_secs(60);
        let daemon = test_daemon::open(dir.path(), timeout);
        let job = test_daemon::submit(&daemon, 1, |request| {
            request.video = Some(pb::VideoSpec {
                container: "mkv".into(),
                codec: "h265".into(),
                ..Default::default()
            });
        });
        let task = test_daemon::lease(&daemon).expect("the frame");
        test_daemon::render(&daemon, &task);
        let job = daemon.job(&job.id).expect("job");
        assert_eq!(job.stage(), "video");
        let waiting = |daemon: &crate::service::Daemon| daemon.job_availability(&job).waiting;
        assert_eq!(waiting(&daemon).as_deref(), Some("no worker is connected"));

        let with = |encoders: &[&str]| WorkerCapabilities {
            video_encoders: encoders.iter().map(|e| e.to_string()).collect(),
            ..WorkerCapabilities::default()
        };
        let blind = daemon
            .workers
            .poll_named(false, "blind", with(&[]), timeout);
        let x264 = daemon
            .workers
            .poll_named(false, "x264", with(&["libx264", "gif"]), timeout);
        let availability = daemon.job_availability(&job);
        assert_eq!(
            availability.waiting.as_deref(),
            Some("waiting for a worker whose ffmpeg has libx265 to make the video")
        );
        assert_eq!(
            availability.refusals,
            vec![
                (
                    "blind".to_string(),
                    "the worker makes no videos (no ffmpeg, or `worker --no-videos`)".to_string()
                ),
                (
                    "x264".to_string(),
                    "the worker's ffmpeg has no libx265 encoder".to_string()
                ),
            ]
        );
        let x265 = daemon
            .workers
            .poll_named(false, "x265", with(&["libx265"]), timeout);
        assert_eq!(waiting(&daemon), None);
        drop((blind, x264, x265));
    }
}

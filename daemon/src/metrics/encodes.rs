//! The metrics of jobs' videos (`pointfarm_encodes_*`): encode leases given, videos stored,
//! attempts failed (reported by the worker, its lease run out, or its embedded worker died)
//! and the time from lease to stored video. Counted by `encodes` where each happens.

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;

/// The counters and the histogram of jobs' videos.
#[derive(Debug)]
pub struct EncodeMetrics {
    leased: Counter,
    succeeded: Counter,
    failed: Counter,
    seconds: Histogram,
}

impl Default for EncodeMetrics {
    fn default() -> Self {
        Self {
            leased: Counter::default(),
            succeeded: Counter::default(),
            failed: Counter::default(),
            // From a quarter second (a short GIF) doubling to about 68 minutes (a long video
            // at a slow preset).
            seconds: Histogram::new(exponential_buckets(0.25, 2.0, 15)),
        }
    }
}

impl EncodeMetrics {
    /// Adds the video metrics to `registry`.
    pub(super) fn register(&self, registry: &mut Registry) {
        registry.register(
            "encodes_leased",
            "Jobs' videos leased to a worker to make (each attempt counts)",
            self.leased.clone(),
        );
        registry.register(
            "encodes_succeeded",
            "Jobs' videos made and stored",
            self.succeeded.clone(),
        );
        registry.register(
            "encodes_failed",
            "Attempts at jobs' videos that ended without one: failed on their worker (ffmpeg's \
             error), or lost with it (its encode lease ran out, or the embedded worker died)",
            self.failed.clone(),
        );
        registry.register(
            "encode_seconds",
            "Time from a video's encode lease to the stored video: fetching the frames, \
             ffmpeg, handing the video in",
            self.seconds.clone(),
        );
    }

    /// A job's video was leased to a worker.
    pub fn leased(&self) {
        self.leased.inc();
    }

    /// A job's video was stored, `seconds` after its lease where that is known.
    pub fn succeeded(&self, seconds: Option<f64>) {
        self.succeeded.inc();
        if let Some(seconds) = seconds {
            self.seconds.observe(seconds);
        }
    }

    /// An attempt at a job's video ended without one.
    pub fn failed(&self) {
        self.failed.inc();
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use pointfarm_proto::v1 as pb;

    use crate::test_daemon;

    /// The value of `series` in the daemon's metrics text.
    fn value(text: &str, series: &str) -> f64 {
        text.lines()
            .find_map(|line| line.strip_prefix(series)?.strip_prefix(' '))
            .unwrap_or_else(|| panic!("no {series} in {text}"))
            .parse()
            .expect("a number")
    }

    #[test]
    fn a_videos_lease_success_and_failure_are_counted_and_timed() {
        let dir = tempfile::tempdir().expect("tempdir");
        let daemon = test_daemon::open(dir.path(), Duration::from_secs(60));
        let text = daemon.metrics_text().expect("text");
        for series in [
            "pointfarm_encodes_leased_total",
            "pointfarm_encodes_succeeded_total",
            "pointfarm_encodes_failed_total",
            "pointfarm_encode_seconds_count",
        ] {
            assert_eq!(value(&text, series), 0.0, "{series}");
        }
        assert!(text.contains("# TYPE pointfarm_encode_seconds histogram"));

        let job = test_daemon::submit(&daemon, 1, |request| {
            request.video = Some(pb::VideoSpec {
                container: "mp4".into(),
                ..Default::default()
            });
        });
        let frame = test_daemon::lease(&daemon).expect("the frame");
        test_daemon::render(&daemon, &frame);
        let x264 = ["libx264".to_owned()];
        let first = daemon
            .lease_encode("e", false, &x264)
            .expect("lease")
            .expect("the video");
        daemon
            .fail_encode(&first.lease_id, false, "ffmpeg said no")
            .expect("failed");
        let second = daemon
            .lease_encode("e", false, &x264)
            .expect("lease")
            .expect("the video again");
        let mut upload = daemon
            .start_video_upload(&second.lease_id, false, 4)
            .expect("upload");
        upload.write(b"mp4!").expect("written");
        let stored = daemon.finish_video_upload(upload).expect("stored");
        assert_eq!(stored.id, job.id);

        let text = daemon.metrics_text().expect("text");
        assert_eq!(value(&text, "pointfarm_encodes_leased_total"), 2.0);
        assert_eq!(value(&text, "pointfarm_encodes_failed_total"), 1.0);
        assert_eq!(value(&text, "pointfarm_encodes_succeeded_total"), 1.0);
        assert_eq!(value(&text, "pointfarm_encode_seconds_count"), 1.0);
        let seconds = value(&text, "pointfarm_encode_seconds_sum");
        assert!((0.0..60.0).contains(&seconds), "{seconds}");
    }
}

//! Prometheus metrics: every metric the daemon and the worker expose is defined here, and
//! each has one owner. Counters and histograms are counted where the event happens, through
//! the methods of [`DaemonMetrics`] and [`WorkerMetrics`]; gauges that mirror state (the
//! queue, the leases, the workers) are read from the daemon's real state at each scrape
//! (`Daemon::metrics_text`, in `farm_state.rs`), so they cannot drift from it. Counters start at zero with the
//! process, as Prometheus expects of them. The one counter kept where its event happens outside
//! the daemon's reach of metrics, the stores rebuilt after damage (`stores.rs`), is read with
//! the state at each scrape and only ever moves up.
//!
//! - `worker`: the metrics of a `pointfarm worker` process (`pointfarm_worker_*`).
//! - `http`: the unauthenticated `GET /metrics` endpoint that serves either in Prometheus's
//!   text format (OpenMetrics).
//!
//! Nothing here knows about gRPC; the endpoint knows only a function that writes the text.

use std::collections::{BTreeMap, HashSet};
use std::sync::Mutex;

use prometheus_client::encoding::text::{encode_eof, encode_registry};
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;

use crate::model::{FrameReport, StageTiming};

pub mod encodes;
pub mod http;
mod worker;

pub use worker::WorkerMetrics;

/// The `Content-Type` of the text that `Daemon::metrics_text` (in `farm_state.rs`) and
/// [`WorkerMetrics::text`] write.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// The state of a frame in `pointfarm_queue_frames`: waiting for a worker, leased to one, or
/// held by a paused job.
pub const QUEUED: &str = "queued";
pub const LEASED: &str = "leased";
pub const PAUSED: &str = "paused";

/// Most distinct stage names a stage histogram keeps; the names come from workers, so a
/// worker that sent new ones at every frame must not grow the scrape without bound. Later
/// names count as [`OTHER_STAGE`].
const MAX_STAGES: usize = 32;
const OTHER_STAGE: &str = "other";

/// The stages' label.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StageLabels {
    stage: String,
}

/// Why jobs were removed: `deleted` by a user, or by the retention rules (`retention`: they
/// ended too long ago; `frame_quota`: their frames passed the quota).
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RemovalLabels {
    reason: &'static str,
}

/// The queue's labels.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct QueueLabels {
    state: &'static str,
    priority: String,
}

type StageFamily = Family<StageLabels, Histogram, fn() -> Histogram>;

/// Per-stage latencies in seconds: from half a millisecond (a GPU pass of a small frame)
/// doubling to about nine minutes (the build of a large dataset's store).
fn stage_histogram() -> Histogram {
    Histogram::new(exponential_buckets(0.0005, 2.0, 21))
}

/// One histogram per stage; see [`MAX_STAGES`].
#[derive(Debug)]
struct StageSeconds {
    family: StageFamily,
    /// The stages with a histogram of their own.
    named: Mutex<HashSet<String>>,
}

impl StageSeconds {
    fn new() -> Self {
        Self {
            family: Family::new_with_constructor(stage_histogram),
            named: Mutex::new(HashSet::new()),
        }
    }

    fn observe(&self, timings: &[StageTiming]) {
        for timing in timings {
            if !timing.ms.is_finite() || timing.ms < 0.0 {
                continue;
            }
            let stage = {
                let mut named = self.named.lock().unwrap_or_else(|e| e.into_inner());
                let name = stage_name(&timing.stage);
                if named.contains(name) || named.len() < MAX_STAGES {
                    named.insert(name.to_owned());
                    name
                } else {
                    OTHER_STAGE
                }
            };
            let labels = StageLabels {
                stage: stage.to_owned(),
            };
            self.family.get_or_create(&labels).observe(timing.ms / 1e3);
        }
    }
}

/// A stage's name as a label: as the worker reports it when it is a short lower-case word,
/// else [`OTHER_STAGE`].
fn stage_name(stage: &str) -> &str {
    let word = !stage.is_empty()
        && stage.len() <= 32
        && stage
            .bytes()
            .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_');
    if word {
        stage
    } else {
        OTHER_STAGE
    }
}

/// A cache's hits and misses, counted from whether something was found in it (`None`: no
/// cache was involved).
#[derive(Debug, Default)]
pub(super) struct CacheCounters {
    hits: Counter,
    misses: Counter,
}

impl CacheCounters {
    pub(super) fn count(&self, hit: Option<bool>) {
        match hit {
            Some(true) => {
                self.hits.inc();
            }
            Some(false) => {
                self.misses.inc();
            }
            None => {}
        }
    }

    /// Registers `{name}_hits` and `{name}_misses`.
    pub(super) fn register(
        &self,
        registry: &mut Registry,
        name: &str,
        hits_help: &str,
        misses_help: &str,
    ) {
        registry.register(format!("{name}_hits"), hits_help, self.hits.clone());
        registry.register(format!("{name}_misses"), misses_help, self.misses.clone());
    }
}

/// Frames of unfinished jobs of one priority.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct QueueDepth {
    /// Waiting for a worker.
    pub queued: u64,
    /// Leased to a worker.
    pub leased: u64,
    /// Of a paused job, not leased: waiting for the job to be resumed, not for a worker.
    pub paused: u64,
}

/// The daemon's state as the gauges show it, read at a scrape.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct FarmState {
    /// By job priority.
    pub queue: BTreeMap<i32, QueueDepth>,
    pub leases_held: u64,
    pub workers_connected: u64,
    /// Level-of-detail stores built again since the start because their bytes failed their
    /// checks (`DatasetStores::rebuilds`).
    pub store_rebuilds: u64,
    /// Level-of-detail stores made by updating a copy of another dataset's store
    /// (`DatasetStores::updates`).
    pub store_updates: u64,
    /// Node records the daemon served to workers (`DatasetStores::records_served`).
    pub store_records_served: u64,
}

/// The outcome of a webhook event for one endpoint, the label of
/// `pointfarm_webhook_deliveries_total`.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct WebhookLabels {
    outcome: &'static str,
}

/// Webhook deliveries by outcome, shared with the delivery thread: delivered (a 2xx answer),
/// failed (refused, or out of tries), dropped (the endpoint's queue was full).
#[derive(Clone, Debug, Default)]
pub struct WebhookCounters {
    deliveries: Family<WebhookLabels, Counter>,
}

impl WebhookCounters {
    const DELIVERED: &'static str = "delivered";
    const FAILED: &'static str = "failed";
    const DROPPED: &'static str = "dropped";

    fn count(&self, outcome: &'static str) {
        self.deliveries
            .get_or_create(&WebhookLabels { outcome })
            .inc();
    }

    fn value(&self, outcome: &'static str) -> u64 {
        self.deliveries
            .get_or_create(&WebhookLabels { outcome })
            .get()
    }

    pub fn delivered(&self) {
        self.count(Self::DELIVERED);
    }

    pub fn failed(&self) {
        self.count(Self::FAILED);
    }

    pub fn dropped(&self) {
        self.count(Self::DROPPED);
    }

    /// Delivered, failed and dropped so far.
    pub fn counts(&self) -> [u64; 3] {
        [Self::DELIVERED, Self::FAILED, Self::DROPPED].map(|outcome| self.value(outcome))
    }
}

/// The daemon's metrics (`pointfarm_*`).
#[derive(Debug)]
pub struct DaemonMetrics {
    registry: Registry,
    frames_completed: Counter,
    frames_failed: Counter,
    stage_seconds: StageSeconds,
    leases_expired: Counter,
    dataset_cache: CacheCounters,
    upload_bytes: Counter,
    store_rebuilds: Counter,
    store_updates: Counter,
    store_records_served: Counter,
    webhooks: WebhookCounters,
    jobs_removed: Family<RemovalLabels, Counter>,
    queue_frames: Family<QueueLabels, Gauge>,
    leases_held: Gauge,
    workers_connected: Gauge,
    pub encodes: encodes::EncodeMetrics,
    /// Held while the gauges are set from a state and encoded, so that two scrapes at once
    /// each show the state they read.
    scrape: Mutex<()>,
}

impl Default for DaemonMetrics {
    fn default() -> Self {
        Self::new()
    }
}

impl DaemonMetrics {
    pub fn new() -> Self {
        let mut metrics = Self {
            registry: Registry::with_prefix("pointfarm"),
            frames_completed: Counter::default(),
            frames_failed: Counter::default(),
            stage_seconds: StageSeconds::new(),
            leases_expired: Counter::default(),
            dataset_cache: CacheCounters::default(),
            upload_bytes: Counter::default(),
            store_rebuilds: Counter::default(),
            store_updates: Counter::default(),
            store_records_served: Counter::default(),
            webhooks: WebhookCounters::default(),
            jobs_removed: Family::default(),
            queue_frames: Family::default(),
            leases_held: Gauge::default(),
            workers_connected: Gauge::default(),
            encodes: Default::default(),
            scrape: Mutex::new(()),
        };
        let registry = &mut metrics.registry;
        metrics.encodes.register(registry);
        registry.register(
            "queue_frames",
            "Frames of unfinished jobs, by state (queued: waiting for a worker; leased: \
             being rendered) and by their job's priority",
            metrics.queue_frames.clone(),
        );
        registry.register(
            "frames_completed",
            "Frames rendered and stored",
            metrics.frames_completed.clone(),
        );
        registry.register(
            "frames_failed",
            "Attempts at frames that ended without a result: failed on their worker, or lost \
             with it (its lease ran out, or the embedded worker process died)",
            metrics.frames_failed.clone(),
        );
        registry.register(
            "frame_stage_seconds",
            "Time of each stage of the completed frames, as their workers reported it",
            metrics.stage_seconds.family.clone(),
        );
        registry.register(
            "leases_held",
            "Frame leases held by workers",
            metrics.leases_held.clone(),
        );
        registry.register(
            "leases_expired",
            "Leases that ran out without a heartbeat while their frame was wanted (the \
             worker was lost); each counts a failed attempt",
            metrics.leases_expired.clone(),
        );
        registry.register(
            "workers_connected",
            "Workers that can render: the embedded worker once it has called in, and remote \
             workers that hold a lease or asked for work within the lease timeout",
            metrics.workers_connected.clone(),
        );
        metrics.dataset_cache.register(
            registry,
            "dataset_cache",
            "Completed frames whose worker found the dataset's points in its dataset cache",
            "Completed frames whose worker decoded the dataset's files (not in its cache)",
        );
        registry.register(
            "upload_bytes",
            "Bytes of dataset uploads received whole and checked",
            metrics.upload_bytes.clone(),
        );
        registry.register(
            "store_rebuilds",
            "Level-of-detail stores built again from their datasets' files because their bytes \
             failed their checks (a node record's checksum or layout, a payload file cut \
             short); each store at most once a run",
            metrics.store_rebuilds.clone(),
        );
        registry.register(
            "store_updates",
            "Level-of-detail stores made by updating a copy of the store of a dataset sharing most \
             of their files, instead of building them whole",
            metrics.store_updates.clone(),
        );
        registry.register(
            "store_records_served",
            "Node records of level-of-detail stores served to workers; workers read a published \
             store's records from object storage instead (serve --store-url)",
            metrics.store_records_served.clone(),
        );
        for reason in ["deleted", "retention", "frame_quota"] {
            metrics
                .jobs_removed
                .get_or_create(&RemovalLabels { reason })
                .inc_by(0);
        }
        registry.register(
            "jobs_removed",
            "Jobs removed with their frames and records, by reason: deleted by a user, or by \
             the retention rules (retention: they ended longer ago than the retention; \
             frame_quota: the stored frames passed the quota)",
            metrics.jobs_removed.clone(),
        );
        // Every outcome's series from the start, so that a rate over them reads 0, not nothing.
        metrics.webhooks.counts();
        registry.register(
            "webhook_deliveries",
            "Job-end events for webhook endpoints, by outcome: delivered (a 2xx answer), \
             failed (refused with a 4xx or a redirect, or out of tries) or dropped (the \
             endpoint's queue was full)",
            metrics.webhooks.deliveries.clone(),
        );
        metrics
    }

    /// The webhook counters, for the delivery thread to count on.
    pub fn webhook_counters(&self) -> WebhookCounters {
        self.webhooks.clone()
    }

    /// A frame was rendered and stored, with its worker's report.
    pub fn frame_completed(&self, report: &FrameReport) {
        self.frames_completed.inc();
        self.stage_seconds.observe(&report.timings);
        self.dataset_cache.count(report.dataset_cache_hit);
    }

    /// An attempt at a frame ended without a result.
    pub fn frame_failed(&self) {
        self.frames_failed.inc();
    }

    /// The lease of a wanted frame ran out (its attempt is counted by
    /// [`DaemonMetrics::frame_failed`]).
    pub fn lease_expired(&self) {
        self.leases_expired.inc();
    }

    /// `count` jobs were removed for `reason` (`deleted`, `retention` or `frame_quota`).
    pub fn jobs_removed(&self, reason: &'static str, count: u64) {
        self.jobs_removed
            .get_or_create(&RemovalLabels { reason })
            .inc_by(count);
    }

    /// An upload of `bytes` was received whole.
    pub fn uploaded(&self, bytes: u64) {
        self.upload_bytes.inc_by(bytes);
    }

    /// The metrics in Prometheus's text format, the gauges showing `state`.
    pub fn text(&self, state: &FarmState) -> String {
        let _scrape = self.scrape.lock().unwrap_or_else(|e| e.into_inner());
        self.queue_frames.clear();
        // The default priority's series are always there, so that a sum over the queue reads
        // 0, not nothing, when it is empty.
        let mut queue = state.queue.clone();
        queue.entry(0).or_default();
        for (priority, depth) in &queue {
            for (label, frames) in [
                (QUEUED, depth.queued),
                (LEASED, depth.leased),
                (PAUSED, depth.paused),
            ] {
                self.queue_frames
                    .get_or_create(&QueueLabels {
                        state: label,
                        priority: priority.to_string(),
                    })
                    .set(gauge_value(frames));
            }
        }
        // Counted by the stores; a scrape catches up with them, never goes back.
        for (counter, counted) in [
            (&self.store_rebuilds, state.store_rebuilds),
            (&self.store_updates, state.store_updates),
            (&self.store_records_served, state.store_records_served),
        ] {
            let shown = counter.get();
            if counted > shown {
                counter.inc_by(counted - shown);
            }
        }
        self.leases_held.set(gauge_value(state.leases_held));
        self.workers_connected
            .set(gauge_value(state.workers_connected));
        encode(&self.registry)
    }
}

fn gauge_value(count: u64) -> i64 {
    i64::try_from(count).unwrap_or(i64::MAX)
}

/// `registry` in Prometheus's text format, whole (with its end marker).
fn encode(registry: &Registry) -> String {
    let mut text = String::new();
    // Writing to a String cannot fail, and the registry holds only well-formed metrics.
    let _ = encode_registry(&mut text, registry).and_then(|()| encode_eof(&mut text));
    text
}

#[cfg(test)]
mod tests;

#[cfg(test)]
mod store_rebuild_tests {
    use super::*;

    /// The value of `series` in `text`, as Prometheus reads it.
    fn value(text: &str, series: &str) -> Option<f64> {
        text.lines()
            .filter(|line| !line.starts_with('#'))
            .filter_map(|line| line.rsplit_once(' '))
            .find(|(name, _)| *name == series)
            .and_then(|(_, value)| value.parse().ok())
    }

    #[test]
    fn store_rebuilds_are_a_counter_that_follows_the_stores_and_never_goes_back() {
        let metrics = DaemonMetrics::new();
        let scrape = |rebuilds| {
            metrics.text(&FarmState {
                store_rebuilds: rebuilds,
                ..FarmState::default()
            })
        };
        let first = scrape(0);
        assert!(
            first.contains("# TYPE pointfarm_store_rebuilds counter"),
            "{first}"
        );
        assert_eq!(value(&first, "pointfarm_store_rebuilds_total"), Some(0.0));
        // Scrapes in turn, each with the rebuilds its state read and the total it shows: a
        // state read before the last scrape's does not take it back.
        for (rebuilds, shown) in [(1, 1.0), (1, 1.0), (0, 1.0), (3, 3.0)] {
            assert_eq!(
                value(&scrape(rebuilds), "pointfarm_store_rebuilds_total"),
                Some(shown),
                "after a state of {rebuilds} rebuilds"
            );
        }
    }
}

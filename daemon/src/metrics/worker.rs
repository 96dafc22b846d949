//! The metrics of a `pointfarm worker` process: its own frames, their stages, and its
//! caches. Named `pointfarm_worker_*`, so that they add up apart from the daemon's, which
//! counts the reports of all its workers.

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::registry::Registry;

use super::{encode, CacheCounters, StageSeconds};
use crate::lease::FrameOutcome;

/// Which node cache of a level-of-detail render.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct CacheLabels {
    cache: &'static str,
}

const GPU: CacheLabels = CacheLabels { cache: "gpu" };
const HOST: CacheLabels = CacheLabels { cache: "host" };

/// A worker's metrics; counting costs next to nothing, so a worker counts whether or not it
/// serves them.
#[derive(Debug)]
pub struct WorkerMetrics {
    registry: Registry,
    frames_rendered: Counter,
    frames_failed: Counter,
    stage_seconds: StageSeconds,
    dataset_cache: CacheCounters,
    node_cache_hits: Family<CacheLabels, Counter>,
    node_cache_misses: Family<CacheLabels, Counter>,
}

impl Default for WorkerMetrics {
    fn default() -> Self {
        Self::new()
    }
}

impl WorkerMetrics {
    pub fn new() -> Self {
        let mut metrics = Self {
            registry: Registry::with_prefix("pointfarm_worker"),
            frames_rendered: Counter::default(),
            frames_failed: Counter::default(),
            stage_seconds: StageSeconds::new(),
            dataset_cache: CacheCounters::default(),
            node_cache_hits: Family::default(),
            node_cache_misses: Family::default(),
        };
        // Both caches' series from the start, at zero.
        for cache in [GPU, HOST] {
            metrics.node_cache_hits.get_or_create(&cache).inc_by(0);
            metrics.node_cache_misses.get_or_create(&cache).inc_by(0);
        }
        let registry = &mut metrics.registry;
        registry.register(
            "frames_rendered",
            "Frames this worker rendered (handed in or not)",
            metrics.frames_rendered.clone(),
        );
        registry.register(
            "frames_failed",
            "Frames this worker failed to render, and reported so",
            metrics.frames_failed.clone(),
        );
        registry.register(
            "frame_stage_seconds",
            "Time of each stage of the frames this worker rendered",
            metrics.stage_seconds.family.clone(),
        );
        metrics.dataset_cache.register(
            registry,
            "dataset_cache",
            "Datasets this worker loaded from its dataset cache",
            "Datasets this worker decoded from their files (then kept in its cache)",
        );
        registry.register(
            "node_cache_hits",
            "Level-of-detail nodes a frame's cut found in a node cache: gpu (already on the \
             GPU) or host (in host memory, then uploaded)",
            metrics.node_cache_hits.clone(),
        );
        registry.register(
            "node_cache_misses",
            "Level-of-detail nodes a frame's cut did not find in a node cache: gpu (uploaded) \
             or host (read from the store)",
            metrics.node_cache_misses.clone(),
        );
        metrics
    }

    /// A frame was rendered, with what its worker reports of it.
    pub fn frame_rendered(&self, outcome: &FrameOutcome) {
        self.frames_rendered.inc();
        self.stage_seconds.observe(&outcome.timings);
        self.dataset_cache.count(outcome.dataset_cache_hit);
        if let Some(cut) = &outcome.cut {
            // A node missing from the GPU cache is uploaded; one missing from the host cache
            // is read.
            for (cache, hits, misses) in [
                (&GPU, cut.gpu_hits, cut.gpu_uploaded),
                (&HOST, cut.host_hits, cut.nodes_read),
            ] {
                self.node_cache_hits.get_or_create(cache).inc_by(hits);
                self.node_cache_misses.get_or_create(cache).inc_by(misses);
            }
        }
    }

    /// A frame failed on this worker.
    pub fn frame_failed(&self) {
        self.frames_failed.inc();
    }

    /// The metrics in Prometheus's text format ([`super::CONTENT_TYPE`]).
    pub fn text(&self) -> String {
        encode(&self.registry)
    }
}

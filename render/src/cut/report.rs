//! `CutReport`: what a frame's cut held and what loading it did.

use serde::{Deserialize, Serialize};

use super::select::Cut;

/// How complete a frame is that drew `drawn` of a dataset's `total` points (a preview's from
/// a sample or a coarse cut, or a cut's): their share, at most 1, and 1 for a dataset without
/// points (nothing is missing from it).
pub fn completeness(drawn: u64, total: u64) -> f64 {
    if total == 0 {
        1.0
    } else {
        (drawn as f64 / total as f64).min(1.0)
    }
}

/// What a frame's cut drew and loaded, in counts: the part of a [`CutReport`] that a
/// frame's record keeps (the daemon stores it with each frame).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CutCounts {
    /// Nodes and points the frame drew.
    pub nodes: u64,
    pub points_rendered: u64,
    /// Points of the whole dataset.
    pub points_total: u64,
    /// Whether a bound, not the pixel error, stopped the cut: the GPU node cache's size or
    /// the points the frame's pixels warrant (`MAX_CUT_POINTS_PER_PIXEL`).
    pub limited_by_budget: bool,
    /// Cut nodes already on the GPU.
    pub gpu_hits: u64,
    /// Cut nodes written to the GPU, and resident ones evicted for them.
    pub gpu_uploaded: u64,
    pub gpu_evicted: u64,
    /// Of the uploaded nodes: those the host cache held, and those read from the store.
    pub host_hits: u64,
    pub nodes_read: u64,
    /// Bytes read from the store by this frame, and by the read-ahead before it.
    pub bytes_read: u64,
    pub read_ahead_bytes: u64,
    /// Of a dataset by URL, since the frame before (its opening and read-ahead included):
    /// requests to the object store, the payload bytes they fetched, and the bytes the
    /// worker's range cache served instead.
    #[serde(default)]
    pub object_requests: u64,
    #[serde(default)]
    pub object_bytes: u64,
    #[serde(default)]
    pub range_cache_bytes: u64,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct CutReport {
    #[serde(flatten)]
    pub counts: CutCounts,
    /// Bytes the caches hold after the frame.
    pub host_cache_bytes: u64,
    pub gpu_cache_bytes: u64,
    /// Hierarchy pages the frame's selection read, and their bytes: a dataset whose pages
    /// are read lazily reads those its cuts reach.
    pub hierarchy_pages_read: u64,
    pub hierarchy_page_bytes: u64,
    /// The load stages: selecting the cut, waiting for the read-ahead, waiting for waves of
    /// nodes to be read, decoded and prepared (the part that uploading the wave before did not
    /// hide; the frame's "load" stage is the two waits), and the time spent preparing them
    /// (colors, order, quantisation), on a thread of its own while waves are read and
    /// uploaded; their transfer to the GPU is the frame's "upload" stage.
    pub select_ms: f64,
    pub wait_ms: f64,
    pub load_ms: f64,
    pub prepare_ms: f64,
}

impl CutReport {
    pub(crate) fn of_cut(cut: &Cut, points_total: u64) -> Self {
        Self {
            counts: CutCounts {
                nodes: cut.nodes.len() as u64,
                points_rendered: cut.points(),
                points_total,
                limited_by_budget: cut.limited_by_budget,
                ..Default::default()
            },
            ..Default::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::completeness;

    #[test]
    fn completeness_is_the_share_drawn_at_most_one() {
        // A cut may draw more points than the files hold (a node's points stand for others).
        let cases = [
            (25, 100, 0.25),
            (100, 100, 1.0),
            (120, 100, 1.0),
            (0, 0, 1.0),
        ];
        for (drawn, total, share) in cases {
            assert_eq!(completeness(drawn, total), share, "{drawn} of {total}");
        }
    }
}

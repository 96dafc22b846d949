//! A COPC file's child hierarchy pages read as they are needed: by a frame's cut
//! ([`CopcPageReader`], the dataset's [`HierarchyPages`]), and at open by the color ranges'
//! sample of the coarsest nodes ([`coarse_pages`]).

use std::sync::{Arc, Mutex};

use super::bytes::CopcBytes;
use super::hierarchy::CopcPages;
use crate::lod::{HierarchyPages, LodError, LodHierarchy, NodeKey, PagesRead};

/// Reads a COPC file's unread hierarchy pages, each checked as the pages read at open were.
pub(crate) struct CopcPageReader {
    bytes: Arc<CopcBytes>,
    /// The file's root spacing, which every merged hierarchy halves per level.
    root_spacing: f64,
    /// What the pages read so far list.
    pages: Mutex<CopcPages>,
}

impl CopcPageReader {
    pub(crate) fn new(bytes: Arc<CopcBytes>, root_spacing: f64, pages: CopcPages) -> Self {
        Self {
            bytes,
            root_spacing,
            pages: Mutex::new(pages),
        }
    }
}

impl HierarchyPages for CopcPageReader {
    fn read_pages(
        &self,
        current: &LodHierarchy,
        keys: &[NodeKey],
    ) -> Result<(LodHierarchy, PagesRead), LodError> {
        // Nothing is read under a poisoned lock: the pages it holds may be part way.
        let mut pages = self
            .pages
            .lock()
            .map_err(|_| LodError::CorruptHierarchy("the COPC page reader is poisoned".into()))?;
        // Read into a copy, so that a page that fails its checks fails every frame that
        // reaches it the same way.
        let mut next = pages.clone();
        next.read(&self.bytes, keys)?;
        let read = PagesRead {
            pages: (next.pages - pages.pages) as u64,
            bytes: next.page_bytes - pages.page_bytes,
        };
        let hierarchy = next.hierarchy(current.cube, current.stats.clone(), self.root_spacing);
        *pages = next;
        Ok((hierarchy, read))
    }
}

/// The unread pages of `hierarchy` whose nodes could be among the coarsest `sample_points`
/// points that the color ranges are sampled from (`lod::for_each_coarse_node`): those whose
/// key comes before the sample is full, in key order, since a page's nodes all sort after its
/// own key. Once none is left, the sample is the one the whole hierarchy gives.
pub(crate) fn coarse_pages(hierarchy: &LodHierarchy, sample_points: u64) -> Vec<NodeKey> {
    let mut sampled = 0u64;
    let mut needed = Vec::new();
    // Sorted by key, as the sample takes them.
    for node in hierarchy.nodes() {
        if sampled >= sample_points {
            break;
        }
        if hierarchy.is_unread_page(node.key) {
            needed.push(node.key);
        } else {
            sampled += u64::from(node.point_count);
        }
    }
    needed
}

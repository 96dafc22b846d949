//! Hierarchies read a page at a time (a COPC file's, read lazily): a frame's walk names the
//! unread pages it reaches, they are read together, merged into a new hierarchy that replaces
//! the dataset's, and the walk runs again until it reaches none. The cut is then the one the
//! whole hierarchy gives, so the same request gives the same image whatever was read before.

use std::sync::{Arc, Mutex, RwLock};

use super::select::{walk_cut, Cut, CutView};
use crate::lod::{LodError, LodHierarchy, NodeKey};

/// Hierarchy pages read, and their bytes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PagesRead {
    pub pages: u64,
    pub bytes: u64,
}

impl PagesRead {
    fn add(&mut self, other: PagesRead) {
        self.pages += other.pages;
        self.bytes += other.bytes;
    }
}

/// Where the pages of a hierarchy with unread pages are read from.
pub trait HierarchyPages: Send + Sync {
    /// `current` with the pages of `keys` (unread pages of it) read, checked and merged in,
    /// and what reading them took: at least one page, none read before (a page listed again
    /// is an error). A page that fails its checks fails the whole call, which leaves what was
    /// read before as it was.
    fn read_pages(
        &self,
        current: &LodHierarchy,
        keys: &[NodeKey],
    ) -> Result<(LodHierarchy, PagesRead), LodError>;
}

/// A frame's cut and the hierarchy it was selected in (the one its nodes are read with).
pub(crate) struct Selected {
    pub cut: Cut,
    pub hierarchy: Arc<LodHierarchy>,
    /// Pages this selection read.
    pub pages_read: PagesRead,
}

/// A hierarchy whose pages are read as frames reach them.
pub(crate) struct LazyLevels {
    current: RwLock<Arc<LodHierarchy>>,
    pages: Arc<dyn HierarchyPages>,
    /// Every page read since the dataset was opened; held while a round reads, so that two
    /// frames needing one page read it once.
    read: Mutex<PagesRead>,
}

impl LazyLevels {
    pub(crate) fn new(hierarchy: Arc<LodHierarchy>, pages: Arc<dyn HierarchyPages>) -> Self {
        Self {
            current: RwLock::new(hierarchy),
            pages,
            read: Mutex::new(PagesRead::default()),
        }
    }

    /// The hierarchy with every page read so far.
    pub(crate) fn current(&self) -> Arc<LodHierarchy> {
        // A poisoned lock still holds a whole hierarchy: it is only ever replaced whole.
        let current = self.current.read().unwrap_or_else(|e| e.into_inner());
        Arc::clone(&current)
    }

    pub(crate) fn pages_read(&self) -> PagesRead {
        *self.read.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The cut for `view`, reading the pages each walk reaches until a walk reaches none.
    pub(crate) fn select(&self, view: &CutView<'_>) -> Result<Selected, LodError> {
        let mut pages_read = PagesRead::default();
        loop {
            let hierarchy = self.current();
            let walk = walk_cut(&hierarchy, view);
            if walk.unread_pages.is_empty() {
                return Ok(Selected {
                    cut: walk.cut,
                    hierarchy,
                    pages_read,
                });
            }
            let mut read = self.read.lock().unwrap_or_else(|e| e.into_inner());
            // Another frame may have read some of them meanwhile.
            let latest = self.current();
            let keys: Vec<NodeKey> = walk
                .unread_pages
                .into_iter()
                .filter(|&key| latest.is_unread_page(key))
                .collect();
            if keys.is_empty() {
                continue;
            }
            let (merged, round) = self.pages.read_pages(&latest, &keys)?;
            // Each round must read a page, or the walk would ask for them forever; a source
            // reads each page once, so the rounds end.
            if round.pages == 0 {
                let keys: Vec<String> = keys.iter().map(NodeKey::to_string).collect();
                return Err(LodError::CorruptHierarchy(format!(
                    "the pages of nodes {} were asked for but none was read",
                    keys.join(", ")
                )));
            }
            *self.current.write().unwrap_or_else(|e| e.into_inner()) = Arc::new(merged);
            read.add(round);
            pages_read.add(round);
        }
    }
}

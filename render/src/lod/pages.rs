//! Hierarchies read a page at a time (a COPC file's, read lazily): a frame's walk names the
//! unread pages it reaches, they are read together, merged into a new hierarchy that replaces
//! the dataset's, and the walk runs again until it reaches none. The cut is then the one the
//! whole hierarchy gives, so the same request gives the same image whatever was read before
//! (the walk is the cut renderer's: `cut/dataset.rs`).

use std::sync::{Arc, Mutex, RwLock};

use super::{LodError, LodHierarchy, NodeKey};

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

    /// What `walk` gives over the hierarchy (and that hierarchy, and the pages read), reading
    /// the unread pages each walk reaches (the second of what it returns) until a walk
    /// reaches none.
    pub(crate) fn walk_until_read<T>(
        &self,
        mut walk: impl FnMut(&LodHierarchy) -> (T, Vec<NodeKey>),
    ) -> Result<(T, Arc<LodHierarchy>, PagesRead), LodError> {
        let mut pages_read = PagesRead::default();
        loop {
            let hierarchy = self.current();
            let (walked, unread_pages) = walk(&hierarchy);
            if unread_pages.is_empty() {
                return Ok((walked, hierarchy, pages_read));
            }
            let mut read = self.read.lock().unwrap_or_else(|e| e.into_inner());
            // Another frame may have read some of them meanwhile.
            let latest = self.current();
            let keys: Vec<NodeKey> = unread_pages
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

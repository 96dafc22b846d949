//! A [`LodDataset`]'s cuts: selected in its hierarchy, reading the hierarchy pages a frame's
//! walk reaches first where they are read lazily (`lod/pages.rs`).

use std::sync::Arc;

use super::select::{select_cut, walk_cut, Cut, CutView};
use crate::lod::{LodDataset, LodError, LodHierarchy, PagesRead};

/// A frame's cut and the hierarchy it was selected in (the one its nodes are read with).
pub(crate) struct Selected {
    pub cut: Cut,
    pub hierarchy: Arc<LodHierarchy>,
    /// Pages this selection read.
    pub pages_read: PagesRead,
}

impl LodDataset {
    /// The cut for `view`: reading the hierarchy pages it reaches first where they are read
    /// lazily, so it is the cut of the whole hierarchy.
    pub(crate) fn select(&self, view: &CutView<'_>) -> Result<Selected, LodError> {
        match &self.lazy {
            Some(lazy) => {
                let (cut, hierarchy, pages_read) = lazy.walk_until_read(|hierarchy| {
                    let walk = walk_cut(hierarchy, view);
                    (walk.cut, walk.unread_pages)
                })?;
                Ok(Selected {
                    cut,
                    hierarchy,
                    pages_read,
                })
            }
            None => Ok(Selected {
                cut: select_cut(&self.hierarchy, view),
                hierarchy: Arc::clone(&self.hierarchy),
                pages_read: PagesRead::default(),
            }),
        }
    }

    /// The cut for `view`, as a frame selects it.
    pub fn select_cut(&self, view: &CutView<'_>) -> Result<Cut, LodError> {
        self.select(view).map(|selected| selected.cut)
    }
}

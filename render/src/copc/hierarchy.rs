//! A COPC file's hierarchy pages walked into the nodes of a [`LodHierarchy`]: every entry's
//! voxel key, point count and LAZ chunk (offset, byte size), child pages followed.
//!
//! [`CopcPages`] holds what the pages read so far list; a child page not read yet is known by
//! the key of the node whose subtree it holds. Rendering reads the root page when the file is
//! opened and the others as frames reach them (`lazy.rs`); `describe`, a daemon and an export
//! read them all at once ([`read_all_pages`]). Either way, everything read from a page is
//! checked, by the same code, before it is used: each page must lie after the point data and
//! inside the file, be visited once (a page that points at itself or an ancestor is a loop),
//! and all pages together may not hold more bytes than the file; each key must be a cell of
//! its level inside the subtree of its page's node, listed once, whose parent is listed; each
//! chunk must lie inside the file; the points of the entries read may never exceed the
//! header's count, and once every page is read they must add up to it.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::ops::Range;
use std::path::PathBuf;
use std::sync::Arc;

use super::bytes::CopcBytes;
use super::error::CopcError;
use super::header::{check_page, check_page_bounds, CopcHeader, PageRef, ENTRY_BYTES};
use super::node_grids::NodeGrids;
use crate::lod::{DatasetStats, LodHierarchy, NodeInfo, NodeKey, RootCube, MAX_LEVEL};

/// What the hierarchy pages read so far list, and what reading them took.
#[derive(Clone)]
pub(crate) struct CopcPages {
    path: PathBuf,
    file_len: u64,
    offset_to_point_data: u64,
    point_count: u64,
    /// Offsets of the pages read: a second visit is a loop.
    visited: HashSet<u64>,
    pub pages: usize,
    pub page_bytes: u64,
    nodes: HashMap<NodeKey, NodeInfo>,
    /// Keys whose entries live in a child page: parents as much as listed nodes are.
    page_keys: HashSet<NodeKey>,
    /// The child pages not read yet, by their node's key.
    unread: BTreeMap<NodeKey, PageRef>,
    /// Points of the entries read.
    points: u64,
    /// Inner nodes' sampling grids, where the file records them.
    grids: Arc<NodeGrids>,
}

/// One raw entry.
struct Entry {
    key: [i32; 4],
    offset: u64,
    byte_size: i32,
    point_count: i32,
}

impl Entry {
    fn parse(bytes: &[u8]) -> Self {
        let i32_at = |at: usize| {
            i32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
        };
        let mut offset = [0u8; 8];
        offset.copy_from_slice(&bytes[16..24]);
        Self {
            key: [i32_at(0), i32_at(4), i32_at(8), i32_at(12)],
            offset: u64::from_le_bytes(offset),
            byte_size: i32_at(24),
            point_count: i32_at(28),
        }
    }
}

/// Reads every hierarchy page of `bytes`, checked, the points of all entries against the
/// header's count.
pub(crate) fn read_all_pages(
    bytes: &CopcBytes,
    header: &CopcHeader,
) -> Result<CopcPages, CopcError> {
    let mut pages = read_root_page(bytes, header)?;
    while !pages.unread.is_empty() {
        let keys: Vec<NodeKey> = pages.unread.keys().copied().collect();
        pages.read(bytes, &keys)?;
    }
    Ok(pages)
}

/// Reads the root hierarchy page of `bytes`, checked; child pages are left unread.
pub(crate) fn read_root_page(
    bytes: &CopcBytes,
    header: &CopcHeader,
) -> Result<CopcPages, CopcError> {
    let path = bytes.name();
    let mut pages = CopcPages {
        path: path.to_owned(),
        file_len: header.file_len,
        offset_to_point_data: header.offset_to_point_data,
        point_count: header.point_count,
        visited: HashSet::new(),
        pages: 0,
        page_bytes: 0,
        nodes: HashMap::new(),
        page_keys: HashSet::new(),
        unread: BTreeMap::new(),
        points: 0,
        grids: Arc::clone(&header.node_grids),
    };
    let root = header.info.root_page;
    check_page(path, header, root, "the root hierarchy page")?;
    let read = bytes.read_at(root.offset, root.size)?;
    pages.add_page(root, None, &read)?;
    pages.check_parents()?;
    pages.check_total()?;
    Ok(pages)
}

impl CopcPages {
    fn bad(&self, reason: String) -> CopcError {
        CopcError::hierarchy(&self.path, reason)
    }

    /// Whether every page has been read.
    pub fn all_read(&self) -> bool {
        self.unread.is_empty()
    }

    /// Reads the child pages of `keys` (unread pages; others are passed over) together: their
    /// bytes in one read of many ranges, their entries checked in key order. An error leaves
    /// this part way through: a caller that goes on after one reads into a copy.
    pub fn read(&mut self, bytes: &CopcBytes, keys: &[NodeKey]) -> Result<(), CopcError> {
        let mut wanted: Vec<(NodeKey, PageRef)> = keys
            .iter()
            .filter_map(|key| self.unread.get(key).map(|&page| (*key, page)))
            .collect();
        wanted.sort_by_key(|&(key, _)| key);
        wanted.dedup_by_key(|&mut (key, _)| key);
        // Their bounds were checked when their entries were read; together they may not
        // hold more bytes than the file either, checked before any is read.
        let round: u64 = wanted.iter().map(|(_, page)| page.size).sum();
        self.check_page_bytes(self.page_bytes.saturating_add(round))?;
        let ranges: Vec<Range<u64>> = wanted
            .iter()
            .map(|(_, page)| page.offset..page.offset + page.size)
            .collect();
        let read = bytes.read_many(&ranges)?;
        for ((key, page), page_bytes) in wanted.into_iter().zip(read) {
            self.unread.remove(&key);
            self.add_page(page, Some(key), &page_bytes)?;
        }
        self.check_parents()?;
        self.check_total()
    }

    /// The pages read may not hold more bytes than the file: `page_bytes` of them.
    fn check_page_bytes(&self, page_bytes: u64) -> Result<(), CopcError> {
        if page_bytes > self.file_len {
            return Err(self.bad(format!(
                "the hierarchy pages hold more bytes ({page_bytes}) than the file ({})",
                self.file_len
            )));
        }
        Ok(())
    }

    /// Once every page is read, the points of all entries must be the header's count.
    fn check_total(&self) -> Result<(), CopcError> {
        if self.all_read() && self.points != self.point_count {
            return Err(self.bad(format!(
                "its entries hold {} points, the header says {}",
                self.points, self.point_count
            )));
        }
        Ok(())
    }

    /// The page at `page` (the root page, or the child page of node `owner`), its `bytes`
    /// checked entry by entry and added.
    fn add_page(
        &mut self,
        page: PageRef,
        owner: Option<NodeKey>,
        bytes: &[u8],
    ) -> Result<(), CopcError> {
        let what = match owner {
            None => "the root hierarchy page".to_string(),
            Some(key) => format!("the hierarchy page of node {key}"),
        };
        if !self.visited.insert(page.offset) {
            return Err(self.bad(format!(
                "{what} at offset {} was already read: the pages form a loop",
                page.offset
            )));
        }
        self.page_bytes += page.size;
        self.check_page_bytes(self.page_bytes)?;
        self.pages += 1;
        for raw in bytes.chunks_exact(ENTRY_BYTES as usize) {
            self.add_entry(&what, owner, Entry::parse(raw))?;
        }
        Ok(())
    }

    fn add_entry(
        &mut self,
        what: &str,
        owner: Option<NodeKey>,
        entry: Entry,
    ) -> Result<(), CopcError> {
        let key = NodeKey::from_voxel_key(entry.key).ok_or_else(|| {
            self.bad(format!(
                "{what} lists voxel key {:?}, not a cell of its level (0 to {MAX_LEVEL})",
                entry.key
            ))
        })?;
        if let Some(owner) = owner.filter(|&owner| !in_subtree(key, owner)) {
            return Err(self.bad(format!(
                "{what} lists node {key}, outside the subtree of node {owner}"
            )));
        }
        match entry.point_count {
            -1 => {
                let size = u64::try_from(entry.byte_size).map_err(|_| {
                    self.bad(format!(
                        "node {key}'s child page has {} bytes",
                        entry.byte_size
                    ))
                })?;
                // A key whose page was read already is read again, and found a loop if it is
                // the same page.
                if self.unread.contains_key(&key) {
                    return Err(self.bad(format!("node {key}'s child page is listed twice")));
                }
                self.page_keys.insert(key);
                let page = PageRef {
                    offset: entry.offset,
                    size,
                };
                // Checked now, as every page once was when all were read at open.
                let what = format!("the hierarchy page of node {key}");
                check_page_bounds(
                    &self.path,
                    self.offset_to_point_data,
                    self.file_len,
                    page,
                    &what,
                )?;
                self.unread.insert(key, page);
            }
            0 => self.insert(NodeInfo::empty(key))?,
            count if count > 0 => {
                let count = count as u32;
                let byte_len = u32::try_from(entry.byte_size)
                    .ok()
                    .filter(|&len| len > 0)
                    .ok_or_else(|| {
                        self.bad(format!("node {key}'s chunk has {} bytes", entry.byte_size))
                    })?;
                let end = entry.offset.checked_add(u64::from(byte_len));
                if entry.offset < self.offset_to_point_data
                    || end.is_none_or(|end| end > self.file_len)
                {
                    return Err(self.bad(format!(
                        "node {key}'s chunk ({byte_len} bytes at offset {}) lies beyond the point data ({}..{} bytes)",
                        entry.offset, self.offset_to_point_data, self.file_len
                    )));
                }
                self.points += u64::from(count);
                if self.points > self.point_count {
                    return Err(self.bad(format!(
                        "its entries hold more points than the header's {}",
                        self.point_count
                    )));
                }
                let node = NodeInfo {
                    point_count: count,
                    sample_grid: self.grids.get(&key).copied().unwrap_or(0),
                    ..NodeInfo::empty(key)
                };
                self.insert(node.in_one_piece(entry.offset, byte_len))?;
            }
            other => {
                return Err(self.bad(format!("node {key} has a point count of {other}")));
            }
        }
        Ok(())
    }

    fn insert(&mut self, node: NodeInfo) -> Result<(), CopcError> {
        if self.nodes.insert(node.key, node).is_some() {
            return Err(self.bad(format!("node {} is listed twice", node.key)));
        }
        Ok(())
    }

    /// Every key read has its parent listed, or lying in a page not read yet (which a later
    /// read checks).
    fn check_parents(&self) -> Result<(), CopcError> {
        let listed = |key: &NodeKey| self.nodes.contains_key(key) || self.page_keys.contains(key);
        for key in self.nodes.keys().chain(&self.page_keys) {
            let Some(parent) = key.parent() else {
                continue;
            };
            if listed(&parent) {
                continue;
            }
            let mut above = Some(parent);
            let pending = std::iter::from_fn(|| {
                let key = above?;
                above = key.parent();
                Some(key)
            })
            .any(|ancestor| self.unread.contains_key(&ancestor));
            if !pending {
                return Err(self.bad(format!(
                    "node {key} is listed without its parent {parent}: its points could never be reached"
                )));
            }
        }
        Ok(())
    }

    /// The hierarchy of the nodes read so far (a page's node listed without points of its
    /// own when its page leaves it out, or is not read yet), with `stats` and the file's cube,
    /// point count and root spacing.
    pub fn hierarchy(
        &self,
        cube: RootCube,
        stats: DatasetStats,
        root_spacing: f64,
    ) -> LodHierarchy {
        let mut nodes = self.nodes.clone();
        for &key in &self.page_keys {
            nodes.entry(key).or_insert(NodeInfo::empty(key));
        }
        LodHierarchy::of_pages(
            cube,
            self.point_count,
            stats,
            root_spacing,
            nodes.into_values().collect(),
            &self.page_keys,
            self.unread.keys().copied().collect(),
        )
    }

    /// Nodes listed so far with points.
    pub fn nodes_with_points(&self) -> impl Iterator<Item = &NodeInfo> + '_ {
        self.nodes.values().filter(|node| node.point_count > 0)
    }
}

/// Whether `key` is `owner` or lies below it.
fn in_subtree(key: NodeKey, owner: NodeKey) -> bool {
    key.level >= owner.level && {
        let shift = u32::from(key.level - owner.level);
        [key.x >> shift, key.y >> shift, key.z >> shift] == [owner.x, owner.y, owner.z]
    }
}

//! A COPC file's hierarchy pages walked into the nodes of a [`LodHierarchy`]: every entry's
//! voxel key, point count and LAZ chunk (offset, byte size), child pages followed.
//!
//! All pages are read when the file is opened (a page is 32 bytes an entry, so even a large
//! file's hierarchy is small next to its points). Everything read from a page is checked
//! before it is used: each page must lie after the point data and inside the file, be
//! visited once (a page that points at itself or an ancestor is a loop), and all pages
//! together may not hold more bytes than the file; each key must be a cell of its level
//! whose parent is listed; each chunk must lie inside the file; the points of all entries
//! must add up to the header's count.

use std::collections::{HashMap, HashSet};
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;

use super::error::CopcError;
use super::header::{check_page, CopcHeader, PageRef, ENTRY_BYTES};
use crate::lod::{NodeInfo, NodeKey, MAX_LEVEL};

/// The nodes the pages list, and what reading them took.
pub(crate) struct CopcNodeList {
    pub nodes: Vec<NodeInfo>,
    pub pages: usize,
    pub page_bytes: u64,
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

/// Reads every hierarchy page of `file` from the root page on.
pub(crate) fn read_pages(
    path: &Path,
    file: &File,
    header: &CopcHeader,
) -> Result<CopcNodeList, CopcError> {
    let bad = |reason: String| CopcError::hierarchy(path, reason);
    let mut pending = vec![(header.info.root_page, None::<NodeKey>)];
    let mut visited: HashSet<u64> = HashSet::new();
    let mut page_bytes = 0u64;
    let mut pages = 0;
    let mut nodes: HashMap<NodeKey, NodeInfo> = HashMap::new();
    // Keys whose entries live in a child page: parents as much as listed nodes are.
    let mut page_keys: HashSet<NodeKey> = HashSet::new();
    let mut points = 0u64;
    while let Some((page, owner)) = pending.pop() {
        let what = match owner {
            None => "the root hierarchy page".to_string(),
            Some(key) => format!("the hierarchy page of node {key}"),
        };
        check_page(path, header, page, &what)?;
        if !visited.insert(page.offset) {
            return Err(bad(format!(
                "{what} at offset {} was already read: the pages form a loop",
                page.offset
            )));
        }
        page_bytes += page.size;
        if page_bytes > header.file_len {
            return Err(bad(format!(
                "the hierarchy pages hold more bytes ({page_bytes}) than the file ({})",
                header.file_len
            )));
        }
        pages += 1;
        // Bounded by the file's size, as just checked.
        let mut bytes = vec![0u8; page.size as usize];
        file.read_exact_at(&mut bytes, page.offset)
            .map_err(|e| CopcError::io(path, e))?;
        for raw in bytes.chunks_exact(ENTRY_BYTES as usize) {
            let entry = Entry::parse(raw);
            let key = node_key(entry.key).ok_or_else(|| {
                bad(format!(
                    "{what} lists voxel key {:?}, not a cell of its level (0 to {MAX_LEVEL})",
                    entry.key
                ))
            })?;
            match entry.point_count {
                -1 => {
                    let size = u64::try_from(entry.byte_size).map_err(|_| {
                        bad(format!(
                            "node {key}'s child page has {} bytes",
                            entry.byte_size
                        ))
                    })?;
                    page_keys.insert(key);
                    pending.push((
                        PageRef {
                            offset: entry.offset,
                            size,
                        },
                        Some(key),
                    ));
                }
                0 => {
                    insert(&mut nodes, path, NodeInfo::empty(key))?;
                }
                count if count > 0 => {
                    let count = count as u32;
                    let byte_len = u32::try_from(entry.byte_size)
                        .ok()
                        .filter(|&len| len > 0)
                        .ok_or_else(|| {
                            bad(format!("node {key}'s chunk has {} bytes", entry.byte_size))
                        })?;
                    let end = entry.offset.checked_add(u64::from(byte_len));
                    if entry.offset < header.offset_to_point_data
                        || end.is_none_or(|end| end > header.file_len)
                    {
                        return Err(bad(format!(
                            "node {key}'s chunk ({byte_len} bytes at offset {}) lies beyond the point data ({}..{} bytes)",
                            entry.offset, header.offset_to_point_data, header.file_len
                        )));
                    }
                    points += u64::from(count);
                    if points > header.point_count {
                        return Err(bad(format!(
                            "its entries hold more points than the header's {}",
                            header.point_count
                        )));
                    }
                    insert(
                        &mut nodes,
                        path,
                        NodeInfo {
                            key,
                            point_count: count,
                            sample_grid: 0,
                            child_mask: 0,
                            offset: entry.offset,
                            byte_len,
                        },
                    )?;
                }
                other => {
                    return Err(bad(format!("node {key} has a point count of {other}")));
                }
            }
        }
    }
    if points != header.point_count {
        return Err(bad(format!(
            "its entries hold {points} points, the header says {}",
            header.point_count
        )));
    }
    // A page's own node may be left out of it when it has no points of its own.
    for key in page_keys {
        nodes.entry(key).or_insert(NodeInfo::empty(key));
    }
    for key in nodes.keys() {
        if let Some(parent) = key.parent() {
            if !nodes.contains_key(&parent) {
                return Err(bad(format!(
                    "node {key} is listed without its parent {parent}: its points could never be reached"
                )));
            }
        }
    }
    let mut nodes: Vec<NodeInfo> = nodes.into_values().collect();
    nodes.sort_by_key(|n| n.key);
    Ok(CopcNodeList {
        nodes,
        pages,
        page_bytes,
    })
}

/// A voxel key as a node key: a level the octree may have and a cell inside it.
fn node_key([level, x, y, z]: [i32; 4]) -> Option<NodeKey> {
    let level = u8::try_from(level).ok().filter(|&l| l <= MAX_LEVEL)?;
    let cells = 1i64 << level;
    let cell = |v: i32| (0..cells).contains(&i64::from(v)).then_some(v as u32);
    Some(NodeKey {
        level,
        x: cell(x)?,
        y: cell(y)?,
        z: cell(z)?,
    })
}

fn insert(
    nodes: &mut HashMap<NodeKey, NodeInfo>,
    path: &Path,
    node: NodeInfo,
) -> Result<(), CopcError> {
    if nodes.insert(node.key, node).is_some() {
        return Err(CopcError::hierarchy(
            path,
            format!("node {} is listed twice", node.key),
        ));
    }
    Ok(())
}

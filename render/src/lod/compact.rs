//! A store's payload rewritten as one file holding only the records its hierarchy and regions
//! list, in the order they lay in: the layers a chain of growths stacked up and the dead bytes
//! their updates left are dropped (`layers.rs` says when). Meant for a store being grown, in
//! a folder of its own until it is checked: the payload is replaced before the hierarchy that
//! describes it is written.

use std::fs::File;
use std::io::Write;
use std::ops::Range;
use std::path::PathBuf;

use super::error::LodError;
use super::hierarchy::{LodHierarchy, NodeInfo};
use super::store::{check_within, LodStore};

/// Bytes copied at once.
const COPY_BYTES: u64 = 1 << 20;

/// What a compaction did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Compacted {
    /// Payload files before: the layers and the store's own.
    pub files_before: usize,
    pub bytes_before: u64,
    pub bytes_after: u64,
}

/// Rewrites `store`'s payload as one file of its live records and writes the hierarchy and
/// regions that address it.
pub fn compact(store: &LodStore) -> Result<Compacted, LodError> {
    let hierarchy = store.read_hierarchy()?;
    let regions = store.read_regions()?;
    let files_before = store.payload_files();
    let bytes_before = store.payload_bytes()?;
    let roots: Vec<NodeInfo> = regions
        .iter()
        .flat_map(|r| r.regions.iter().filter_map(|region| region.root))
        .collect();
    let spans = live_spans(hierarchy.stored_nodes().chain(&roots), bytes_before)?;

    let path = PathBuf::from({
        let mut name = store.payload_path().as_os_str().to_owned();
        name.push(".compact");
        name
    });
    let failed = |e: std::io::Error| LodError::payload(&path, e);
    let mut out = std::io::BufWriter::with_capacity(
        COPY_BYTES as usize,
        File::create(&path).map_err(failed)?,
    );
    let mut buffer = vec![0u8; COPY_BYTES as usize];
    for span in &spans {
        let mut at = span.old.start;
        while at < span.old.end {
            let n = (span.old.end - at).min(COPY_BYTES) as usize;
            store.read_payload(&mut buffer[..n], at)?;
            out.write_all(&buffer[..n]).map_err(failed)?;
            at += n as u64;
        }
    }
    let file = out.into_inner().map_err(|e| failed(e.into_error()))?;
    file.sync_all().map_err(failed)?;
    drop(file);

    let moved = |info: &NodeInfo| relocated(info, &spans);
    let nodes: Vec<NodeInfo> = hierarchy.nodes().iter().map(moved).collect();
    let compacted = LodHierarchy::assemble(
        hierarchy.cube,
        hierarchy.point_count,
        hierarchy.max_leaf_points,
        hierarchy.stats.clone(),
        nodes,
    )
    .with_attributes(hierarchy.attributes().cloned());
    let regions = regions.map(|mut regions| {
        for region in &mut regions.regions {
            region.root = region.root.as_ref().map(moved);
        }
        regions
    });
    store.replace_payload(&path)?;
    store.write_hierarchy_with(&compacted, regions.as_ref())?;
    Ok(Compacted {
        files_before,
        bytes_before,
        bytes_after: store.payload_bytes()?,
    })
}

/// A run of live bytes: where it lay, and where it starts in the compacted file.
struct Span {
    old: Range<u64>,
    new_start: u64,
}

/// The live bytes of `nodes` (records and attributes sections) within a payload of
/// `payload_bytes` (an attributes section past it fails its read), joined where they touch
/// or overlap, in file order.
fn live_spans<'a>(
    nodes: impl Iterator<Item = &'a NodeInfo>,
    payload_bytes: u64,
) -> Result<Vec<Span>, LodError> {
    let mut ranges: Vec<Range<u64>> = Vec::new();
    for info in nodes.filter(|n| n.point_count > 0) {
        check_within(info, payload_bytes)?;
        let attributes = (info.attributes_len > 0).then(|| info.attributes_range());
        ranges.extend(info.pieces(info.byte_len).chain(attributes));
    }
    ranges.sort_unstable_by_key(|r| r.start);
    let mut spans: Vec<Span> = Vec::new();
    let mut next = 0u64;
    for range in ranges {
        match spans.last_mut() {
            Some(span) if range.start <= span.old.end => {
                if range.end > span.old.end {
                    next += range.end - span.old.end;
                    span.old.end = range.end;
                }
            }
            _ => {
                spans.push(Span {
                    old: range.clone(),
                    new_start: next,
                });
                next += range.end - range.start;
            }
        }
    }
    Ok(spans)
}

/// Where `offset`, live, lies in the compacted file.
fn moved_offset(offset: u64, spans: &[Span]) -> u64 {
    let i = spans.partition_point(|s| s.old.end <= offset);
    match spans.get(i) {
        Some(span) if span.old.start <= offset => span.new_start + (offset - span.old.start),
        _ => offset,
    }
}

/// `info` with its record and attributes section where the compacted file holds them.
fn relocated(info: &NodeInfo, spans: &[Span]) -> NodeInfo {
    if info.point_count == 0 {
        return *info;
    }
    let offset = moved_offset(info.offset, spans);
    let rest_offset = match info.byte_len > info.head_len {
        true => moved_offset(info.rest_offset, spans),
        false => offset + u64::from(info.head_len),
    };
    let attributes_offset = match info.attributes_len {
        0 => info.attributes_offset,
        _ => moved_offset(info.attributes_offset, spans),
    };
    NodeInfo {
        offset,
        rest_offset,
        attributes_offset,
        ..*info
    }
}

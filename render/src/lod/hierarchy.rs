//! `LodHierarchy`: the small, always-resident description of a built dataset (its cube, every
//! node's key, point count, sampling grid and where its record lies in the payload file, and the
//! dataset's statistics), and its record.
//!
//! Layout, little-endian: "PFH5" | cube min 3 x f64 | side f64 | points u64 |
//! max leaf points u32 | flags u8 (bit 0: RGB) | max RGB 3 x u16 | z range 2 x f64 |
//! intensity bins used u32, then (value u16, count u64) each | classes used u16, then
//! (class u8, count u64) each | nodes u32, then per node: level u8, x, y, z u32, points u32,
//! sampling grid u16, child mask u8, payload offset u64, payload bytes u32, head bytes u32,
//! rest offset u64, attributes offset u64, attributes bytes u32 | attribute schema present u8,
//! then the schema (`attributes.rs`) | checksum u64. A record of another version is refused
//! (the dataset is then rebuilt): "PFH7" marks stores whose nodes keep every attribute of
//! their points in an attributes section of their own, beside the coarse section and the
//! rest ("PFN3", `codec.rs`; `sink.rs`).

use std::collections::{BTreeSet, HashMap, HashSet};

use glam::DVec3;

use super::attributes::AttributeSchema;
use super::checksum::checksum64;
use super::error::LodError;
use super::fields::FieldReader;
use super::key::{NodeKey, RootCube};
use super::stats::{DatasetStats, INTENSITY_BINS};

const MAGIC: &[u8; 4] = b"PFH7";
/// The magics of earlier versions of the record, with what each lacks, so a store built by an
/// earlier version is refused with a reason rather than read wrong.
const EARLIER_VERSIONS: [(&[u8; 4], &str); 5] = [
    (b"PFH1", "payloads in sled"),
    (b"PFH2", "no lowest RGB values"),
    (b"PFH3", "no point weights"),
    (b"PFH5", "records stored in one piece"),
    (b"PFH6", "no attributes sections"),
];
/// Bytes of one node in the record.
const NODE_RECORD_BYTES: usize = 56;
const CHECKSUM_SEED: &[u8] = b"hierarchy";

/// One node of the hierarchy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NodeInfo {
    pub key: NodeKey,
    pub point_count: u32,
    /// Cells per axis of the grid the node was sampled on; 0 for a leaf.
    pub sample_grid: u32,
    /// Bit `i` set when child `i` exists.
    pub child_mask: u8,
    /// Where the node's record starts in the payload file; 0 for a node without points.
    pub offset: u64,
    /// Bytes of the node's record in the payload file (what reading it costs); 0 for a node
    /// without points.
    pub byte_len: u32,
    /// The record's first bytes stored at `offset` (a store's coarse section); the other
    /// `byte_len - head_len` lie at `rest_offset`. A record stored in one piece (every COPC
    /// chunk) has `head_len == byte_len`.
    pub head_len: u32,
    /// Where the record's bytes after its head lie; `offset + head_len` when it is stored in
    /// one piece.
    pub rest_offset: u64,
    /// Where the node's attributes section lies (`attributes.rs`), which only an export reads;
    /// 0 for a node without one.
    pub attributes_offset: u64,
    /// Bytes of the attributes section; 0 where the store keeps none.
    pub attributes_len: u32,
}

impl NodeInfo {
    /// A node listed without points of its own (its children hold them).
    pub fn empty(key: NodeKey) -> Self {
        Self {
            key,
            point_count: 0,
            sample_grid: 0,
            child_mask: 0,
            offset: 0,
            byte_len: 0,
            head_len: 0,
            rest_offset: 0,
            attributes_offset: 0,
            attributes_len: 0,
        }
    }

    /// Bytes the node takes in the payload file: its record and its attributes section.
    pub fn stored_bytes(&self) -> u64 {
        u64::from(self.byte_len) + u64::from(self.attributes_len)
    }

    /// Where the node's attributes section lies in the payload file.
    pub fn attributes_range(&self) -> std::ops::Range<u64> {
        let start = self.attributes_offset;
        start..start.saturating_add(u64::from(self.attributes_len))
    }

    /// A record stored in one piece: `byte_len` bytes at `offset`.
    pub fn in_one_piece(self, offset: u64, byte_len: u32) -> Self {
        Self {
            offset,
            byte_len,
            head_len: byte_len,
            rest_offset: offset.saturating_add(u64::from(byte_len)),
            ..self
        }
    }

    /// The pieces of the record's first `len` bytes (at most all of them) in the payload
    /// file: its head's, then its rest's where `len` reaches past the head.
    pub fn pieces(&self, len: u32) -> impl Iterator<Item = std::ops::Range<u64>> {
        let len = len.min(self.byte_len);
        let head = len.min(self.head_len);
        let rest = len - head;
        [(self.offset, head), (self.rest_offset, rest)]
            .into_iter()
            .filter(|&(_, n)| n > 0)
            .map(|(at, n)| at..at.saturating_add(u64::from(n)))
    }

    pub fn is_leaf(&self) -> bool {
        self.child_mask == 0
    }
}

#[derive(Debug, Clone, PartialEq)]
pub struct LodHierarchy {
    pub cube: RootCube,
    pub point_count: u64,
    pub max_leaf_points: u32,
    pub stats: DatasetStats,
    /// The spacing of the root's points, halved at each level below (COPC's rule), for a
    /// hierarchy whose nodes were not sampled on grids of their own; `None`: each inner node's
    /// spacing is its side over its sampling grid. Not part of the record: only hierarchies
    /// read from a COPC file's own pages have it, and those are never stored.
    level_spacing: Option<f64>,
    /// Nodes whose entries and subtree lie in a hierarchy page not read yet (a COPC file read
    /// lazily): each listed as a node without points or children until its page is read. Not
    /// part of the record: a hierarchy that is sent or stored has every page read.
    unread_pages: BTreeSet<NodeKey>,
    /// What the nodes' attributes sections hold, where the build kept them.
    attributes: Option<AttributeSchema>,
    /// Sorted by key: level, then x, y, z.
    nodes: Vec<NodeInfo>,
    index: HashMap<NodeKey, usize>,
}

impl LodHierarchy {
    /// Builds the hierarchy from every emitted node: empty nodes without children dropped,
    /// child masks set, sorted by key.
    pub(crate) fn assemble(
        cube: RootCube,
        point_count: u64,
        max_leaf_points: u32,
        stats: DatasetStats,
        emitted: Vec<NodeInfo>,
    ) -> Self {
        Self::assemble_keeping(
            cube,
            point_count,
            max_leaf_points,
            stats,
            emitted,
            &HashSet::new(),
        )
    }

    /// [`LodHierarchy::assemble`], keeping the nodes of `kept` even when they are empty and
    /// have no children.
    fn assemble_keeping(
        cube: RootCube,
        point_count: u64,
        max_leaf_points: u32,
        stats: DatasetStats,
        mut emitted: Vec<NodeInfo>,
        kept: &HashSet<NodeKey>,
    ) -> Self {
        // Deepest first, so a node's children are settled before it is.
        emitted.sort_by_key(|n| std::cmp::Reverse(n.key));
        let mut masks: HashMap<NodeKey, u8> = HashMap::new();
        let mut nodes = Vec::with_capacity(emitted.len());
        for mut node in emitted {
            node.child_mask = masks.get(&node.key).copied().unwrap_or(0);
            if node.point_count == 0 && node.child_mask == 0 && !kept.contains(&node.key) {
                continue;
            }
            if let Some(parent) = node.key.parent() {
                *masks.entry(parent).or_insert(0) |= 1 << node.key.child_index();
            }
            nodes.push(node);
        }
        nodes.reverse();
        Self::from_nodes(cube, point_count, max_leaf_points, stats, nodes)
    }

    fn from_nodes(
        cube: RootCube,
        point_count: u64,
        max_leaf_points: u32,
        stats: DatasetStats,
        nodes: Vec<NodeInfo>,
    ) -> Self {
        let index = nodes.iter().enumerate().map(|(i, n)| (n.key, i)).collect();
        Self {
            cube,
            point_count,
            max_leaf_points,
            stats,
            level_spacing: None,
            unread_pages: BTreeSet::new(),
            attributes: None,
            nodes,
            index,
        }
    }

    /// This hierarchy with its nodes' attributes sections holding rows of `attributes`.
    pub(crate) fn with_attributes(mut self, attributes: Option<AttributeSchema>) -> Self {
        self.attributes = attributes;
        self
    }

    /// What the nodes' attributes sections hold; `None` where the store keeps none (a store
    /// of generated points, a COPC file).
    pub fn attributes(&self) -> Option<&AttributeSchema> {
        self.attributes.as_ref()
    }

    /// A hierarchy whose inner nodes' spacing is `root_spacing` halved at each level (a COPC
    /// file's), from its nodes (any order; child masks are set here, empty nodes without
    /// children dropped).
    pub fn with_level_spacing(
        cube: RootCube,
        point_count: u64,
        stats: DatasetStats,
        root_spacing: f64,
        nodes: Vec<NodeInfo>,
    ) -> Self {
        Self::of_pages(
            cube,
            point_count,
            stats,
            root_spacing,
            nodes,
            &HashSet::new(),
            BTreeSet::new(),
        )
    }

    /// [`LodHierarchy::with_level_spacing`] for a COPC file whose entries come in pages: the
    /// nodes of `page_keys` (whose subtrees have pages of their own) are kept even when empty,
    /// so the hierarchy has the same nodes whether their pages are read or not yet; those of
    /// `unread_pages` wait for their page ([`LodHierarchy::is_unread_page`]).
    pub fn of_pages(
        cube: RootCube,
        point_count: u64,
        stats: DatasetStats,
        root_spacing: f64,
        nodes: Vec<NodeInfo>,
        page_keys: &HashSet<NodeKey>,
        unread_pages: BTreeSet<NodeKey>,
    ) -> Self {
        let mut hierarchy = Self::assemble_keeping(cube, point_count, 0, stats, nodes, page_keys);
        // Leaves are known only once the masks are set.
        hierarchy.max_leaf_points = hierarchy
            .nodes
            .iter()
            .filter(|n| n.is_leaf())
            .map(|n| n.point_count)
            .max()
            .unwrap_or(0);
        hierarchy.level_spacing = Some(root_spacing);
        hierarchy.unread_pages = unread_pages;
        hierarchy
    }

    /// Whether `key`'s entry and subtree lie in a page not read yet.
    pub fn is_unread_page(&self, key: NodeKey) -> bool {
        self.unread_pages.contains(&key)
    }

    /// The nodes whose pages are not read yet, by key.
    pub fn unread_pages(&self) -> &BTreeSet<NodeKey> {
        &self.unread_pages
    }

    /// The root spacing a COPC file's hierarchy halves per level (not part of the record).
    pub fn level_spacing(&self) -> Option<f64> {
        self.level_spacing
    }

    /// This hierarchy with `root_spacing` halved per level: a COPC hierarchy sent as a record,
    /// which leaves the spacing out, gets it back.
    pub fn with_root_spacing(mut self, root_spacing: f64) -> Self {
        self.level_spacing = Some(root_spacing);
        self
    }

    pub fn nodes(&self) -> &[NodeInfo] {
        &self.nodes
    }

    /// The nodes that hold points: those with a record to read (an empty node has none).
    pub fn stored_nodes(&self) -> impl Iterator<Item = &NodeInfo> {
        self.nodes.iter().filter(|n| n.point_count > 0)
    }

    pub fn node(&self, key: NodeKey) -> Option<&NodeInfo> {
        self.index.get(&key).map(|&i| &self.nodes[i])
    }

    /// Bytes of every node's record and attributes section: the payload file's size after
    /// the build.
    pub fn payload_bytes(&self) -> u64 {
        self.nodes.iter().map(NodeInfo::stored_bytes).sum()
    }

    /// Points a node to another copy of its record (the damage tests' hook).
    #[cfg(test)]
    pub(crate) fn set_byte_range(&mut self, key: NodeKey, offset: u64, byte_len: u32) {
        if let Some(&i) = self.index.get(&key) {
            self.nodes[i] = self.nodes[i].in_one_piece(offset, byte_len);
        }
    }

    pub fn root(&self) -> Option<&NodeInfo> {
        self.node(NodeKey::ROOT)
    }

    pub fn children(&self, key: NodeKey) -> impl Iterator<Item = &NodeInfo> + '_ {
        let mask = self.node(key).map_or(0, |n| n.child_mask);
        (0..8)
            .filter(move |i| mask & (1 << i) != 0)
            .filter_map(move |i| self.node(key.child(i)))
    }

    /// The corner and side of `key`'s cube in world coordinates.
    pub fn node_cube(&self, key: NodeKey) -> (DVec3, f64) {
        (self.cube.node_min(key), self.cube.side_at(key.level))
    }

    /// The spacing of the original points, from the leaves ([`crate::spacing::of_leaves`]):
    /// what sizes adaptive points where a cut reaches them.
    pub fn point_spacing(&self) -> Option<f64> {
        let leaves = self.nodes.iter().filter(|n| n.is_leaf());
        crate::spacing::of_leaves(leaves.map(|n| (self.cube.side_at(n.key.level), n.point_count)))
    }

    /// How far apart `key`'s points lie where a cut stops at it: an inner node's sampling
    /// cell (a surface through its cube leaves a point in every cell it crosses); a leaf's
    /// `side / sqrt(count)` ([`crate::spacing::of_leaves`]), at most its parent's cell, whose
    /// points lie among its own. `None` for a node without points.
    pub fn points_spacing(&self, key: NodeKey) -> Option<f64> {
        let node = self.node(key).filter(|n| n.point_count > 0)?;
        if let Some(cell) = self.spacing(key) {
            return Some(cell);
        }
        let surface = self.cube.side_at(key.level) / f64::from(node.point_count).sqrt();
        let parent_cell = key.parent().and_then(|parent| self.spacing(parent));
        Some(parent_cell.map_or(surface, |cell| surface.min(cell)))
    }

    /// The spacing of an inner node's points: its side over its sampling grid, else (a COPC
    /// file that does not record grids) the root spacing halved per level; `None` for a leaf,
    /// whose points are simply all that is left.
    pub fn spacing(&self, key: NodeKey) -> Option<f64> {
        let node = self.node(key).filter(|node| !node.is_leaf())?;
        if node.sample_grid > 0 {
            return Some(self.cube.side_at(key.level) / f64::from(node.sample_grid));
        }
        self.level_spacing
            .map(|root| root / (1u64 << key.level) as f64)
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(128 + self.nodes.len() * NODE_RECORD_BYTES);
        out.extend_from_slice(MAGIC);
        for c in self.cube.min.to_array() {
            out.extend_from_slice(&c.to_le_bytes());
        }
        out.extend_from_slice(&self.cube.side.to_le_bytes());
        out.extend_from_slice(&self.point_count.to_le_bytes());
        out.extend_from_slice(&self.max_leaf_points.to_le_bytes());
        out.push(u8::from(self.stats.has_rgb));
        for c in self.stats.max_rgb.into_iter().chain(self.stats.min_rgb) {
            out.extend_from_slice(&c.to_le_bytes());
        }
        for z in self.stats.z_range {
            out.extend_from_slice(&z.to_le_bytes());
        }
        let used: Vec<(usize, u64)> = nonzero(&self.stats.intensity_histogram);
        out.extend_from_slice(&(used.len() as u32).to_le_bytes());
        for (value, count) in used {
            out.extend_from_slice(&(value as u16).to_le_bytes());
            out.extend_from_slice(&count.to_le_bytes());
        }
        let classes = nonzero(&self.stats.class_counts);
        out.extend_from_slice(&(classes.len() as u16).to_le_bytes());
        for (class, count) in classes {
            out.push(class as u8);
            out.extend_from_slice(&count.to_le_bytes());
        }
        out.extend_from_slice(&(self.nodes.len() as u32).to_le_bytes());
        for n in &self.nodes {
            out.extend_from_slice(&n.key.level.to_le_bytes());
            for c in [n.key.x, n.key.y, n.key.z, n.point_count] {
                out.extend_from_slice(&c.to_le_bytes());
            }
            out.extend_from_slice(&(n.sample_grid as u16).to_le_bytes());
            out.push(n.child_mask);
            out.extend_from_slice(&n.offset.to_le_bytes());
            out.extend_from_slice(&n.byte_len.to_le_bytes());
            out.extend_from_slice(&n.head_len.to_le_bytes());
            out.extend_from_slice(&n.rest_offset.to_le_bytes());
            out.extend_from_slice(&n.attributes_offset.to_le_bytes());
            out.extend_from_slice(&n.attributes_len.to_le_bytes());
        }
        match &self.attributes {
            Some(schema) => {
                out.push(1);
                schema.encode(&mut out);
            }
            None => out.push(0),
        }
        let sum = checksum64(CHECKSUM_SEED, &out);
        out.extend_from_slice(&sum.to_le_bytes());
        out
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, LodError> {
        let corrupt = |reason: &str| LodError::CorruptHierarchy(reason.to_string());
        if bytes.len() < MAGIC.len() + 8 {
            return Err(corrupt("shorter than its header"));
        }
        let (body, sum) = bytes.split_at(bytes.len() - 8);
        let mut stored = [0; 8];
        stored.copy_from_slice(sum);
        if checksum64(CHECKSUM_SEED, body) != u64::from_le_bytes(stored) {
            return Err(corrupt("checksum mismatch"));
        }
        let mut r = FieldReader::new(body, "truncated");
        let magic = r.take(4)?;
        if let Some((_, missing)) = EARLIER_VERSIONS
            .iter()
            .find(|(earlier, _)| magic == earlier.as_slice())
        {
            return Err(corrupt(&format!(
                "a record of an earlier version ({missing}): rebuild the dataset"
            )));
        }
        if magic != MAGIC {
            return Err(corrupt("not a hierarchy record"));
        }
        let min = DVec3::new(r.f64()?, r.f64()?, r.f64()?);
        let side = r.f64()?;
        let cube = RootCube { min, side };
        let point_count = r.u64()?;
        let max_leaf_points = r.u32()?;
        let mut stats = DatasetStats::new(r.u8()? & 1 != 0);
        stats.max_rgb = [r.u16()?, r.u16()?, r.u16()?];
        stats.min_rgb = [r.u16()?, r.u16()?, r.u16()?];
        stats.z_range = [r.f64()?, r.f64()?];
        for _ in 0..r.u32()? {
            let value = usize::from(r.u16()?);
            stats.intensity_histogram[value] = r.u64()?;
        }
        for _ in 0..r.u16()? {
            let class = usize::from(r.u8()?);
            stats.class_counts[class] = r.u64()?;
        }
        let count = r.u32()? as usize;
        if count > body.len() / NODE_RECORD_BYTES {
            return Err(corrupt("more nodes than bytes"));
        }
        let mut nodes = Vec::with_capacity(count);
        for _ in 0..count {
            let level = r.u8()?;
            let key = NodeKey {
                level,
                x: r.u32()?,
                y: r.u32()?,
                z: r.u32()?,
            };
            let node = NodeInfo {
                key,
                point_count: r.u32()?,
                sample_grid: u32::from(r.u16()?),
                child_mask: r.u8()?,
                offset: r.u64()?,
                byte_len: r.u32()?,
                head_len: r.u32()?,
                rest_offset: r.u64()?,
                attributes_offset: r.u64()?,
                attributes_len: r.u32()?,
            };
            if node.head_len > node.byte_len {
                return Err(corrupt("a node's head is longer than its record"));
            }
            nodes.push(node);
        }
        let attributes = match r.u8()? {
            0 => None,
            1 => Some(
                r.decode_with(AttributeSchema::decode)
                    .map_err(|e| corrupt(&e))?,
            ),
            other => return Err(corrupt(&format!("attribute schema marker {other}"))),
        };
        if !r.at_end() {
            return Err(corrupt("trailing bytes"));
        }
        debug_assert_eq!(stats.intensity_histogram.len(), INTENSITY_BINS);
        Ok(
            Self::from_nodes(cube, point_count, max_leaf_points, stats, nodes)
                .with_attributes(attributes),
        )
    }
}

/// Statistics and a list of nodes as bytes with a checksum (a hierarchy's record of them),
/// for a build's journal: the nodes are kept as listed, empty ones too.
pub(super) fn encode_listing(stats: &DatasetStats, nodes: Vec<NodeInfo>) -> Vec<u8> {
    let cube = RootCube {
        min: DVec3::ZERO,
        side: 1.0,
    };
    LodHierarchy::from_nodes(cube, 0, 0, stats.clone(), nodes).encode()
}

/// What [`encode_listing`] wrote, its checksum checked.
pub(super) fn decode_listing(bytes: &[u8]) -> Result<(DatasetStats, Vec<NodeInfo>), LodError> {
    let listing = LodHierarchy::decode(bytes)?;
    Ok((listing.stats, listing.nodes))
}

fn nonzero(counts: &[u64]) -> Vec<(usize, u64)> {
    counts
        .iter()
        .enumerate()
        .filter(|(_, &c)| c > 0)
        .map(|(i, &c)| (i, c))
        .collect()
}

//! `update_lod`: a built store updated with the points of added files instead of built again.
//!
//! A store keeps its regions (`regions.rs`): the subtrees of each partition's children (a
//! quarter of a partition on a surface), each with its root's points as they were before the
//! levels above sampled from them. An update
//!
//! 1. routes each added point to the region whose cube holds it, walking down from the root;
//!    a point below no region (an empty part of the cube) starts a new region at the first
//!    node on its way that is neither a region nor above one;
//! 2. rebuilds each region that received points from all its points: its nodes below its
//!    subtree root and that root's kept points, decoded from the store (every original point
//!    is there exactly once, so no file is read again), and the added ones; the regions are
//!    built as a build's partitions are (split on disk when too large for the budget);
//! 3. samples every level above the regions again from the regions' subtree roots, kept ones
//!    read from their records (what sampling takes depends on every child, so the levels above
//!    are few nodes but all of them are rebuilt; a rebuilt region's children become regions);
//! 4. writes the new hierarchy with the new regions in one sled batch.
//!
//! Nodes are appended to the payload file, never written over, so until the last step the old
//! hierarchy still describes records that are all there: an update that is killed leaves the
//! old store whole, with bytes past its records that the next update or build overwrites or
//! leaves unread. Records of replaced nodes stay in the file as dead bytes, reported; a store
//! whose dead bytes outgrow its live ones is worth building again.
//!
//! Decoded positions are the centres of their quantisation steps; where the store's points
//! lie on one LAS grid they are put back on it, so an update moves no point. A rebuilt region's
//! points count once each again (weight 1) before they are sampled, as a build's do; a kept
//! region's root keeps the weights it was stored with.

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::sync::atomic::AtomicUsize;
use std::sync::Mutex;
use std::time::Instant;

use super::attributes::AttributeRows;
use super::build::on_threads;
use super::codec::decode_node;
use super::context::{BuildContext, Pending};
use super::error::LodError;
use super::grid::PositionGrid;
use super::hierarchy::{LodHierarchy, NodeInfo};
use super::journal::{BuildJournal, WaitingRoot};
use super::key::{NodeKey, RootCube, MAX_LEVEL};
use super::memory::MemoryMeter;
use super::options::LodBuildOptions;
use super::partitions::{build_bytes_per_point, build_partitions};
use super::pause;
use super::plan::Partition;
use super::point::{RawPoint, RecordLayout};
use super::progress::BuildProgress;
use super::records::read_nodes;
use super::regions::{Region, StoreRegions};
use super::sink::NodeSink;
use super::source::PointSource;
use super::spill::{SpillDir, SpillWriter};
use super::stats::DatasetStats;
use super::store::LodStore;
use super::upper::build_upper_levels;
use super::weights::decode_weight;

/// The most regions one update may start in empty parts of the cube (each a spill buffer).
const MAX_NEW_REGIONS: usize = 1 << 16;
/// The most bytes of records the routing of added points buffers.
const ROUTE_BUFFER_BYTES: u64 = 16 << 20;
/// Nodes decoded at once when a region is read back from the store.
const DECODE_NODES: usize = 256;

/// What an update did.
#[derive(Debug, Clone)]
pub struct LodUpdateReport {
    pub hierarchy: LodHierarchy,
    pub points_added: u64,
    /// Regions that received points and were built again.
    pub regions_rebuilt: usize,
    /// Regions started in parts of the cube that held no points.
    pub regions_added: usize,
    /// Regions whose subtrees were kept as they were.
    pub regions_kept: usize,
    /// Points decoded from the store: the rebuilt regions' and every kept region's root.
    pub points_decoded: u64,
    /// Bytes appended to the payload file: the nodes stored and the regions' kept roots.
    pub stored_bytes: u64,
    /// Bytes of the payload file no node or region of the new store lists.
    pub dead_bytes: u64,
    pub seconds: f64,
}

/// Adds the points of `added` to the store, which keeps its cube, leaf size and sampling;
/// `files` is the new list of the store's files. Refused, leaving the store as it was, when
/// the store keeps no regions, or the added points lie outside its cube or carry other
/// attributes: such a store is built again.
pub fn update_lod(
    store: &LodStore,
    added: &dyn PointSource,
    files: Vec<String>,
    options: &LodBuildOptions,
) -> Result<LodUpdateReport, LodError> {
    on_threads(options, || update_on_pool(store, added, files, options))
}

fn cannot(reason: impl Into<String>) -> LodError {
    LodError::CannotUpdate(reason.into())
}

/// Where each node of the old store belongs.
enum Place {
    /// Strictly below the region of this index.
    Below(usize),
    /// The subtree root of the region of this index.
    RegionRoot(usize),
    /// Above every region: sampled again.
    Above,
}

/// The regions by key, and every node strictly above one.
struct RegionMap {
    index: HashMap<NodeKey, usize>,
    above: HashSet<NodeKey>,
}

impl RegionMap {
    fn new(regions: &[Region]) -> Self {
        let index = regions
            .iter()
            .enumerate()
            .map(|(i, r)| (r.key, i))
            .collect();
        let mut above = HashSet::new();
        for region in regions {
            let mut key = region.key;
            while let Some(parent) = key.parent() {
                if !above.insert(parent) {
                    break;
                }
                key = parent;
            }
        }
        Self { index, above }
    }

    fn place(&self, key: NodeKey) -> Place {
        if let Some(&i) = self.index.get(&key) {
            return Place::RegionRoot(i);
        }
        let mut up = key;
        while let Some(parent) = up.parent() {
            if let Some(&i) = self.index.get(&parent) {
                return Place::Below(i);
            }
            up = parent;
        }
        Place::Above
    }

    /// The region holding `p`, made when `p` lies below none: the first node on its way
    /// down that is neither a region nor above one.
    fn route(&mut self, cube: &RootCube, p: glam::DVec3, regions: &mut Vec<NodeKey>) -> usize {
        for level in 0..=MAX_LEVEL {
            let key = NodeKey::new(level, cube.cell_at(p, u32::from(level)));
            if let Some(&i) = self.index.get(&key) {
                return i;
            }
            if !self.above.contains(&key) {
                let i = regions.len();
                regions.push(key);
                self.index.insert(key, i);
                return i;
            }
        }
        unreachable!("a node at the deepest level is above no region")
    }
}

fn update_on_pool(
    store: &LodStore,
    added: &dyn PointSource,
    files: Vec<String>,
    options: &LodBuildOptions,
) -> Result<LodUpdateReport, LodError> {
    let start = Instant::now();
    let old = store.read_hierarchy()?;
    let kept = store
        .read_regions()?
        .ok_or_else(|| cannot("the store keeps no regions (built by a resumed build)"))?;
    let cube = old.cube;
    let bounds = added.bounds();
    let top = cube.min + glam::DVec3::splat(cube.side);
    if bounds.min.cmplt(cube.min).any() || bounds.max.cmpgt(top).any() {
        return Err(cannot(format!(
            "the added points reach {:?}..{:?}, outside the store's cube {:?}..{:?}",
            bounds.min.to_array(),
            bounds.max.to_array(),
            cube.min.to_array(),
            top.to_array()
        )));
    }
    if added.attributes() != old.attributes().cloned() {
        return Err(cannot(
            "the added files carry other attributes than the store's",
        ));
    }
    let mut options = options.clone();
    options.max_leaf_points = old.max_leaf_points as usize;
    let options = &options;
    let meter = MemoryMeter::new(options.memory_budget_bytes);
    meter.pin(DatasetStats::HEAP_BYTES, "the dataset's statistics")?;
    let row_bytes = old.attributes().map_or(0, |a| a.row_bytes());
    let layout = RecordLayout::for_grid(None, row_bytes);
    let spill = SpillDir::create(&options.spill_dir, layout)?;

    // 1. Route the added points.
    let mut map = RegionMap::new(&kept.regions);
    let mut keys: Vec<NodeKey> = kept.regions.iter().map(|r| r.key).collect();
    let old_regions = keys.len();
    let mut counts = vec![0u64; old_regions + MAX_NEW_REGIONS];
    let mut stats = old.stats.clone();
    let region_path = {
        let spill_path = spill.path().to_path_buf();
        move |i: usize| spill_path.join(format!("region-{i}.bin"))
    };
    let buffer = ROUTE_BUFFER_BYTES.min(meter.largest_possible() / 8);
    let reservation = meter.reserve(2 * buffer, "routing added points")?;
    let mut writer = SpillWriter::named(
        &spill,
        counts.len(),
        region_path.clone(),
        buffer as usize,
        reservation,
    );
    let mut record = vec![0u8; layout.record_bytes()];
    let mut points_added = 0u64;
    added.for_each_batch(&mut |batch| {
        batch.check_lengths(row_bytes)?;
        if batch.rgb.is_some() != stats.has_rgb && !batch.is_empty() {
            return Err(cannot(
                "the added files differ from the store in having RGB",
            ));
        }
        stats.add(&batch);
        for i in 0..batch.len() {
            let p = batch.raw_point(i);
            if !p.position.is_finite() {
                return Err(LodError::NonFinitePoint {
                    index: points_added,
                    position: p.position.to_array(),
                });
            }
            let region = map.route(&cube, p.position, &mut keys);
            if region >= counts.len() {
                return Err(cannot("the added points start too many regions"));
            }
            layout.write(&p, batch.row(i, row_bytes), &mut record)?;
            writer.push_record(region, &record)?;
            counts[region] += 1;
            points_added += 1;
        }
        Ok(())
    })?;
    if points_added != added.point_count() {
        return Err(LodError::SourceChanged(format!(
            "{points_added} points were read of {}",
            added.point_count()
        )));
    }

    // 2. Read back the points of the old regions that received some.
    let touched: HashSet<usize> = (0..old_regions).filter(|&i| counts[i] > 0).collect();
    let mut below: Vec<Vec<NodeKey>> = vec![Vec::new(); old_regions];
    let mut kept_nodes = Vec::new();
    for node in old.nodes() {
        match map.place(node.key) {
            Place::Below(i) if touched.contains(&i) => below[i].push(node.key),
            // The octree's root as a region has no kept record: its node holds its root's
            // points, and nothing above samples it again.
            Place::RegionRoot(i) if kept.regions[i].root.is_none() => match touched.contains(&i) {
                true => below[i].push(node.key),
                false => kept_nodes.push(*node),
            },
            Place::Below(_) => kept_nodes.push(*node),
            Place::RegionRoot(_) | Place::Above => {}
        }
    }
    let mut points_decoded = 0u64;
    let mut rows = AttributeRows::new(row_bytes);
    for &i in &touched {
        let region = &kept.regions[i];
        for keys in below[i].chunks(DECODE_NODES) {
            let infos: Vec<NodeInfo> = keys.iter().filter_map(|k| old.node(*k).copied()).collect();
            let nodes = read_nodes(store, &old, keys)?;
            let sections = store.read_attribute_sections(row_bytes, &infos)?;
            for (node, section) in nodes.iter().zip(&sections) {
                let points = node_points(node, section, row_bytes, kept.grid, &mut rows, true);
                spill_points(&mut writer, layout, &points, &rows, i, &mut record)?;
                counts[i] += points.len() as u64;
                points_decoded += points.len() as u64;
            }
            rows = AttributeRows::new(row_bytes);
        }
        if let Some(root) = &region.root {
            let points = read_root(store, &old, root, row_bytes, kept.grid, &mut rows, true)?;
            spill_points(&mut writer, layout, &points, &rows, i, &mut record)?;
            counts[i] += points.len() as u64;
            points_decoded += points.len() as u64;
            rows = AttributeRows::new(row_bytes);
        }
    }
    writer.finish()?;

    // 3. Build the regions that received points, then every level above the regions.
    let journal = BuildJournal::disabled(spill.path());
    let progress = BuildProgress::new();
    let sink = NodeSink::new(store, &journal, cube, stats.has_rgb, &progress);
    let threads = rayon::current_num_threads() as u64;
    let budget = meter.largest_possible();
    let leaf = options.max_leaf_points as u64;
    let ctx = BuildContext {
        cube,
        options,
        meter: &meter,
        spill: &spill,
        sink: &sink,
        journal: &journal,
        max_partition_points: (budget / (build_bytes_per_point(layout) * threads))
            .min(options.max_partition_points)
            .max(4 * leaf),
        pending: Mutex::new(Default::default()),
        partitions_split: AtomicUsize::new(0),
        regions: Mutex::new(Vec::new()),
    };
    let mut kept_regions = Vec::new();
    for (i, region) in kept.regions.iter().enumerate() {
        if touched.contains(&i) {
            continue;
        }
        kept_regions.push(*region);
        if let Some(root) = &region.root {
            let mut rows = AttributeRows::new(row_bytes);
            let points = read_root(store, &old, root, row_bytes, kept.grid, &mut rows, false)?;
            points_decoded += points.len() as u64;
            let path = ctx.root_path(region.key);
            let (bytes, checksum) = spill.write_file(&path, &points, &rows, false)?;
            let waiting = WaitingRoot {
                count: points.len() as u64,
                sample_grid: root.sample_grid,
                bytes,
                checksum,
            };
            ctx.pending
                .lock()
                .unwrap_or_else(|poisoned| poisoned.into_inner())
                .insert(
                    region.key,
                    Pending {
                        root: waiting,
                        path,
                    },
                );
        }
    }
    let rebuilt: Vec<(Partition, Vec<PathBuf>)> = (0..keys.len())
        .filter(|&i| counts[i] > 0)
        .map(|i| {
            let partition = Partition {
                key: keys[i],
                count: counts[i],
            };
            (partition, vec![region_path(i)])
        })
        .collect();
    let regions_rebuilt = touched.len();
    let regions_added = keys.len() - old_regions;
    build_partitions(&ctx, rebuilt)?;
    build_upper_levels(&ctx)?;
    let mut regions = kept_regions.clone();
    regions.extend(
        ctx.regions
            .into_inner()
            .unwrap_or_else(|poisoned| poisoned.into_inner()),
    );

    // 4. Switch to the new hierarchy and regions at once.
    let point_count = old.point_count + points_added;
    let stored_bytes = sink.bytes();
    let kept_points: u64 = kept_nodes.iter().map(|n| u64::from(n.point_count)).sum();
    if sink.points() + kept_points != point_count {
        return Err(LodError::SourceChanged(format!(
            "the updated store holds {} points, {point_count} were expected",
            sink.points() + kept_points
        )));
    }
    let mut nodes = kept_nodes;
    nodes.extend(sink.into_nodes());
    let hierarchy = LodHierarchy::assemble(cube, point_count, old.max_leaf_points, stats, nodes)
        .with_attributes(old.attributes().cloned());
    let grid = kept.grid.filter(|g| added.position_grid() == Some(*g));
    let new_regions = StoreRegions {
        grid,
        regions,
        files,
    };
    pause::at("update", 0);
    store.write_hierarchy_with(&hierarchy, Some(&new_regions))?;
    let root_bytes: u64 = new_regions
        .regions
        .iter()
        .filter_map(|r| r.root.map(|n| n.stored_bytes()))
        .sum();
    let live = hierarchy.payload_bytes() + root_bytes;
    let payload_after = store.payload_bytes()?;
    Ok(LodUpdateReport {
        hierarchy,
        points_added,
        regions_rebuilt,
        regions_added,
        regions_kept: kept_regions.len(),
        points_decoded,
        stored_bytes,
        dead_bytes: payload_after.saturating_sub(live),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Appends `points` to region `region`'s spill file.
fn spill_points(
    writer: &mut SpillWriter<'_>,
    layout: RecordLayout,
    points: &[RawPoint],
    rows: &AttributeRows,
    region: usize,
    record: &mut [u8],
) -> Result<(), LodError> {
    for p in points {
        layout.write(p, rows.of(p), record)?;
        writer.push_record(region, record)?;
    }
    Ok(())
}

/// A region's kept subtree root, decoded.
fn read_root(
    store: &LodStore,
    hierarchy: &LodHierarchy,
    root: &NodeInfo,
    row_bytes: usize,
    grid: Option<PositionGrid>,
    rows: &mut AttributeRows,
    original: bool,
) -> Result<Vec<RawPoint>, LodError> {
    let bytes = store.read_range(root)?;
    let node = decode_node(&hierarchy.cube, root.key, root.point_count, &bytes)?;
    let sections = store.read_attribute_sections(row_bytes, std::slice::from_ref(root))?;
    Ok(node_points(
        &node,
        &sections[0],
        row_bytes,
        grid,
        rows,
        original,
    ))
}

/// A decoded node's points as the builder carries them, their rows appended to `rows`;
/// positions put back on `grid` where the store has one; each point's weight 1 where it is
/// built again as an `original` point, else its stored weight.
fn node_points(
    node: &super::codec::NodePoints,
    section: &[u8],
    row_bytes: usize,
    grid: Option<PositionGrid>,
    rows: &mut AttributeRows,
    original: bool,
) -> Vec<RawPoint> {
    let positions = node.world_positions();
    (0..node.len())
        .map(|i| {
            let position = match grid {
                Some(grid) => on_grid(grid, positions[i]),
                None => positions[i],
            };
            let row = match row_bytes {
                0 => 0,
                n => rows.push(&section[i * n..(i + 1) * n]),
            };
            let weight = match (original, node.weights.get(i)) {
                (false, Some(&code)) => decode_weight(code),
                _ => 1,
            };
            RawPoint {
                position,
                rgb: node.rgb.as_ref().map_or([0; 3], |rgb| rgb[i]),
                intensity: node.intensity[i],
                classification: node.classification[i],
                return_number: node.return_number[i],
                weight,
                row,
            }
        })
        .collect()
}

/// The point of `grid` nearest `p`: the original a quantised position stands for.
fn on_grid(grid: PositionGrid, p: glam::DVec3) -> glam::DVec3 {
    let i = ((p - grid.offset()) / grid.scale()).round();
    grid.position([i.x as i64, i.y as i64, i.z as i64])
}

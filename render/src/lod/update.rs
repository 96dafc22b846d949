//! `update_store`: a built store updated with the points of added files, and without those of
//! removed ones, instead of built again (`update_lod`: files added only).
//!
//! A store keeps its regions (`regions.rs`): the subtrees of each partition's children (a
//! quarter of a partition on a surface), each with its root's points as they were before the
//! levels above sampled from them. An update
//!
//! 1. routes each added point to the region whose cube holds it, walking down from the root;
//!    a point below no region (an empty part of the cube) starts a new region at the first
//!    node on its way that is neither a region nor above one;
//! 2. takes the points of removed files out of the regions their boxes meet (`removal.rs`),
//!    reading again only the remaining files whose boxes hold a point it drops;
//! 3. rebuilds each region that received or lost points from all its points: its nodes below its
//!    subtree root and that root's kept points, decoded from the store (every original point
//!    is there exactly once, so no file is read again), and the added ones; the regions are
//!    built as a build's partitions are (split on disk when too large for the budget);
//! 4. samples every level above the regions again from the regions' subtree roots, kept ones
//!    read from their records (what sampling takes depends on every child, so the levels above
//!    are few nodes but all of them are rebuilt; a rebuilt region's children become regions);
//! 5. writes the new hierarchy with the new regions in one sled batch.
//!
//! A changed file is a removal of it as it was and an addition of it as it is. The dataset's
//! statistics lose the dropped points' histogram counts and take their ranges from the
//! remaining files' facts, so they are a fresh build's of the files after the update.
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
use std::time::Instant;

use super::attributes::AttributeRows;
use super::build::{build_context, on_threads};
use super::codec::decode_node;
use super::context::Pending;
use super::error::LodError;
use super::file_facts::{FactsGathering, FileFacts};
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
use super::removal::{count_point, ranges_of, Removal};
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
    /// Points taken out with the removed files.
    pub points_removed: u64,
    /// Remaining files read again for their points inside a removed file's box.
    pub files_reread: usize,
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

/// What changed in a store's files since it was built or last updated.
pub struct StoreChange<'a> {
    /// The points of the files added (a changed file as it is now), one part a file.
    pub added: Option<&'a dyn PointSource>,
    /// The store's files that are gone (a changed file as it was), by their place in the
    /// order the store took them in: its build source's parts, then each update's added files.
    pub removed: Vec<usize>,
    /// Opens the store's remaining files at these places as one source: those whose boxes
    /// hold a dropped point are read again.
    pub reopen: &'a ReopenFiles<'a>,
    /// One entry per file after the update: the remaining ones in the store's order, then the
    /// added ones.
    pub files: Vec<String>,
}

/// How an update opens the store's remaining files at some places, to read them again.
pub type ReopenFiles<'a> =
    dyn Fn(&[usize]) -> Result<Box<dyn PointSource + 'a>, LodError> + Sync + 'a;

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
    let no_files = |_: &[usize]| -> Result<Box<dyn PointSource>, LodError> {
        Err(cannot("no file is removed, so none is read again"))
    };
    let change = StoreChange {
        added: Some(added),
        removed: Vec::new(),
        reopen: &no_files,
        files,
    };
    update_store(store, &change, options)
}

/// Applies `change` to the store, which keeps its cube, leaf size and sampling. Refused,
/// leaving the store as it was, when the store keeps no regions, the added points lie outside
/// its cube or carry other attributes, a file is removed from a store that does not record
/// its files' boxes or its LAS grid, or no point would remain: such a store is built again.
pub fn update_store(
    store: &LodStore,
    change: &StoreChange<'_>,
    options: &LodBuildOptions,
) -> Result<LodUpdateReport, LodError> {
    on_threads(options, || update_on_pool(store, change, options))
}

/// [`update_store`] within `memory_budget` bytes of build buffers (at least what a build
/// needs), spilling under `spill_dir`; the error says why, a refusal by its reason alone.
pub fn update_within(
    store: &LodStore,
    change: &StoreChange<'_>,
    spill_dir: PathBuf,
    memory_budget: u64,
) -> Result<LodUpdateReport, String> {
    let mut options = LodBuildOptions::new(spill_dir);
    options.memory_budget_bytes = memory_budget.max(options.min_memory_budget_bytes());
    update_store(store, change, &options).map_err(|e| match e {
        LodError::CannotUpdate(reason) => reason,
        other => other.to_string(),
    })
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

    /// The region holding `p`, if one does.
    fn locate(&self, cube: &RootCube, p: glam::DVec3) -> Option<usize> {
        for level in 0..=MAX_LEVEL {
            let key = NodeKey::new(level, cube.cell_at(p, u32::from(level)));
            if let Some(&i) = self.index.get(&key) {
                return Some(i);
            }
            if !self.above.contains(&key) {
                return None;
            }
        }
        None
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
    change: &StoreChange<'_>,
    options: &LodBuildOptions,
) -> Result<LodUpdateReport, LodError> {
    let start = Instant::now();
    let old = store.read_hierarchy()?;
    let kept = store
        .read_regions()?
        .ok_or_else(|| cannot("the store keeps no regions (built by a resumed build)"))?;
    let cube = old.cube;
    if let Some(added) = change.added {
        check_added(added, &old)?;
    }
    let mut removal = Removal::plan(&kept, &change.removed)?;
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
    let regions_at_most = old_regions + MAX_NEW_REGIONS;
    let mut stats = old.stats.clone();
    let region_path = {
        let spill_path = spill.path().to_path_buf();
        move |i: usize| spill_path.join(format!("region-{i}.bin"))
    };
    let buffer = ROUTE_BUFFER_BYTES.min(meter.largest_possible() / 8);
    let reservation = meter.reserve(2 * buffer, "routing added points")?;
    let mut spill_to = RegionSpill {
        writer: SpillWriter::named(
            &spill,
            regions_at_most,
            region_path.clone(),
            buffer as usize,
            reservation,
        ),
        layout,
        record: vec![0u8; layout.record_bytes()],
        counts: vec![0u64; regions_at_most],
    };
    let mut points_added = 0u64;
    let mut added_facts = Vec::new();
    if let Some(added) = change.added {
        let gathering = FactsGathering::new(added);
        gathering.for_each_batch(&mut |batch| {
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
                if region >= regions_at_most {
                    return Err(cannot("the added points start too many regions"));
                }
                let row = batch.row(i, row_bytes);
                spill_to.push(region, &p, row)?;
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
        added_facts = gathering.into_facts();
    }

    // 2. Read back the points of the old regions that received some or may lose some,
    // without those of removed files.
    let candidates: HashSet<usize> = (0..old_regions)
        .filter(|&i| {
            spill_to.counts[i] > 0
                || removal
                    .as_ref()
                    .is_some_and(|r| r.meets(&cube, kept.regions[i].key))
        })
        .collect();
    let mut touched: HashSet<usize> = (0..old_regions)
        .filter(|&i| spill_to.counts[i] > 0)
        .collect();
    // Each stored node below a region (the octree's root as a region has no kept record: its
    // node holds its root's points, and nothing above samples it again) with its region.
    let owned: Vec<(usize, NodeInfo)> = old
        .nodes()
        .iter()
        .filter_map(|node| match map.place(node.key) {
            Place::Below(i) => Some((i, *node)),
            Place::RegionRoot(i) if kept.regions[i].root.is_none() => Some((i, *node)),
            Place::RegionRoot(_) | Place::Above => None,
        })
        .collect();
    let mut below: Vec<Vec<NodeKey>> = vec![Vec::new(); old_regions];
    for (i, node) in &owned {
        if candidates.contains(i) {
            below[*i].push(node.key);
        }
    }
    let mut points_decoded = 0u64;
    let mut rows = AttributeRows::new(row_bytes);
    for &i in &candidates {
        let region = &kept.regions[i];
        let dropped_before = removal.as_ref().map_or(0, |r| r.dropped);
        let mut take = |points: &[RawPoint], rows: &AttributeRows| -> Result<(), LodError> {
            points_decoded += points.len() as u64;
            for p in points {
                if removal.as_mut().is_some_and(|r| r.drops(p, &mut stats)) {
                    continue;
                }
                spill_to.push(i, p, rows.of(p))?;
            }
            Ok(())
        };
        for keys in below[i].chunks(DECODE_NODES) {
            let infos: Vec<NodeInfo> = keys.iter().filter_map(|k| old.node(*k).copied()).collect();
            let nodes = read_nodes(store, &old, keys)?;
            let sections = store.read_attribute_sections(row_bytes, &infos)?;
            for (node, section) in nodes.iter().zip(&sections) {
                let points = node_points(node, section, row_bytes, kept.grid, &mut rows, true);
                take(&points, &rows)?;
            }
            rows = AttributeRows::new(row_bytes);
        }
        if let Some(root) = &region.root {
            let points = read_root(store, &old, root, row_bytes, kept.grid, &mut rows, true)?;
            take(&points, &rows)?;
            rows = AttributeRows::new(row_bytes);
        }
        if removal.as_ref().map_or(0, |r| r.dropped) > dropped_before {
            touched.insert(i);
        }
    }
    // The remaining files whose boxes hold a dropped point give back their points there.
    let mut points_reread = 0u64;
    let mut files_reread = 0;
    if let Some(removal) = removal.as_ref().filter(|r| !r.reread.is_empty()) {
        let places: Vec<usize> = removal.reread.iter().copied().collect();
        files_reread = places.len();
        let source = (change.reopen)(&places)?;
        source.for_each_batch(&mut |batch| {
            batch.check_lengths(row_bytes)?;
            for i in 0..batch.len() {
                let p = batch.raw_point(i);
                if !removal.inside(p.position) {
                    continue;
                }
                let region = map
                    .locate(&cube, p.position)
                    .filter(|r| touched.contains(r))
                    .ok_or_else(|| {
                        LodError::SourceChanged(format!(
                            "a file read again holds a point at {:?} that the store did not",
                            p.position.to_array()
                        ))
                    })?;
                count_point(&mut stats, &p, true);
                let row = batch.row(i, row_bytes);
                spill_to.push(region, &p, row)?;
                points_reread += 1;
            }
            Ok(())
        })?;
    }
    spill_to.writer.finish()?;
    let counts = spill_to.counts;
    let points_dropped = removal.as_ref().map_or(0, |r| r.dropped);
    let point_count = (old.point_count + points_added + points_reread)
        .checked_sub(points_dropped)
        .filter(|&n| n > 0)
        .ok_or_else(|| cannot("no point would remain"))?;
    let file_facts = kept.file_facts.as_ref().map(|facts| {
        let gone: HashSet<usize> = change.removed.iter().copied().collect();
        let mut after: Vec<FileFacts> = (0..facts.len())
            .filter(|i| !gone.contains(i))
            .map(|i| facts[i])
            .collect();
        after.extend(added_facts);
        after
    });
    if let (Some(_), Some(facts)) = (&removal, &file_facts) {
        ranges_of(&mut stats, facts);
    }

    // 3. Build the regions that received or lost points, then every level above the regions.
    let journal = BuildJournal::disabled(spill.path());
    let progress = BuildProgress::new();
    let sink = NodeSink::new(store, &journal, cube, stats.has_rgb, &progress);
    let threads = rayon::current_num_threads() as u64;
    let budget = meter.largest_possible();
    let leaf = options.max_leaf_points as u64;
    let max_partition_points = (budget / (build_bytes_per_point(layout) * threads))
        .min(options.max_partition_points)
        .max(4 * leaf);
    let ctx = build_context(options, &meter, &spill, &sink, max_partition_points);
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
    let kept_nodes: Vec<NodeInfo> = owned
        .into_iter()
        .filter(|(i, _)| !touched.contains(i))
        .map(|(_, node)| node)
        .collect();
    // A region that lost every point is gone.
    let rebuilt: Vec<(Partition, Vec<PathBuf>)> = (0..keys.len())
        .filter(|&i| counts[i] > 0 && (i >= old_regions || touched.contains(&i)))
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
    let grid = match change.added {
        Some(added) => kept.grid.filter(|g| added.position_grid() == Some(*g)),
        None => kept.grid,
    };
    let new_regions = StoreRegions {
        grid,
        regions,
        files: change.files.clone(),
        file_facts,
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
        points_removed: points_dropped - points_reread,
        files_reread,
        regions_rebuilt,
        regions_added,
        regions_kept: kept_regions.len(),
        points_decoded,
        stored_bytes,
        dead_bytes: payload_after.saturating_sub(live),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Refuses added points outside the store's cube, or of other attributes. Files without
/// points (empty tiles) add nothing to refuse, whatever their headers say.
fn check_added(added: &dyn PointSource, old: &LodHierarchy) -> Result<(), LodError> {
    if added.point_count() == 0 {
        return Ok(());
    }
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
    Ok(())
}

/// The spill files of the regions being rebuilt, and the points each holds.
struct RegionSpill<'s> {
    writer: SpillWriter<'s>,
    layout: RecordLayout,
    record: Vec<u8>,
    counts: Vec<u64>,
}

impl RegionSpill<'_> {
    /// Writes `p` with its attribute `row` to the spill file of `region`, and counts it there.
    fn push(&mut self, region: usize, p: &RawPoint, row: &[u8]) -> Result<(), LodError> {
        self.layout.write(p, row, &mut self.record)?;
        self.writer.push_record(region, &self.record)?;
        self.counts[region] += 1;
        Ok(())
    }
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

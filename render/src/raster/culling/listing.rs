//! One segment's entries that can be in view, near to far: groups of batches wholly in view
//! are listed without testing their batches, batches wholly in view are listed whole, and of
//! a batch that straddles the view's edge only its runs of sub-batches that can be in view.
//! Each entry is one word (`ListedEntry`).

use glam::{DVec3, Vec3};

use super::frustum::Frustum;
use crate::raster::gpu_data::GpuBatch;
use crate::raster::pixel_rect::{PixelCoverage, PixelRect};
use crate::raster::points::{BatchTables, BATCH_POINTS, GROUP_BATCHES, SUB_BATCH_POINTS};

/// A frame table's entry: batch `index` of its segment's resident table and the run of that
/// batch's sub-batches to draw, in one word (the shaders' `listed_batch` in common.wgsl):
/// the index in the upper 24 bits (a segment's point indices are u32, so it holds at most
/// 2^20 batches), then the run's first sub-batch and its length - 1, 4 bits each. A frame
/// uploads 4 bytes per listed batch instead of a copy of its 32-byte entry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct ListedEntry(pub u32);

/// Sub-batches per batch: a run's first and length each fit in 4 bits.
const SUBS_PER_BATCH: usize = BATCH_POINTS / SUB_BATCH_POINTS;
const _: () = assert!(SUBS_PER_BATCH <= 16);
const _: () = assert!((u32::MAX as usize / BATCH_POINTS) < 1 << 24);

impl ListedEntry {
    fn whole(batch: usize) -> Self {
        Self::run(batch, 0, SUBS_PER_BATCH)
    }

    fn run(batch: usize, first_sub: usize, subs: usize) -> Self {
        debug_assert!(first_sub + subs <= SUBS_PER_BATCH && subs > 0);
        Self(((batch as u32) << 8) | ((first_sub as u32) << 4) | (subs as u32 - 1))
    }

    /// The entry as the shaders see it: its batch's box, with the run's points.
    #[cfg(test)]
    pub fn batch(self, batches: &[GpuBatch]) -> GpuBatch {
        let batch = batches[(self.0 >> 8) as usize];
        let first = batch.first + ((self.0 >> 4) & 15) * SUB_BATCH_POINTS as u32;
        let end =
            (first + ((self.0 & 15) + 1) * SUB_BATCH_POINTS as u32).min(batch.first + batch.count);
        GpuBatch {
            first,
            count: end - first,
            ..batch
        }
    }
}

/// What one segment's listed entries hold.
#[derive(Clone, Copy, Debug)]
pub(super) struct Listing {
    pub points: u64,
    /// The box of the listed batches.
    pub min: Vec3,
    pub max: Vec3,
}

impl Listing {
    pub const EMPTY: Self = Self {
        points: 0,
        min: Vec3::INFINITY,
        max: Vec3::NEG_INFINITY,
    };

    fn add(&mut self, batch: &GpuBatch, points: u32) {
        self.points += u64::from(points);
        self.min = self.min.min(Vec3::from_array(batch.min));
        self.max = self.max.max(Vec3::from_array(batch.max));
    }
}

/// Appends to `out` the entries of `tables` that can be in view, near to far for a view
/// whose depth grows along `depth_gradient`, and adds the pixels their points can touch to
/// `coverage`. A group of batches wholly inside the frustum is listed without testing its
/// batches; of the other groups, each batch is tested: a batch wholly inside is listed whole;
/// of a batch that straddles the edge, only the runs of sub-batches that can be in view. The
/// entries follow the table's near-to-far order (`DrawOrders`), so no frame sorts.
pub(super) fn list_in_view(
    frustum: &Frustum,
    tables: BatchTables<'_>,
    depth_gradient: DVec3,
    out: &mut Vec<u32>,
    coverage: &mut PixelCoverage,
) -> Listing {
    let visibility = batch_visibility(frustum, tables, coverage);
    let mut listing = Listing::EMPTY;
    for &b in tables.draw_orders.get(tables.batches, depth_gradient) {
        let b = b as usize;
        match visibility[b] {
            Visibility::Hidden => {}
            Visibility::Whole => {
                let batch = &tables.batches[b];
                out.push(ListedEntry::whole(b).0);
                listing.add(batch, batch.count);
            }
            Visibility::Straddling(footprint) => {
                if list_runs_in_view(frustum, tables, b, out, &mut listing) {
                    coverage.add(footprint);
                }
            }
        }
    }
    listing
}

/// Whether a batch is listed, and how.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Visibility {
    Hidden,
    /// Listed as it is (its footprint already added to the coverage).
    Whole,
    /// At the view's edge: its runs are tested when it is listed, and its footprint (the
    /// batch's, which holds its runs') added to the coverage if any is.
    Straddling(PixelRect),
}

/// Each batch's [`Visibility`], testing groups first; adds the footprints of the batches
/// listed whole to `coverage`.
fn batch_visibility(
    frustum: &Frustum,
    tables: BatchTables<'_>,
    coverage: &mut PixelCoverage,
) -> Vec<Visibility> {
    let mut visibility = vec![Visibility::Hidden; tables.batches.len()];
    if tables.groups.is_empty() {
        test_batches(
            frustum,
            tables,
            0..tables.batches.len(),
            &mut visibility,
            coverage,
        );
        return visibility;
    }
    for (g, group) in tables.groups.iter().enumerate() {
        let Some(view) = frustum.view_of(group) else {
            continue;
        };
        let batches = g * GROUP_BATCHES..((g + 1) * GROUP_BATCHES).min(tables.batches.len());
        if view.whole {
            coverage.add(view.footprint);
            visibility[batches].fill(Visibility::Whole);
        } else {
            test_batches(frustum, tables, batches, &mut visibility, coverage);
        }
    }
    visibility
}

/// [`batch_visibility`] for the batches `range`, one by one.
fn test_batches(
    frustum: &Frustum,
    tables: BatchTables<'_>,
    range: std::ops::Range<usize>,
    visibility: &mut [Visibility],
    coverage: &mut PixelCoverage,
) {
    for b in range {
        let Some(view) = frustum.view_of(&tables.batches[b]) else {
            continue;
        };
        visibility[b] = if view.whole || tables.sub_batches.is_empty() {
            coverage.add(view.footprint);
            Visibility::Whole
        } else {
            Visibility::Straddling(view.footprint)
        };
    }
}

/// Appends to `out` the runs of consecutive sub-batches of batch `b` that can be in view;
/// whether there was any. Their footprints are not computed: the batch's holds them, and the
/// test without them costs a sub-batch no division (docs/perf/batch-culling.md).
fn list_runs_in_view(
    frustum: &Frustum,
    tables: BatchTables<'_>,
    b: usize,
    out: &mut Vec<u32>,
    listing: &mut Listing,
) -> bool {
    let batch = &tables.batches[b];
    let subs = tables
        .sub_batches
        .get(b * SUBS_PER_BATCH..)
        .unwrap_or_default()
        .iter()
        .take(SUBS_PER_BATCH)
        .take_while(|sub| sub.first < batch.first + batch.count);
    // The open run: its first sub-batch, length and points.
    let mut run: Option<(usize, usize, u32)> = None;
    let mut listed = false;
    let mut close = |run: Option<(usize, usize, u32)>, out: &mut Vec<u32>| {
        if let Some((first, length, points)) = run {
            out.push(ListedEntry::run(b, first, length).0);
            listing.add(batch, points);
            listed = true;
        }
    };
    for (s, sub) in subs.enumerate() {
        if frustum.excludes(sub) {
            close(run.take(), out);
            continue;
        }
        match run.as_mut() {
            Some((_, length, points)) => {
                *length += 1;
                *points += sub.count;
            }
            None => run = Some((s, 1, sub.count)),
        }
    }
    close(run, out);
    listed
}

#[cfg(test)]
mod tests {
    use crate::testing::{perspective_camera, top_down_camera};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::camera::Camera;
    use crate::raster::culling::{batch, decoded};
    use crate::raster::draw_order::DrawOrders;

    /// An entry names its batch and a run of its sub-batches; the run ends with the batch,
    /// which may hold fewer points than a full one.
    #[test]
    fn entries_hold_their_batch_or_a_run_of_it() {
        let full = GpuBatch {
            first: 0,
            count: BATCH_POINTS as u32,
            ..batch(Vec3::ZERO, Vec3::ONE)
        };
        let short = GpuBatch {
            first: BATCH_POINTS as u32,
            count: 1000,
            ..batch(Vec3::ONE, Vec3::splat(2.0))
        };
        let batches = [full, short];
        let at = |entry: ListedEntry| {
            let b = entry.batch(&batches);
            (b.min, b.max, b.first, b.count)
        };
        let sub = SUB_BATCH_POINTS as u32;
        assert_eq!(at(ListedEntry::whole(0)), (full.min, full.max, 0, 4096));
        assert_eq!(
            at(ListedEntry::whole(1)),
            (short.min, short.max, 4096, 1000)
        );
        assert_eq!(
            at(ListedEntry::run(0, 15, 1)),
            (full.min, full.max, 15 * sub, sub)
        );
        assert_eq!(
            at(ListedEntry::run(1, 1, 2)),
            (short.min, short.max, 4096 + sub, 2 * sub)
        );
        // The last run of the short batch stops at its end.
        assert_eq!(
            at(ListedEntry::run(1, 2, 3)),
            (short.min, short.max, 4096 + 2 * sub, 1000 - 2 * sub)
        );
    }

    /// Views of a cube of side 20 centred on the origin that see part of it.
    fn views_of_the_cube() -> [Camera; 3] {
        [
            // Perspective, seeing a corner of the cube.
            perspective_camera(
                DVec3::new(14.0, -30.0, 12.0),
                DVec3::new(9.0, 0.0, 8.0),
                30.0,
                (1.0, 100.0),
            ),
            // Orthographic from above, a quarter of the top face.
            top_down_camera(DVec3::new(5.0, 5.0, 0.0), 40.0, 8.0, (20.0, 60.0)),
            // Perspective, the near plane cutting through the cube.
            perspective_camera(
                DVec3::new(0.0, -5.0, 0.0),
                DVec3::new(0.0, 10.0, 0.0),
                60.0,
                (2.0, 100.0),
            ),
        ]
    }

    /// Of batches that straddle the edge of the view only the sub-batches that can be in
    /// view are listed: every point in view is in a listed entry, and fewer points are listed
    /// than whole batches would give.
    #[test]
    fn straddling_batches_list_only_their_sub_batches_that_can_be_in_view() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let points: Vec<Vec3> = (0..24 * BATCH_POINTS + 300)
            .map(|_| Vec3::from_array(std::array::from_fn(|_| rng.random_range(-10.0..10.0))))
            .collect();
        let (batches, sub_batches, dequantised) = crate::raster::points::host_tables(&points);
        let orders = DrawOrders::default();
        let (width, height) = (160, 120);
        for camera in views_of_the_cube() {
            let transform = camera.transform(DVec3::ZERO, width, height);
            let frustum = Frustum::new(&transform, 1);
            let gradient = transform.depth_row.truncate();
            let mut listed = Vec::new();
            let mut coverage = PixelCoverage::new(width, height);
            list_in_view(
                &frustum,
                BatchTables {
                    batches: &batches,
                    sub_batches: &sub_batches,
                    groups: &[],
                    draw_orders: &orders,
                },
                gradient,
                &mut listed,
                &mut coverage,
            );
            let footprint = coverage.union();
            let listed = decoded(&listed, &batches);
            let mut whole_batches = Vec::new();
            list_in_view(
                &frustum,
                BatchTables {
                    batches: &batches,
                    sub_batches: &[],
                    groups: &[],
                    draw_orders: &orders,
                },
                gradient,
                &mut whole_batches,
                &mut PixelCoverage::new(width, height),
            );
            let whole_batches = decoded(&whole_batches, &batches);
            let mut is_listed = vec![false; points.len()];
            for entry in &listed {
                // Each entry keeps its batch's box: the shaders dequantise against it.
                let batch = batches[entry.first as usize / BATCH_POINTS];
                assert_eq!((entry.min, entry.max), (batch.min, batch.max));
                assert!(entry.first + entry.count <= batch.first + batch.count);
                for flag in &mut is_listed[entry.first as usize..][..entry.count as usize] {
                    assert!(!*flag, "{camera:?}: a point listed twice");
                    *flag = true;
                }
            }
            let mut in_view = 0;
            for (i, p) in dequantised.iter().enumerate() {
                let Some((x, y, _)) = transform.project(p.as_dvec3()) else {
                    continue;
                };
                if x >= 0.0 && y >= 0.0 && x < f64::from(width) && y < f64::from(height) {
                    in_view += 1;
                    assert!(
                        is_listed[i],
                        "{camera:?}: point {i} at {p} in view, not listed"
                    );
                    assert!(footprint.contains(x as u32, y as u32), "{camera:?}");
                }
            }
            let listed_points: u32 = listed.iter().map(|e| e.count).sum();
            let whole_points: u32 = whole_batches.iter().map(|e| e.count).sum();
            assert!(in_view > 0, "{camera:?}: nothing in view");
            assert!(
                listed_points < whole_points,
                "{camera:?}: {in_view} in view, {listed_points} listed, {whole_points} in \
                 whole batches"
            );
        }
    }

    /// Listing by groups gives the very entries that testing every batch gives, in the same
    /// order, and a footprint that holds theirs: a group is listed whole only when all its
    /// batches would be.
    #[test]
    fn groups_list_the_same_entries_as_batches_one_by_one() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let points: Vec<Vec3> = (0..10 * GROUP_BATCHES * BATCH_POINTS + 999)
            .map(|_| Vec3::from_array(std::array::from_fn(|_| rng.random_range(-10.0..10.0))))
            .collect();
        let (batches, sub_batches, _) = crate::raster::points::host_tables(&points);
        let groups = crate::raster::points::batch_groups(&batches);
        let orders = DrawOrders::default();
        assert_eq!(groups.len(), 11);
        let (width, height) = (160, 120);
        // The whole cube in view (every group listed whole), then groups in, out, and across
        // the edge of the view.
        let whole = perspective_camera(
            DVec3::new(0.0, -60.0, 10.0),
            DVec3::ZERO,
            40.0,
            (1.0, 200.0),
        );
        let mut whole_groups = 0;
        for camera in std::iter::once(whole).chain(views_of_the_cube()) {
            let transform = camera.transform(DVec3::ZERO, width, height);
            let frustum = Frustum::new(&transform, 1);
            let list = |groups: &[GpuBatch]| {
                let (mut listed, mut coverage) = (Vec::new(), PixelCoverage::new(width, height));
                let tables = BatchTables {
                    batches: &batches,
                    sub_batches: &sub_batches,
                    groups,
                    draw_orders: &orders,
                };
                let gradient = transform.depth_row.truncate();
                list_in_view(&frustum, tables, gradient, &mut listed, &mut coverage);
                (listed, coverage.union())
            };
            let (by_group, group_footprint) = list(&groups);
            let (one_by_one, footprint) = list(&[]);
            assert!(!one_by_one.is_empty(), "{camera:?}: nothing listed");
            assert_eq!(by_group, one_by_one, "{camera:?}");
            assert_eq!(
                group_footprint.union(footprint),
                group_footprint,
                "{camera:?}"
            );
            whole_groups += groups
                .iter()
                .filter(|g| frustum.view_of(g).is_some_and(|v| v.whole))
                .count();
        }
        assert!(whole_groups >= groups.len(), "{whole_groups} groups whole");
    }
}

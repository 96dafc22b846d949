//! The typical distance between neighbouring points of a cloud, which sizes points
//! adaptively ([`crate::request::PointSize::Adaptive`]).
//!
//! Scans sample surfaces: `n` points over an area `A` lie about `sqrt(A / n)` apart. The area
//! is measured by box counting: on a grid coarse enough that every cell the surface crosses
//! holds several points, the occupied cells times a cell's face is the area. A surface at a
//! slant to the grid crosses more cells (up to sqrt(3) times for a diagonal plane), so its
//! spacing reads up to a third larger: adaptive points round up rather than leave holes.
//! Counting cells of a random sample keeps the cost small and bounded whatever the cloud's
//! size; random, not every k-th point, because scanners write points in scan lines.

use glam::Vec3;

/// Points sampled, evenly through the cloud: enough cells to measure the area to a few
/// percent, few enough to count in milliseconds.
const SAMPLE_POINTS: usize = 1 << 18;
/// Sampled points an occupied cell holds on average before its grid is trusted to have
/// found every cell of the surface.
const MIN_POINTS_PER_CELL: f64 = 8.0;
/// The finest grid tried, in cells along the box's longest side.
const FINEST_GRID: u32 = 1 << 12;

/// The spacing of `positions`, in their units; `None` for fewer than two distinct points.
pub fn of_points(positions: &[Vec3]) -> Option<f64> {
    of_sample(&sample_of(positions), positions.len() as u64)
}

/// The random sample of about [`SAMPLE_POINTS`] of `positions` that [`of_points`] measures
/// (all of them when there are fewer), in their order; what else is taken from a cloud's
/// spread, such as the box the automatic camera frames, is taken from it too.
pub fn sample_of(positions: &[Vec3]) -> Vec<Vec3> {
    // Each point is kept with probability SAMPLE_POINTS / n, decided by a hash of its index.
    let keep = ((SAMPLE_POINTS as u128) << 32) / positions.len().max(1) as u128;
    positions
        .iter()
        .enumerate()
        .filter(|&(i, _)| u128::from(mix(i as u64) >> 32) < keep)
        .map(|(_, p)| *p)
        .collect()
}

/// The spacing of a cloud of `points` points of which `sample` is an even sample (a random
/// one, or the coarsest levels of a level-of-detail hierarchy, which are spatially even): the
/// area the sample's surface covers, measured by box counting, shared among all the points.
/// `None` for fewer than two distinct finite points.
pub fn of_sample(sample: &[Vec3], points: u64) -> Option<f64> {
    let sample: Vec<Vec3> = sample.iter().copied().filter(|p| p.is_finite()).collect();
    let (min, max) = sample.iter().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    let extent = f64::from((max - min).max_element());
    if sample.len() < 2 || extent.is_nan() || extent <= 0.0 {
        return None;
    }
    let points = points.max(sample.len() as u64);
    let mut grid = FINEST_GRID;
    let mut cells = Vec::with_capacity(sample.len());
    loop {
        let cell = extent / f64::from(grid);
        let occupied = occupied_cells(&sample, min, cell, &mut cells);
        if sample.len() as f64 / occupied as f64 >= MIN_POINTS_PER_CELL || grid == 1 {
            let area = occupied as f64 * cell * cell;
            return Some((area / points as f64).sqrt());
        }
        grid /= 2;
    }
}

/// SplitMix64's finaliser: a well-spread hash of a point's index.
fn mix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

/// Cells of side `cell` from `min` that hold a point of `sample` (`cells` is scratch).
fn occupied_cells(sample: &[Vec3], min: Vec3, cell: f64, cells: &mut Vec<u64>) -> usize {
    cells.clear();
    cells.extend(sample.iter().map(|p| {
        let index = |axis: usize| ((f64::from(p[axis] - min[axis]) / cell) as u64).min(0x1f_ffff);
        index(0) | index(1) << 21 | index(2) << 42
    }));
    cells.sort_unstable();
    cells.dedup();
    cells.len()
}

/// The spacing of a level-of-detail store's points from its leaves, each a cube of side
/// `side` holding `count` original points: a surface crossing a cube covers about its face,
/// so a leaf's points lie about `side / sqrt(count)` apart. The median over the points (each
/// leaf weighted by its count), so that sparse edges do not decide; `None` without leaves.
pub fn of_leaves(leaves: impl IntoIterator<Item = (f64, u32)>) -> Option<f64> {
    let mut spacings: Vec<(f64, u64)> = leaves
        .into_iter()
        .filter(|&(side, count)| count > 0 && side.is_finite() && side > 0.0)
        .map(|(side, count)| (side / f64::from(count).sqrt(), u64::from(count)))
        .collect();
    spacings.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total: u64 = spacings.iter().map(|&(_, count)| count).sum();
    let mut seen = 0;
    spacings.into_iter().find_map(|(spacing, count)| {
        seen += count;
        (2 * seen >= total).then_some(spacing)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A square grid of `side` x `side` points `step` apart in the plane through the origin
    /// with normal `normal`.
    fn plane(side: u32, step: f32, normal: Vec3) -> Vec<Vec3> {
        let u = normal.any_orthonormal_vector();
        let v = normal.normalize().cross(u);
        (0..side * side)
            .map(|i| (u * (i % side) as f32 + v * (i / side) as f32) * step)
            .collect()
    }

    #[test]
    fn a_grid_of_points_has_its_step() {
        // A slanted plane crosses more cells (module doc): up to a third larger.
        for (normal, step, low, high) in [
            (Vec3::Z, 0.5, 0.9, 1.1),
            (Vec3::X, 3.0, 0.9, 1.1),
            (Vec3::new(1.0, 0.0, 3.0), 0.02, 0.9, 1.34),
        ] {
            let points = plane(1000, step, normal);
            let spacing = of_points(&points).expect("a spacing");
            assert!(
                (low..high).contains(&(spacing / f64::from(step))),
                "normal {normal}, step {step}: spacing {spacing}"
            );
        }
    }

    #[test]
    fn a_coarse_level_of_a_grid_gives_the_whole_grids_step() {
        // Every eighth point each way, as a level-of-detail's coarse level keeps them.
        let side = 1000;
        let points = plane(side, 0.5, Vec3::Z);
        let coarse: Vec<Vec3> = points
            .iter()
            .enumerate()
            .filter(|(i, _)| {
                (i % side as usize).is_multiple_of(8) && (i / side as usize).is_multiple_of(8)
            })
            .map(|(_, p)| *p)
            .collect();
        let spacing = of_sample(&coarse, points.len() as u64).expect("a spacing");
        assert!((0.45..0.55).contains(&spacing), "{spacing}");
        assert_eq!(of_sample(&coarse[..1], 10), None);
        assert_eq!(of_sample(&[Vec3::NAN, Vec3::ONE], 10), None);
    }

    #[test]
    fn sampling_keeps_the_spacing_of_the_whole_cloud() {
        // 4M points in rows, as a scanner writes them: the estimate comes from a sample of a
        // sixteenth of them.
        let points = plane(2000, 0.1, Vec3::Z);
        let spacing = of_points(&points).expect("a spacing");
        assert!((spacing / 0.1 - 1.0).abs() < 0.1, "spacing {spacing}");
    }

    #[test]
    fn denser_points_are_closer() {
        let sparse = of_points(&plane(300, 1.0, Vec3::Z)).expect("a spacing");
        let dense = of_points(&plane(600, 0.5, Vec3::Z)).expect("a spacing");
        assert!((sparse / dense - 2.0).abs() < 0.3, "{sparse} vs {dense}");
    }

    #[test]
    fn no_spacing_without_two_distinct_points() {
        assert_eq!(of_points(&[]), None);
        assert_eq!(of_points(&[Vec3::ONE]), None);
        assert_eq!(of_points(&[Vec3::ONE; 5]), None);
        assert_eq!(of_points(&[Vec3::NAN, Vec3::ONE]), None);
    }

    #[test]
    fn leaves_give_their_count_weighted_median() {
        // Most points in leaves of side 10 holding 100 points: 1 apart.
        let leaves = [(10.0, 100), (10.0, 100), (10.0, 100), (40.0, 4), (1.0, 0)];
        assert_eq!(of_leaves(leaves), Some(1.0));
        assert_eq!(of_leaves([]), None);
    }
}

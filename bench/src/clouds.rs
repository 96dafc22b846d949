//! The generated clouds of the workloads: the uniform cube (whole, or cell by cell in Morton
//! order for the huge workload) and the shuffled k-plane cuboid.

use glam::{DVec3, Vec3};
use pointfarm_render::cloud::{pack_rgba8, ColorSource, PointCloud, WorldBounds};
use pointfarm_render::raster::BATCH_POINTS;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Side of the generated uniform cube, in world units.
pub(crate) const CUBE_SIDE: f64 = 100.0;

/// The generated cube: its centre (the clouds' origin) and its box, at survey-like coordinates.
pub(crate) fn cube_bounds() -> (DVec3, WorldBounds) {
    let min = DVec3::new(515_000.0, 4_918_000.0, 2_000.0);
    let bounds = WorldBounds {
        min,
        max: min + DVec3::splat(CUBE_SIDE),
    };
    (bounds.center(), bounds)
}

/// The color of a point at `unit` (0..1 per axis) in the cube.
fn cube_color(unit: Vec3) -> u32 {
    let [r, g, b] = (unit * 255.0).as_uvec3().to_array().map(|c| c as u8);
    pack_rgba8(r, g, b)
}

/// Uniform random points in a `CUBE_SIDE` cube at survey-like coordinates, generated relative
/// to the cube's centre (no f64 copy of the cloud).
pub fn uniform_cube(points: usize, seed: u64) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (origin, bounds) = cube_bounds();
    let mut positions = Vec::with_capacity(points);
    let mut colors = Vec::with_capacity(points);
    for _ in 0..points {
        let unit = Vec3::new(rng.random(), rng.random(), rng.random());
        positions.push((unit - 0.5) * CUBE_SIDE as f32);
        colors.push(cube_color(unit));
    }
    PointCloud {
        origin,
        positions,
        colors,
        intensity: vec![0; points],
        classification: vec![0; points],
        return_number: vec![0; points],
        bounds,
        color_source: ColorSource::Rgb16,
    }
}

/// The uniform cube generated cell by cell: the cube is split into 2^(3 levels) cells visited
/// in Morton order, each filled with its share of uniform random points, so that consecutive
/// points are close together without a sort and the cloud never exists whole on the host.
pub(crate) struct CellCubeGenerator {
    rng: ChaCha8Rng,
    levels: u32,
    next_cell: u64,
    cells: u64,
    points: usize,
}

impl CellCubeGenerator {
    pub(crate) fn new(points: usize, seed: u64) -> Self {
        // Cells of at most one batch each.
        let mut levels = 0;
        while (points as u64).div_ceil(1 << (3 * levels)) > BATCH_POINTS as u64 {
            levels += 1;
        }
        Self {
            rng: ChaCha8Rng::seed_from_u64(seed),
            levels,
            next_cell: 0,
            cells: 1 << (3 * levels),
            points,
        }
    }

    /// Points of cell `cell`: an even share, the first cells taking the remainder.
    fn cell_points(&self, cell: u64) -> usize {
        let base = self.points as u64 / self.cells;
        (base + u64::from(cell < self.points as u64 % self.cells)) as usize
    }

    /// Whole cells of at most `max_points` points (at least one cell), or `None` when done.
    pub(crate) fn next_segment(&mut self, max_points: usize) -> Option<(Vec<Vec3>, Vec<u32>)> {
        if self.next_cell >= self.cells {
            return None;
        }
        let side = (1u32 << self.levels) as f32;
        let (mut positions, mut colors) = (Vec::new(), Vec::new());
        while self.next_cell < self.cells {
            let n = self.cell_points(self.next_cell);
            if !positions.is_empty() && positions.len() + n > max_points {
                break;
            }
            let corner = Vec3::from_array(demorton3(self.next_cell).map(|c| c as f32));
            for _ in 0..n {
                let jitter = Vec3::new(self.rng.random(), self.rng.random(), self.rng.random());
                let unit = (corner + jitter) / side;
                positions.push((unit - 0.5) * CUBE_SIDE as f32);
                colors.push(cube_color(unit));
            }
            self.next_cell += 1;
        }
        Some((positions, colors))
    }
}

/// The x, y, z cell coordinates interleaved in a Morton code (x in the lowest bit).
fn demorton3(code: u64) -> [u32; 3] {
    let mut xyz = [0u32; 3];
    for bit in 0..21 {
        for (axis, c) in xyz.iter_mut().enumerate() {
            *c |= (((code >> (3 * bit + axis)) & 1) as u32) << bit;
        }
    }
    xyz
}

/// The cuboid's points: plane `k` at height `k`, each plane one color.
pub fn shuffled_cuboid(planes: usize, side: usize, seed: u64) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let origin = DVec3::new(515_000.0, 4_918_000.0, 2_000.0);
    let mut order: Vec<usize> = (0..planes * side * side).collect();
    order.shuffle(&mut rng);
    let plane_colors: Vec<u32> = (0..planes)
        .map(|_| pack_rgba8(rng.random(), rng.random(), rng.random()))
        .collect();
    let (positions, colors) = order
        .into_iter()
        .map(|i| {
            let (plane, cell) = (i / (side * side), i % (side * side));
            let (x, y) = (cell % side, cell / side);
            let p = origin + DVec3::new(x as f64 + 0.5, y as f64 + 0.5, plane as f64);
            (p, plane_colors[plane])
        })
        .unzip::<_, _, Vec<DVec3>, Vec<u32>>();
    PointCloud::from_world_points(&positions, colors)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cell_generator_yields_every_point_once_in_compact_cells() {
        let mut generator = CellCubeGenerator::new(100_000, 3);
        let (mut total, mut segments) = (0, 0);
        while let Some((positions, colors)) = generator.next_segment(3 * BATCH_POINTS) {
            assert!(positions.len() <= 3 * BATCH_POINTS && positions.len() == colors.len());
            let half = CUBE_SIDE as f32 / 2.0;
            assert!(positions.iter().all(|p| p.abs().max_element() <= half));
            total += positions.len();
            segments += 1;
        }
        assert_eq!(total, 100_000);
        assert!(segments >= 100_000 / (3 * BATCH_POINTS));
        assert_eq!(demorton3(0b111_000), [2, 2, 2]);
        assert_eq!(demorton3(0b100), [0, 0, 1]);
    }

    #[test]
    fn cuboid_has_every_grid_point_once() {
        let cloud = shuffled_cuboid(3, 4, 1);
        assert_eq!(cloud.len(), 48);
        let mut cells: Vec<(i64, i64, i64)> = cloud
            .positions
            .iter()
            .map(|p| {
                let w = cloud.origin + p.as_dvec3();
                (w.x.floor() as i64, w.y.floor() as i64, w.z.round() as i64)
            })
            .collect();
        cells.sort_unstable();
        cells.dedup();
        assert_eq!(cells.len(), 48);
    }
}

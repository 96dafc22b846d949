//! A generated scene cut into the tiles of its ground plan, as a survey campaign delivers it.

use pointfarm_render::cloud::PointCloud;

/// The indices of `cloud`'s points in each of `across` x `along` equal tiles of its ground
/// plan (x across, y along), row by row from the lowest y; a point on a tile's far edge
/// belongs to the tile before it, one on the box's far edge to the last.
pub fn ground_plan_tiles(cloud: &PointCloud, across: usize, along: usize) -> Vec<Vec<usize>> {
    let (min, size) = (cloud.bounds.min, cloud.bounds.size());
    let cell = |v: f64, lo: f64, extent: f64, n: usize| {
        (((v - lo) / extent * n as f64) as usize).min(n - 1)
    };
    let mut tiles: Vec<Vec<usize>> = vec![Vec::new(); across * along];
    for (i, p) in cloud.positions.iter().enumerate() {
        let world = cloud.origin + p.as_dvec3();
        let x = cell(world.x, min.x, size.x, across);
        let y = cell(world.y, min.y, size.y, along);
        tiles[y * across + x].push(i);
    }
    tiles
}

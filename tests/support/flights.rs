//! A campaign of tiles and low keyframed flights over one or two of them, which see a few
//! tiles only: what camera-first builds are tested with, locally and through the daemon.

use std::path::{Path, PathBuf};

use pointfarm_render::cloud::{PointCloud, WorldBounds};
use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::sample::sample_scene;

use crate::tiles::ground_plan_tiles;

/// The tiles across and along the scene's ground plan.
pub const COLUMNS: usize = 5;
pub const ROWS: usize = 4;

/// The scene of `points` points cut into `COLUMNS` x `ROWS` tiles of its ground plan, written
/// to `dir/tiles`; returns the folder and the scene's bounds.
pub fn write_tiles(dir: &Path, points: usize) -> (PathBuf, WorldBounds) {
    let cloud: PointCloud = sample_scene(points, 11);
    let tiles = ground_plan_tiles(&cloud, COLUMNS, ROWS);
    let folder = dir.join("tiles");
    std::fs::create_dir_all(&folder).expect("folder");
    for (index, points) in tiles.iter().enumerate() {
        let path = folder.join(format!("tile-{index:02}.las"));
        write_las(&path, &cloud.select(points), &LasWriteOptions::default()).expect("tile");
    }
    (folder, cloud.bounds)
}

/// The tiles of `points` points (`write_tiles`) and a flight of `frames` frames over the
/// first of them (`write_flight_over_one_tile`), written in `dir`: the tiles' folder, the
/// flight's file and the scene's bounds.
pub fn write_tiles_and_flight_over_one_tile(
    dir: &Path,
    points: usize,
    frames: usize,
) -> (PathBuf, PathBuf, WorldBounds) {
    let (tiles, bounds) = write_tiles(dir, points);
    let flight = write_flight_over_one_tile(dir, &bounds, frames);
    (tiles, flight, bounds)
}

/// A low flight of `frames` frames looking down over the first tile, then the second: the
/// rest are out of view. Written to `dir/flight.toml`.
pub fn write_flight(dir: &Path, bounds: &WorldBounds, frames: usize) -> PathBuf {
    write_flight_along(dir, bounds, frames, [0.0, 1.0])
}

/// A low flight of `frames` frames looking down over the middle of the first tile, moving
/// within it: it sees that tile, a twentieth of the campaign, and at most the edge of a
/// neighbour. Written to `dir/flight.toml`.
pub fn write_flight_over_one_tile(dir: &Path, bounds: &WorldBounds, frames: usize) -> PathBuf {
    write_flight_along(dir, bounds, frames, [-0.1, 0.1])
}

/// A low flight from above the middle of the first row's tile `columns[0]` (in tiles, from
/// the first tile's middle) to above `columns[1]`.
fn write_flight_along(
    dir: &Path,
    bounds: &WorldBounds,
    frames: usize,
    columns: [f64; 2],
) -> PathBuf {
    let size = bounds.size();
    let (tile_x, tile_y) = (size.x / COLUMNS as f64, size.y / ROWS as f64);
    let height = 0.2 * tile_x.min(tile_y);
    let over = |column: f64| {
        let (x, y) = (
            bounds.min.x + (column + 0.5) * tile_x,
            bounds.min.y + 0.5 * tile_y,
        );
        format!(
            "[[keyframes]]\nposition = [{x}, {}, {}]\ntarget = [{x}, {y}, {}]\nfov_y_deg = 40\n",
            y - 0.05 * height,
            bounds.max.z + height,
            bounds.min.z
        )
    };
    let text = format!(
        "frames = {frames}\ninterpolation = \"linear\"\n{}{}",
        over(columns[0]),
        over(columns[1])
    );
    let path = dir.join("flight.toml");
    std::fs::write(&path, text).expect("path");
    path
}

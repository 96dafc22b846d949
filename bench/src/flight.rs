//! The low keyframed flight the camera-first figures fly, locally and through a daemon: over
//! the middle of a campaign's inner tile, which it alone sees.

use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::request::{Keyframe, Point3};

/// The two keyframes of a low flight looking down over the middle of the inner tile of a grid
/// of `rows` x `columns` tiles over `bounds`, from 0.4 to 0.6 of the tile across.
pub fn inner_tile_keyframes(
    bounds: &WorldBounds,
    (rows, columns): (usize, usize),
) -> Vec<Keyframe> {
    let size = bounds.size();
    let (tile_x, tile_y) = (size.x / columns as f64, size.y / rows as f64);
    let (row, column) = ((rows / 2) as f64, (columns / 2) as f64);
    let height = 0.1 * tile_x.min(tile_y);
    let key = |share: f64| {
        let x = bounds.min.x + (column + share) * tile_x;
        let y = bounds.min.y + (row + 0.5) * tile_y;
        let point = |x, y, z| Point3 { x, y, z };
        Keyframe {
            position: point(x, y - 0.3 * height, bounds.max.z + height),
            target: point(x, y, bounds.min.z),
            up: point(0.0, 0.0, 1.0),
            fov_y_deg: 30.0,
        }
    };
    vec![key(0.4), key(0.6)]
}

/// `keyframes` as a camera path file of `frames` frames between them, linearly.
pub fn camera_path_file(keyframes: &[Keyframe], frames: u64) -> String {
    let mut text = format!("frames = {frames}\ninterpolation = \"linear\"\n");
    for key in keyframes {
        let [p, t, u] = [key.position, key.target, key.up].map(|p| [p.x, p.y, p.z]);
        text.push_str(&format!(
            "[[keyframes]]\nposition = {p:?}\ntarget = {t:?}\nup = {u:?}\nfov_y_deg = {}\n",
            key.fov_y_deg
        ));
    }
    text
}

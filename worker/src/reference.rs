//! The CPU reference renderer: the oracle that every GPU mode is tested against.
//!
//! Written for clarity, not speed, and independently of the GPU passes: it shares only the
//! camera convention (`camera::CameraTransform`) and computes in f64. Every point in the view
//! covers a `point_size`-pixel square. Depths are compared as the f32 the GPU stores.
//!
//! - Basic mode: per pixel, the point with the smallest (depth, colour) pair wins. That is the
//!   documented contract of the GPU's basic mode, so where depths are distinct the images
//!   must agree exactly.
//! - High-quality mode: per pixel, the rounded average colour of every point whose depth is
//!   at most `(1 + depth_band)` times the nearest depth.

use image::RgbaImage;

use crate::cloud::PointCloud;
use crate::raster::{FrameSettings, Quality, Shading};

/// The reference's output: an image and the depth of the nearest point of each pixel.
#[derive(Debug, Clone)]
pub struct ReferenceFrame {
    pub image: RgbaImage,
    /// Linear depth per pixel, row-major; +infinity where no point landed.
    pub depth: Vec<f32>,
}

/// Renders `cloud` as `settings` define it: quality mode, then shading.
pub fn render(cloud: &PointCloud, settings: &FrameSettings) -> ReferenceFrame {
    let mut frame = match settings.quality {
        Quality::Basic => render_basic(cloud, settings),
        Quality::High { depth_band } => render_high_quality(cloud, settings, depth_band),
    };
    if let Shading::Edl { strength, radius } = settings.shading {
        shade_edl(&mut frame, strength, radius);
    }
    frame
}

/// Eye-Dome Lighting as Potree does it: for each pixel, over 8 neighbours on a circle of
/// `radius` pixels, response = (1/8) sum max(0, log2 d - log2 d_neighbour), or 100 per
/// surface neighbour for a background pixel (the outline); colour *= exp(-300 strength
/// response). Computed in f32 like the GPU.
pub fn shade_edl(frame: &mut ReferenceFrame, strength: f32, radius: f32) {
    let (width, height) = (frame.image.width() as i64, frame.image.height() as i64);
    let depth_at = |x: i64, y: i64| {
        if (0..width).contains(&x) && (0..height).contains(&y) {
            frame.depth[(y * width + x) as usize]
        } else {
            f32::INFINITY
        }
    };
    let offsets: Vec<(i64, i64)> = (0..8)
        .map(|i| {
            let angle = std::f32::consts::TAU * i as f32 / 8.0;
            (
                (angle.cos() * radius).round() as i64,
                (angle.sin() * radius).round() as i64,
            )
        })
        .collect();
    let mut shaded = frame.image.clone();
    for (x, y, pixel) in shaded.enumerate_pixels_mut() {
        let here = depth_at(x as i64, y as i64);
        let mut sum = 0.0f32;
        for &(dx, dy) in &offsets {
            let there = depth_at(x as i64 + dx, y as i64 + dy);
            if there.is_infinite() {
                continue;
            }
            sum += if here.is_infinite() {
                100.0
            } else {
                (here.log2() - there.log2()).max(0.0)
            };
        }
        let shade = (-300.0 * strength * sum / 8.0).exp();
        if shade >= 1.0 {
            continue;
        }
        let [r, g, b, a] = pixel.0;
        let scale = |c: u8| (c as f32 * shade).round() as u8;
        let alpha = if here.is_infinite() {
            let a = a as f32 / 255.0;
            ((1.0 + (a - 1.0) * shade) * 255.0).round() as u8
        } else {
            a
        };
        pixel.0 = [scale(r), scale(g), scale(b), alpha];
    }
    frame.image = shaded;
}

/// Calls `visit(pixel index, depth, colour)` for every pixel that every visible point covers.
fn for_each_covered_pixel(
    cloud: &PointCloud,
    settings: &FrameSettings,
    mut visit: impl FnMut(usize, f32, u32),
) {
    let (width, height) = (settings.width as i64, settings.height as i64);
    let transform = settings
        .camera
        .transform(cloud.origin, settings.width, settings.height);
    let size = settings.point_size as i64;
    for (position, &colour) in cloud.positions.iter().zip(&cloud.colors) {
        let Some((px, py, depth)) = transform.project(position.as_dvec3()) else {
            continue;
        };
        let x0 = px.floor() as i64 - (size - 1) / 2;
        let y0 = py.floor() as i64 - (size - 1) / 2;
        for y in (y0..y0 + size).filter(|y| (0..height).contains(y)) {
            for x in (x0..x0 + size).filter(|x| (0..width).contains(x)) {
                visit((y * width + x) as usize, depth as f32, colour);
            }
        }
    }
}

/// The nearest depth of each pixel (+infinity where no point landed).
fn nearest_depths(cloud: &PointCloud, settings: &FrameSettings) -> Vec<f32> {
    let mut nearest = vec![f32::INFINITY; (settings.width * settings.height) as usize];
    for_each_covered_pixel(cloud, settings, |pixel, depth, _| {
        nearest[pixel] = nearest[pixel].min(depth);
    });
    nearest
}

fn frame_from(
    settings: &FrameSettings,
    colours: Vec<Option<u32>>,
    depth: Vec<f32>,
) -> ReferenceFrame {
    let background = u32::from_le_bytes(settings.background);
    let mut image = RgbaImage::new(settings.width, settings.height);
    for (pixel, colour) in image.pixels_mut().zip(colours) {
        pixel.0 = colour.unwrap_or(background).to_le_bytes();
    }
    ReferenceFrame { image, depth }
}

/// Basic mode: the nearest point's colour; at equal depths the smallest colour word.
pub fn render_basic(cloud: &PointCloud, settings: &FrameSettings) -> ReferenceFrame {
    let mut winner: Vec<Option<(f32, u32)>> =
        vec![None; (settings.width * settings.height) as usize];
    for_each_covered_pixel(cloud, settings, |pixel, depth, colour| {
        let wins = match winner[pixel] {
            None => true,
            Some((d, c)) => depth < d || (depth == d && colour < c),
        };
        if wins {
            winner[pixel] = Some((depth, colour));
        }
    });
    let depth = winner
        .iter()
        .map(|w| w.map_or(f32::INFINITY, |(d, _)| d))
        .collect();
    frame_from(
        settings,
        winner.iter().map(|w| w.map(|(_, c)| c)).collect(),
        depth,
    )
}

/// High-quality mode: the average colour of the points within the depth band.
pub fn render_high_quality(
    cloud: &PointCloud,
    settings: &FrameSettings,
    depth_band: f32,
) -> ReferenceFrame {
    let nearest = nearest_depths(cloud, settings);
    // The band test in f32, as the GPU does it.
    let band = 1.0f32 + depth_band;
    let mut sums = vec![[0u64; 4]; nearest.len()];
    for_each_covered_pixel(cloud, settings, |pixel, depth, colour| {
        if depth <= nearest[pixel] * band {
            let [r, g, b, _] = colour.to_le_bytes();
            let sum = &mut sums[pixel];
            sum[0] += r as u64;
            sum[1] += g as u64;
            sum[2] += b as u64;
            sum[3] += 1;
        }
    });
    let average = |sum: &[u64; 4]| {
        let channel = |total: u64| (total as f64 / sum[3] as f64).round() as u8;
        u32::from_le_bytes([channel(sum[0]), channel(sum[1]), channel(sum[2]), 255])
    };
    let colours = sums
        .iter()
        .map(|s| (s[3] > 0).then(|| average(s)))
        .collect();
    frame_from(settings, colours, nearest)
}

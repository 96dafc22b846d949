//! The CPU reference renderer: the oracle that every GPU mode is tested against.
//!
//! Written for clarity, not speed, and independently of the GPU passes: it shares only the
//! camera convention (`camera::CameraTransform`) and computes in f64. Every point in the view
//! covers a square of `FrameSettings::point_side_at` its depth (the pixels in its disc with
//! round points). Depths are compared as the f32 the GPU stores.
//!
//! - Basic mode: per pixel, the point with the smallest (depth, color) pair wins. That is the
//!   documented contract of the GPU's basic mode, so where depths are distinct the images
//!   must agree exactly.
//! - High-quality mode: per pixel, the rounded average color of every point whose depth is
//!   at most `(1 + depth_band)` times the nearest depth.
//! - Visibility, filling and Pintus shading (Pintus et al. 2011): written from the paper in
//!   f64, reconstructing points through the inverse view-projection matrix.

use glam::{DMat4, DVec3, DVec4};
use image::RgbaImage;

use crate::camera::Projection;
use crate::cloud::PointCloud;
use crate::raster::exposure::{self, LumaHistograms};
use crate::raster::{
    Exposure, FrameSettings, Quality, Shading, FILL_DEPTH_TOLERANCE, VISIBILITY_MIN_SOLID_ANGLE,
};

/// The reference's output: an image and the depth of the nearest point of each pixel.
#[derive(Debug, Clone)]
pub struct ReferenceFrame {
    pub image: RgbaImage,
    /// Linear depth per pixel, row-major; +infinity where no point landed.
    pub depth: Vec<f32>,
    /// The gain exposed with after Eye-Dome Lighting, as [`Frame::gain`](crate::raster::Frame)
    /// reports it; `None` without EDL.
    pub gain: Option<f32>,
}

/// Renders `cloud` as `settings` define it: quality mode, then shading.
pub fn render(cloud: &PointCloud, settings: &FrameSettings) -> ReferenceFrame {
    let mut frame = match settings.quality {
        Quality::Basic => render_basic(cloud, settings),
        Quality::High { depth_band } => render_high_quality(cloud, settings, depth_band),
    };
    if let Some(fill) = settings.fill {
        let mutable = remove_hidden(&mut frame, settings, fill.kernel);
        fill_holes(&mut frame, &mutable, fill.iterations());
    }
    match settings.shading {
        Shading::None => {}
        Shading::Edl { strength, radius } => {
            frame.gain = Some(shade_edl(&mut frame, strength, radius, settings.exposure));
        }
        Shading::Pintus { levels, exponent } => {
            shade_pintus(&mut frame, settings, levels, exponent)
        }
    }
    frame
}

/// Turns pixels and linear depths back into points (relative to the camera target) through
/// the inverse of the camera's view-projection matrix.
struct Unprojector {
    inverse: DMat4,
    depth_row: DVec4,
    eye: DVec3,
    perspective: bool,
    width: f64,
    height: f64,
}

impl Unprojector {
    fn new(settings: &FrameSettings) -> Self {
        let camera = &settings.camera;
        let transform = camera.transform(camera.target, settings.width, settings.height);
        Self {
            inverse: transform.view_proj.inverse(),
            depth_row: transform.depth_row,
            eye: camera.position - camera.target,
            perspective: matches!(camera.projection, Projection::Perspective { .. }),
            width: settings.width as f64,
            height: settings.height as f64,
        }
    }

    /// The point on the ray through the centre of pixel (x, y) at linear depth `depth`.
    fn point(&self, x: i64, y: i64, depth: f64) -> DVec3 {
        let ndc_x = (x as f64 + 0.5) / self.width * 2.0 - 1.0;
        let ndc_y = 1.0 - (y as f64 + 0.5) / self.height * 2.0;
        let at = |z: f64| {
            let p = self.inverse * DVec4::new(ndc_x, ndc_y, z, 1.0);
            p.truncate() / p.w
        };
        let (a, b) = (at(0.0), at(1.0));
        let depth_of = |p: DVec3| self.depth_row.dot(p.extend(1.0));
        a + (b - a) * ((depth - depth_of(a)) / (depth_of(b) - depth_of(a)))
    }

    /// Unit vector from `p` towards the camera.
    fn to_camera(&self, p: DVec3) -> DVec3 {
        if self.perspective {
            (self.eye - p).normalize()
        } else {
            -self.depth_row.truncate().normalize()
        }
    }
}

/// Pintus et al.'s visibility: for each pixel, the kernel (side `kernel`) around it is cut
/// into 8 sectors centred on the axes and diagonals; in each, the horizon is the neighbour
/// whose direction from the pixel's point is closest to the direction to the camera, and the
/// open cone sector spans (2 pi / 8)(1 - cos(angle to the horizon)) steradians, or
/// (2 pi / 8) 2 with no neighbour. Pixels with less than [`VISIBILITY_MIN_SOLID_ANGLE`] in
/// all are emptied (depth +infinity, background color) and returned as mutable. A background
/// pixel is infinitely far: any neighbour closes its sector.
pub fn remove_hidden(
    frame: &mut ReferenceFrame,
    settings: &FrameSettings,
    kernel: u32,
) -> Vec<bool> {
    let unproject = Unprojector::new(settings);
    let (width, height) = (settings.width as i64, settings.height as i64);
    let radius = (kernel / 2) as i64;
    let depth = frame.depth.clone();
    let background = settings.background;
    let mut mutable = vec![false; depth.len()];
    for y in 0..height {
        for x in 0..width {
            let here = depth[(y * width + x) as usize];
            let centre = here.is_finite().then(|| unproject.point(x, y, here as f64));
            let mut horizon: [Option<f64>; 8] = [None; 8];
            for ny in (y - radius..=y + radius).filter(|ny| (0..height).contains(ny)) {
                for nx in (x - radius..=x + radius).filter(|nx| (0..width).contains(nx)) {
                    let there = depth[(ny * width + nx) as usize];
                    if (nx, ny) == (x, y) || there.is_infinite() {
                        continue;
                    }
                    let cosine = match centre {
                        Some(p0) => {
                            let towards = (unproject.point(nx, ny, there as f64) - p0).normalize();
                            unproject.to_camera(p0).dot(towards)
                        }
                        None => 1.0,
                    };
                    let angle = ((ny - y) as f64).atan2((nx - x) as f64);
                    let sector = ((angle / std::f64::consts::FRAC_PI_4).round() as i64)
                        .rem_euclid(8) as usize;
                    let h = horizon[sector].get_or_insert(cosine);
                    *h = h.max(cosine);
                }
            }
            let open: f64 = horizon
                .iter()
                .map(|h| std::f64::consts::TAU / 8.0 * h.map_or(2.0, |cosine| 1.0 - cosine))
                .sum();
            if open < VISIBILITY_MIN_SOLID_ANGLE as f64 {
                let pixel = (y * width + x) as usize;
                mutable[pixel] = true;
                frame.depth[pixel] = f32::INFINITY;
                frame.image.get_pixel_mut(x as u32, y as u32).0 = background;
            }
        }
    }
    mutable
}

/// Pintus et al.'s anisotropic filling: `iterations` synchronous 3x3 steps over the mutable
/// pixels. An empty one takes the median depth of its valid neighbours (the lower middle one
/// when even; equal depths in row-major order) with that neighbour's color; a filled one
/// becomes the average of its valid neighbours and itself weighted by equation 1,
/// (1 - r/2)(1 - min(1, |z - z0| / delta)), delta = [`FILL_DEPTH_TOLERANCE`] z0.
pub fn fill_holes(frame: &mut ReferenceFrame, mutable: &[bool], iterations: u32) {
    let (width, height) = (frame.image.width() as i64, frame.image.height() as i64);
    for _ in 0..iterations {
        let depth = frame.depth.clone();
        let image = frame.image.clone();
        for y in 0..height {
            for x in 0..width {
                let pixel = (y * width + x) as usize;
                if !mutable[pixel] {
                    continue;
                }
                let mut neighbours = Vec::new();
                for ny in (y - 1..=y + 1).filter(|ny| (0..height).contains(ny)) {
                    for nx in (x - 1..=x + 1).filter(|nx| (0..width).contains(nx)) {
                        let z = depth[(ny * width + nx) as usize];
                        if z.is_finite() {
                            let r = (((nx - x).pow(2) + (ny - y).pow(2)) as f64).sqrt();
                            let color = image.get_pixel(nx as u32, ny as u32).0;
                            neighbours.push((z, color, r));
                        }
                    }
                }
                if neighbours.is_empty() {
                    continue;
                }
                let z0 = depth[pixel];
                let (z, color) = if z0.is_infinite() {
                    neighbours.sort_by(|a, b| a.0.total_cmp(&b.0));
                    let (z, color, _) = neighbours[(neighbours.len() - 1) / 2];
                    (z, color)
                } else {
                    let delta = FILL_DEPTH_TOLERANCE as f64 * z0 as f64;
                    let mut total = 0.0;
                    let mut z_sum = 0.0;
                    let mut color_sum = [0.0f64; 4];
                    for &(z, color, r) in &neighbours {
                        let w = (1.0 - r / 2.0)
                            * (1.0 - ((z as f64 - z0 as f64).abs() / delta).min(1.0));
                        total += w;
                        z_sum += w * z as f64;
                        for c in 0..4 {
                            color_sum[c] += w * color[c] as f64 / 255.0;
                        }
                    }
                    ((z_sum / total) as f32, color_sum.map(|c| unorm8(c / total)))
                };
                frame.depth[pixel] = z;
                frame.image.get_pixel_mut(x as u32, y as u32).0 = color;
            }
        }
    }
}

/// A color channel from 0..1 to 0..255 as WGSL's `pack4x8unorm` does it.
fn unorm8(value: f64) -> u8 {
    (value.clamp(0.0, 1.0) * 255.0 + 0.5).floor() as u8
}

/// Pintus et al.'s shape-depicting shading, equations 2 and 3: on each level k, over the
/// valid 3x3 neighbourhood of the depth D^k, mean mu and standard deviation sigma;
/// w^k = clamp(1 - |d - (mu - sigma)| / (2 sigma + eps)); D^(k+1) = mu - sigma / 2. eps is the
/// pixel's footprint at its depth (see shaders/pintus.wgsl for why). Color times
/// sum_k w^k / (k+1)^exponent over the sum of the weights. Background pixels are unchanged.
pub fn shade_pintus(
    frame: &mut ReferenceFrame,
    settings: &FrameSettings,
    levels: u32,
    exponent: f32,
) {
    let (width, height) = (settings.width as i64, settings.height as i64);
    let footprint = |d: f64| match settings.camera.projection {
        Projection::Perspective { fov_y_deg } => {
            2.0 * (fov_y_deg.to_radians() / 2.0).tan() * d / height as f64
        }
        Projection::Orthographic { height: view } => view / height as f64,
    };
    let mut depth: Vec<f64> = frame.depth.iter().map(|&d| d as f64).collect();
    let mut shade = vec![0.0f64; depth.len()];
    let mut total_weight = 0.0;
    for k in 0..levels {
        let weight = 1.0 / ((k + 1) as f64).powf(exponent as f64);
        total_weight += weight;
        let mut next = depth.clone();
        for y in 0..height {
            for x in 0..width {
                let pixel = (y * width + x) as usize;
                let d = depth[pixel];
                if d.is_infinite() {
                    continue;
                }
                let mut window = Vec::with_capacity(9);
                for ny in (y - 1..=y + 1).filter(|ny| (0..height).contains(ny)) {
                    for nx in (x - 1..=x + 1).filter(|nx| (0..width).contains(nx)) {
                        let z = depth[(ny * width + nx) as usize];
                        if z.is_finite() {
                            window.push(z);
                        }
                    }
                }
                let n = window.len() as f64;
                let mean = window.iter().sum::<f64>() / n;
                let sigma = (window.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / n).sqrt();
                let (low, high) = (mean - sigma, mean + sigma);
                let w = (1.0 - (d - low).abs() / (high - low + footprint(d))).clamp(0.0, 1.0);
                shade[pixel] += weight * w;
                next[pixel] = (mean + low) / 2.0;
            }
        }
        depth = next;
    }
    for (pixel, color) in frame.image.pixels_mut().enumerate() {
        if frame.depth[pixel].is_finite() {
            let s = shade[pixel] / total_weight;
            for c in 0..3 {
                color.0[c] = unorm8(color.0[c] as f64 / 255.0 * s);
            }
        }
    }
}

/// Eye-Dome Lighting as `shaders/edl.wgsl` describes it: over 4 pairs of opposite neighbours
/// on a circle of `radius` pixels, how far the pixel lies behind the plane through a pair (in
/// inverse depth), or behind a lone neighbour; 100 per surface neighbour for a background
/// pixel (the outline); color *= exp(-300 strength response / 8). Then the exposure that
/// brings the surface's median luma back (`raster::exposure`), or the gain `setting` holds;
/// returns the gain. Computed in f32 like the GPU.
pub fn shade_edl(frame: &mut ReferenceFrame, strength: f32, radius: f32, setting: Exposure) -> f32 {
    let (width, height) = (frame.image.width() as i64, frame.image.height() as i64);
    let depth_at = |x: i64, y: i64| {
        if (0..width).contains(&x) && (0..height).contains(&y) {
            frame.depth[(y * width + x) as usize]
        } else {
            f32::INFINITY
        }
    };
    let offsets: Vec<(i64, i64)> = (0..4)
        .map(|i| {
            let angle = std::f32::consts::TAU * i as f32 / 8.0;
            (
                (angle.cos() * radius).round() as i64,
                (angle.sin() * radius).round() as i64,
            )
        })
        .collect();
    let mut shaded = frame.image.clone();
    let mut histograms = LumaHistograms::default();
    for (x, y, pixel) in shaded.enumerate_pixels_mut() {
        let (x, y) = (x as i64, y as i64);
        let here = depth_at(x, y);
        let mut sum = 0.0f32;
        for &(dx, dy) in &offsets {
            let (a, b) = (depth_at(x + dx, y + dy), depth_at(x - dx, y - dy));
            sum += match (here.is_finite(), a.is_finite(), b.is_finite()) {
                (false, a, b) => 100.0 * (f32::from(u8::from(a)) + f32::from(u8::from(b))),
                (true, true, true) => 2.0 * (here * (1.0 / a + 1.0 / b) * 0.5).log2().max(0.0),
                (true, true, false) => (here.log2() - a.log2()).max(0.0),
                (true, false, true) => (here.log2() - b.log2()).max(0.0),
                (true, false, false) => 0.0,
            };
        }
        let shade = (-300.0 * strength * sum / 8.0).exp();
        let [r, g, b, a] = pixel.0;
        if shade < 1.0 {
            let scale = |c: u8| (c as f32 * shade).round() as u8;
            let alpha = if here.is_infinite() {
                let a = a as f32 / 255.0;
                ((1.0 + (a - 1.0) * shade) * 255.0).round() as u8
            } else {
                a
            };
            pixel.0 = [scale(r), scale(g), scale(b), alpha];
        }
        if here.is_finite() {
            let [r2, g2, b2, _] = pixel.0;
            histograms.count([r, g, b], [r2, g2, b2]);
        }
    }
    let gain = match setting {
        Exposure::Measured => histograms.gain(),
        Exposure::Held(gain) => gain,
    };
    exposure::expose(&mut shaded, &frame.depth, gain);
    frame.image = shaded;
    gain
}

/// Calls `visit(pixel index, depth, color)` for every pixel that every visible point covers.
fn for_each_covered_pixel(
    cloud: &PointCloud,
    settings: &FrameSettings,
    mut visit: impl FnMut(usize, f32, u32),
) {
    let (width, height) = (settings.width as i64, settings.height as i64);
    let transform = settings
        .camera
        .transform(cloud.origin, settings.width, settings.height);
    for (position, &color) in cloud.positions.iter().zip(&cloud.colors) {
        let Some((px, py, depth)) = transform.project(position.as_dvec3()) else {
            continue;
        };
        let size = settings.point_side_at(depth as f32) as i64;
        let x0 = px.floor() as i64 - (size - 1) / 2;
        let y0 = py.floor() as i64 - (size - 1) / 2;
        for y in (y0..y0 + size).filter(|y| (0..height).contains(y)) {
            for x in (x0..x0 + size).filter(|x| (0..width).contains(x)) {
                // Round points: pixel centres in the disc, as the shaders' `splat_pixel`.
                let (cx, cy) = (2 * (x - x0) + 1 - size, 2 * (y - y0) + 1 - size);
                if settings.round_points && cx * cx + cy * cy > size * size {
                    continue;
                }
                visit((y * width + x) as usize, depth as f32, color);
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
    colors: Vec<Option<u32>>,
    depth: Vec<f32>,
) -> ReferenceFrame {
    let background = u32::from_le_bytes(settings.background);
    let mut image = RgbaImage::new(settings.width, settings.height);
    for (pixel, color) in image.pixels_mut().zip(colors) {
        pixel.0 = color.unwrap_or(background).to_le_bytes();
    }
    ReferenceFrame {
        image,
        depth,
        gain: None,
    }
}

/// Basic mode: the nearest point's color; at equal depths the smallest color word.
pub fn render_basic(cloud: &PointCloud, settings: &FrameSettings) -> ReferenceFrame {
    let winner = basic_winners(cloud, settings);
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

/// Pixels whose nearest point has a rival of another color at the same depth or behind it
/// by at most `relative` of the depth.
///
/// There the winner hangs on rounding. This reference projects the exact positions in f64;
/// the GPU projects positions quantised per batch in f32, so the two copies of a point that
/// fall in different batches are no longer an exact tie there, and an adapter that fuses the
/// multiply-adds (NVIDIA's does; lavapipe does not) can tip a near tie the other way.
pub fn depth_ties(cloud: &PointCloud, settings: &FrameSettings, relative: f32) -> Vec<bool> {
    let winner = basic_winners(cloud, settings);
    let mut tied = vec![false; winner.len()];
    for_each_covered_pixel(cloud, settings, |pixel, depth, color| {
        if let Some((d, c)) = winner[pixel] {
            if color != c && depth - d <= relative * d.abs() {
                tied[pixel] = true;
            }
        }
    });
    tied
}

/// The nearest point of each pixel, as (depth, color); equal depths go to the smaller color.
fn basic_winners(cloud: &PointCloud, settings: &FrameSettings) -> Vec<Option<(f32, u32)>> {
    let mut winner: Vec<Option<(f32, u32)>> =
        vec![None; (settings.width * settings.height) as usize];
    for_each_covered_pixel(cloud, settings, |pixel, depth, color| {
        let wins = match winner[pixel] {
            None => true,
            Some((d, c)) => depth < d || (depth == d && color < c),
        };
        if wins {
            winner[pixel] = Some((depth, color));
        }
    });
    winner
}

/// High-quality mode: the average color of the points within the depth band.
pub fn render_high_quality(
    cloud: &PointCloud,
    settings: &FrameSettings,
    depth_band: f32,
) -> ReferenceFrame {
    render_high_quality_weighted(cloud, settings, depth_band, &vec![1; cloud.len()])
}

/// High quality where point `i` stands for `weights[i]` points (a level-of-detail cut's,
/// `shaders/hq_accumulate_weighted.wgsl`): its color and count added that many times.
pub fn render_high_quality_weighted(
    cloud: &PointCloud,
    settings: &FrameSettings,
    depth_band: f32,
    weights: &[u32],
) -> ReferenceFrame {
    assert_eq!(weights.len(), cloud.len(), "one weight a point");
    let nearest = nearest_depths(cloud, settings);
    // The band test in f32, as the GPU does it.
    let band = 1.0f32 + depth_band;
    // The same walk over the pixels, each point known by its index.
    let indexed = PointCloud {
        colors: (0..cloud.len() as u32).collect(),
        ..cloud.clone()
    };
    let mut sums = vec![[0u64; 4]; nearest.len()];
    for_each_covered_pixel(&indexed, settings, |pixel, depth, i| {
        if depth <= nearest[pixel] * band {
            let [r, g, b, _] = cloud.colors[i as usize].to_le_bytes();
            let w = u64::from(weights[i as usize]);
            let sum = &mut sums[pixel];
            sum[0] += r as u64 * w;
            sum[1] += g as u64 * w;
            sum[2] += b as u64 * w;
            sum[3] += w;
        }
    });
    let average = |sum: &[u64; 4]| {
        let channel = |total: u64| (total as f64 / sum[3] as f64).round() as u8;
        u32::from_le_bytes([channel(sum[0]), channel(sum[1]), channel(sum[2]), 255])
    };
    let colors = sums
        .iter()
        .map(|s| (s[3] > 0).then(|| average(s)))
        .collect();
    frame_from(settings, colors, nearest)
}

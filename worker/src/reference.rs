//! The CPU reference renderer: the oracle that every GPU mode is tested against.
//!
//! Written for clarity, not speed, and independently of the GPU passes: it shares only the
//! camera convention (`camera::CameraTransform`) and computes in f64. For every point in the
//! view it covers a `point_size`-pixel square and keeps, per pixel, the point with the smallest
//! (depth, colour) pair, the depth compared as the f32 the GPU stores. That is the documented
//! contract of the basic mode, so where depths are distinct the images must agree exactly.

use image::RgbaImage;

use crate::cloud::PointCloud;
use crate::raster::FrameSettings;

/// The reference's output: an image and the depth of the point each pixel shows.
#[derive(Debug, Clone)]
pub struct ReferenceFrame {
    pub image: RgbaImage,
    /// Linear depth per pixel, row-major; +infinity where no point landed.
    pub depth: Vec<f32>,
}

/// Renders `cloud` as the basic mode defines it.
pub fn render_basic(cloud: &PointCloud, settings: &FrameSettings) -> ReferenceFrame {
    let (width, height) = (settings.width as usize, settings.height as usize);
    let transform = settings
        .camera
        .transform(cloud.origin, settings.width, settings.height);
    // Per pixel: the winning (depth as f32, colour), or None.
    let mut nearest: Vec<Option<(f32, u32)>> = vec![None; width * height];

    for (position, &colour) in cloud.positions.iter().zip(&cloud.colors) {
        let Some((px, py, depth)) = transform.project(position.as_dvec3()) else {
            continue;
        };
        let depth = depth as f32;
        let size = settings.point_size as i64;
        let x0 = px.floor() as i64 - (size - 1) / 2;
        let y0 = py.floor() as i64 - (size - 1) / 2;
        for y in y0..y0 + size {
            for x in x0..x0 + size {
                if x < 0 || y < 0 || x >= width as i64 || y >= height as i64 {
                    continue;
                }
                let slot = &mut nearest[y as usize * width + x as usize];
                let candidate = (depth, colour);
                let wins = match *slot {
                    None => true,
                    Some((d, c)) => depth < d || (depth == d && colour < c),
                };
                if wins {
                    *slot = Some(candidate);
                }
            }
        }
    }

    let background = u32::from_le_bytes(settings.background);
    let mut image = RgbaImage::new(settings.width, settings.height);
    let mut depth = vec![f32::INFINITY; width * height];
    for (i, pixel) in image.pixels_mut().enumerate() {
        let colour = match nearest[i] {
            Some((d, c)) => {
                depth[i] = d;
                c
            }
            None => background,
        };
        pixel.0 = colour.to_le_bytes();
    }
    ReferenceFrame { image, depth }
}

//! Frames too large for one pass: split into a grid of tiles whose buffers each fit the
//! adapter's storage binding limit, each drawn through its window of the frame's frustum
//! (`Camera::window_transform`) with an apron, an overlap wide enough for every pass that
//! reads neighbouring pixels, then cropped to its own pixels and stitched into one frame.
//!
//! A tile's pixels come out as the whole frame's would: points are projected by the same
//! frustum cut to the tile, the passes on the resolved images see the same neighbours as far
//! as they reach (and the tile's edge only where the frame's is), and the screen-space passes
//! compute the frame's own view rays (`ScreenParams::frame_offset`). Only the f32 rounding of
//! the tile's projection can move a point lying within about a millionth of a pixel of a
//! pixel's edge to the neighbouring pixel.

use std::time::Instant;

use glam::DVec3;
use image::RgbaImage;

use super::occlusion::{self, OcclusionSkipped};
use super::{
    downsample, Clock, FillSettings, FrameSettings, GpuPointCloud, Quality, RenderError, Renderer,
    Shading, Stage, StageTimings, MAX_FILL_KERNEL, MAX_IMAGE_SIDE, MAX_PINTUS_LEVELS,
    MAX_POINT_SIZE, MAX_SUPERSAMPLE,
};
use crate::camera::{Camera, CameraTransform, ImageWindow};
use crate::raster::Frame;

/// The part of a frame one pass of the renderer draws: all of it, or one tile.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct FrameWindow {
    pub frame_width: u32,
    pub frame_height: u32,
    pub window: ImageWindow,
    /// The pixels of the drawn window that frame-wide statistics count (the exposure's
    /// histograms): all of a whole frame, a tile's core without its apron.
    pub counted: ImageWindow,
}

impl FrameWindow {
    /// All of a `width` x `height` frame.
    pub fn whole(width: u32, height: u32) -> Self {
        Self {
            frame_width: width,
            frame_height: height,
            window: ImageWindow::whole(width, height),
            counted: ImageWindow::whole(width, height),
        }
    }

    /// The camera's transform for this window of the frame.
    pub fn transform(&self, camera: &Camera, origin: DVec3) -> CameraTransform {
        if self.window == ImageWindow::whole(self.frame_width, self.frame_height) {
            // The plain projection, so that an untiled frame is drawn exactly as it always was.
            return camera.transform(origin, self.frame_width, self.frame_height);
        }
        camera.window_transform(origin, self.frame_width, self.frame_height, self.window)
    }
}

/// Bytes per pixel of a frame's largest per-pixel binding: the high-quality accumulator (4
/// words), else the point framebuffer (2 words).
pub(crate) fn bytes_per_pixel(quality: Quality) -> u64 {
    match quality {
        Quality::Basic => 8,
        Quality::High { .. } => 16,
    }
}

/// How far, in pixels of the image drawn (`settings` already scaled for supersampling), a
/// pixel's value can depend on others: a splat's reach, then the visibility kernel's radius
/// and one pixel per filling step, then the shading's samples (Eye-Dome Lighting's radius, one
/// pixel per Pintus level).
pub(crate) fn apron(settings: &FrameSettings) -> u32 {
    let fill = settings
        .fill
        .map_or(0, |fill| fill.kernel / 2 + fill.iterations());
    let shading = match settings.shading {
        Shading::None => 0,
        Shading::Edl { radius, .. } => radius.max(0.0).ceil() as u32,
        Shading::Pintus { levels, .. } => levels,
    };
    settings
        .point_size
        .saturating_add(fill)
        .saturating_add(shading)
}

/// The tiles of a frame: a grid of cores, the frame's own pixels, each drawn (supersampled)
/// as a tile of one size that holds the core and, inside the frame, its apron.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct TileGrid {
    /// The frame, in output pixels.
    pub width: u32,
    pub height: u32,
    /// The supersampling factor: drawn pixels per output pixel along each side.
    pub scale: u32,
    /// A core's size in output pixels (the last column's and row's may be smaller).
    pub core_width: u32,
    pub core_height: u32,
    /// Every tile's size, in drawn pixels.
    pub tile_width: u32,
    pub tile_height: u32,
    pub apron: u32,
}

/// The largest side of a drawn (supersampled) image that an adapter whose storage bindings
/// hold `limit` bytes renders whatever a request's options are. Tiles lift the binding limit, so
/// this is [`MAX_IMAGE_SIDE`] unless not even a one-pixel tile with the widest apron fits (the
/// high-quality accumulator at the largest point size, filling kernel and shading, about
/// 10 MiB; wgpu's default limits promise 128 MiB): then the side of a square frame drawn whole.
pub fn largest_drawn_side(limit: u64) -> u32 {
    let camera = Camera {
        position: DVec3::new(0.0, -10.0, 0.0),
        target: DVec3::ZERO,
        up: DVec3::Z,
        projection: crate::camera::Projection::Perspective { fov_y_deg: 50.0 },
        near: 1.0,
        far: 100.0,
    };
    let widest = FrameSettings {
        quality: Quality::HIGH,
        point_size: MAX_POINT_SIZE,
        fill: Some(FillSettings {
            kernel: MAX_FILL_KERNEL,
        }),
        shading: Shading::Pintus {
            levels: MAX_PINTUS_LEVELS,
            exponent: 1.0,
        },
        supersample: MAX_SUPERSAMPLE,
        ..FrameSettings::new(
            MAX_IMAGE_SIDE / MAX_SUPERSAMPLE,
            MAX_IMAGE_SIDE / MAX_SUPERSAMPLE,
            camera,
        )
    };
    if TileGrid::plan(&widest, limit).is_ok() {
        return MAX_IMAGE_SIDE;
    }
    let whole = (limit / bytes_per_pixel(Quality::HIGH)).isqrt();
    whole.min(u64::from(MAX_IMAGE_SIDE)) as u32
}

/// One tile: its core in output pixels, and the window of the drawn (supersampled) frame it
/// is drawn as.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Tile {
    pub core: ImageWindow,
    pub drawn: ImageWindow,
}

impl TileGrid {
    /// The fewest tiles of `settings`' frame whose largest per-pixel binding fits `limit`
    /// bytes; `None` when the whole frame does. `ImageTooLarge` only when not even a tile of
    /// one output pixel with its apron fits.
    pub fn plan(settings: &FrameSettings, limit: u64) -> Result<Option<TileGrid>, RenderError> {
        let scale = settings.supersample.max(1);
        let drawn = settings.scaled_for_supersampling();
        let per_pixel = bytes_per_pixel(drawn.quality);
        let bytes = |w: u32, h: u32| u64::from(w) * u64::from(h) * per_pixel;
        if bytes(drawn.width, drawn.height) <= limit {
            return Ok(None);
        }
        let apron = apron(&drawn);
        let (width, height) = (settings.width, settings.height);
        // A core of `core` output pixels is drawn with the apron on both sides, within the frame.
        let tile_side = |core: u32, frame: u32| {
            (u64::from(core) * u64::from(scale) + 2 * u64::from(apron)).min(u64::from(frame)) as u32
        };
        let mut best: Option<(u64, u64, TileGrid)> = None;
        for rows in 1..=height {
            let core_height = height.div_ceil(rows);
            // Each core height once, at the fewest rows that give it.
            if rows > 1 && height.div_ceil(rows - 1) == core_height {
                continue;
            }
            let tile_height = tile_side(core_height, drawn.height);
            let widest = limit / (per_pixel * u64::from(tile_height));
            let core_width = if widest >= u64::from(drawn.width) {
                width
            } else {
                let fits = widest.saturating_sub(2 * u64::from(apron)) / u64::from(scale);
                fits.min(u64::from(width)) as u32
            };
            if core_width == 0 {
                continue;
            }
            // As many columns as needed, then cores of even width.
            let core_width = width.div_ceil(width.div_ceil(core_width));
            let tile_width = tile_side(core_width, drawn.width);
            let grid = TileGrid {
                width,
                height,
                scale,
                core_width,
                core_height,
                tile_width,
                tile_height,
                apron,
            };
            let tiles = u64::from(grid.columns()) * u64::from(grid.rows());
            // Of as many tiles, the fewest pixels drawn twice.
            let drawn_pixels = tiles * u64::from(tile_width) * u64::from(tile_height);
            if best.is_none_or(|(t, p, _)| (tiles, drawn_pixels) < (t, p)) {
                best = Some((tiles, drawn_pixels, grid));
            }
        }
        match best {
            Some((_, _, grid)) => Ok(Some(grid)),
            None => {
                let side = |frame: u32| tile_side(1, frame);
                Err(RenderError::ImageTooLarge {
                    width: drawn.width,
                    height: drawn.height,
                    needed_mib: bytes(side(drawn.width), side(drawn.height)).div_ceil(1 << 20),
                    limit_mib: limit >> 20,
                })
            }
        }
    }

    pub fn columns(&self) -> u32 {
        self.width.div_ceil(self.core_width)
    }

    pub fn rows(&self) -> u32 {
        self.height.div_ceil(self.core_height)
    }

    /// The tiles, row by row.
    pub fn tiles(&self) -> impl Iterator<Item = Tile> + '_ {
        (0..self.rows())
            .flat_map(move |row| (0..self.columns()).map(move |col| self.tile(col, row)))
    }

    fn tile(&self, col: u32, row: u32) -> Tile {
        let span = |index: u32, core: u32, frame: u32, tile: u32| {
            let start = index * core;
            let end = (start + core).min(frame);
            // The tile starts an apron before its core, moved back into the drawn frame.
            let drawn_start = (start * self.scale)
                .saturating_sub(self.apron)
                .min(frame * self.scale - tile);
            (start, end - start, drawn_start)
        };
        let (x0, width, drawn_x0) = span(col, self.core_width, self.width, self.tile_width);
        let (y0, height, drawn_y0) = span(row, self.core_height, self.height, self.tile_height);
        Tile {
            core: ImageWindow {
                x0,
                y0,
                width,
                height,
            },
            drawn: ImageWindow {
                x0: drawn_x0,
                y0: drawn_y0,
                width: self.tile_width,
                height: self.tile_height,
            },
        }
    }
}

/// What the point passes of a tiled frame did, summed over its tiles.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct TiledCounts {
    pub listed_batches: u32,
    pub listed_points: u64,
    pub occlusion_skipped: OcclusionSkipped,
}

/// Renders `settings`' frame tile by tile with `renderer` and stitches it; returns it with the
/// counts of all its tiles.
pub(super) fn render(
    renderer: &mut Renderer,
    cloud: &GpuPointCloud,
    settings: &FrameSettings,
    grid: &TileGrid,
) -> Result<(Frame, TiledCounts), RenderError> {
    let drawn = settings.scaled_for_supersampling();
    let (width, height) = (settings.width, settings.height);
    tracing::debug!(
        width,
        height,
        columns = grid.columns(),
        rows = grid.rows(),
        apron = grid.apron,
        "frame rendered in tiles"
    );
    let mut image = RgbaImage::new(width, height);
    let mut depth = settings
        .read_depth
        .then(|| vec![f32::INFINITY; width as usize * height as usize]);
    let mut timings = StageTimings::default();
    let mut counts = TiledCounts::default();
    let mut atomics = None;
    for tile in grid.tiles() {
        let view = FrameWindow {
            frame_width: drawn.width,
            frame_height: drawn.height,
            window: tile.drawn,
            counted: core_in_tile(tile, grid.scale),
        };
        let tile_settings = FrameSettings {
            width: tile.drawn.width,
            height: tile.drawn.height,
            ..drawn
        };
        let frame = renderer.render_once(cloud, &tile_settings, view)?;
        timings.add(&frame.timings);
        atomics = Some(frame.atomics);
        counts.listed_batches += renderer.batches.total();
        counts.listed_points += renderer.batches.listed_points();

        // The counts, the crop and the copy into the frame are the tile's share of the readback.
        let started = Instant::now();
        if let Some(targets) = &renderer.targets {
            let skipped = occlusion::read_skipped(&renderer.gpu, &targets.occlusion)?;
            counts.occlusion_skipped.depth_pass += skipped.depth_pass;
            counts.occlusion_skipped.later_passes += skipped.later_passes;
        }
        let k = grid.scale;
        let mut core = Frame {
            image: crop_image(&frame.image, tile, k),
            depth: frame.depth.as_deref().map(|d| crop_depth(d, tile, k)),
            timings: StageTimings::default(),
            atomics: frame.atomics,
            gain: None,
        };
        let mut readback_ms = started.elapsed().as_secs_f64() * 1e3;
        if k > 1 {
            let started = Instant::now();
            core = downsample(core, k);
            let ms = started.elapsed().as_secs_f64() * 1e3;
            timings.add_ms(Stage::Downsample, ms, Clock::Host);
        }
        let started = Instant::now();
        paste(&mut image, depth.as_deref_mut(), &core, tile.core);
        readback_ms += started.elapsed().as_secs_f64() * 1e3;
        timings.add_ms(Stage::Readback, readback_ms, Clock::Host);
    }
    let atomics = atomics.ok_or_else(|| RenderError::Gpu("a tiled frame without tiles".into()))?;
    Ok((
        Frame {
            image,
            depth,
            timings,
            atomics,
            gain: None,
        },
        counts,
    ))
}

/// Where a tile's core lies in its drawn image, and its size there.
fn core_in_tile(tile: Tile, k: u32) -> ImageWindow {
    ImageWindow {
        x0: tile.core.x0 * k - tile.drawn.x0,
        y0: tile.core.y0 * k - tile.drawn.y0,
        width: tile.core.width * k,
        height: tile.core.height * k,
    }
}

fn crop_image(image: &RgbaImage, tile: Tile, k: u32) -> RgbaImage {
    let core = core_in_tile(tile, k);
    image::imageops::crop_imm(image, core.x0, core.y0, core.width, core.height).to_image()
}

fn crop_depth(depth: &[f32], tile: Tile, k: u32) -> Vec<f32> {
    let core = core_in_tile(tile, k);
    let stride = tile.drawn.width as usize;
    (0..core.height as usize)
        .flat_map(|row| {
            let start = (core.y0 as usize + row) * stride + core.x0 as usize;
            depth[start..start + core.width as usize].iter().copied()
        })
        .collect()
}

/// Copies a core's pixels (and depths) into the frame at `at`.
fn paste(image: &mut RgbaImage, depth: Option<&mut [f32]>, core: &Frame, at: ImageWindow) {
    let frame_width = image.width() as usize;
    let (x0, width) = (at.x0 as usize, at.width as usize);
    let pixels: &mut [u8] = image;
    for (row, source) in core.image.chunks_exact(width * 4).enumerate() {
        let start = ((at.y0 as usize + row) * frame_width + x0) * 4;
        pixels[start..start + width * 4].copy_from_slice(source);
    }
    if let (Some(depth), Some(source)) = (depth, &core.depth) {
        for (row, source) in source.chunks_exact(width).enumerate() {
            let start = (at.y0 as usize + row) * frame_width + x0;
            depth[start..start + width].copy_from_slice(source);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::perspective_camera;

    #[test]
    fn every_adapter_with_the_default_binding_limit_renders_the_largest_image() {
        assert_eq!(largest_drawn_side(128 << 20), MAX_IMAGE_SIDE);
        assert_eq!(largest_drawn_side(16 << 20), MAX_IMAGE_SIDE);
        // Too small for the widest apron's one-pixel tile: only frames drawn whole.
        assert_eq!(largest_drawn_side(1 << 20), 256);
    }

    fn settings(width: u32, height: u32) -> FrameSettings {
        let camera =
            perspective_camera(DVec3::new(10.0, 0.0, 5.0), DVec3::ZERO, 50.0, (1.0, 100.0));
        FrameSettings::new(width, height, camera)
    }

    /// Every output pixel lies in exactly one core; every tile holds its core and the apron
    /// around it inside the frame, and fits the limit.
    fn assert_covers(settings: &FrameSettings, grid: &TileGrid, limit: u64) {
        let k = grid.scale;
        let drawn = settings.scaled_for_supersampling();
        let per_pixel = bytes_per_pixel(drawn.quality);
        assert!(u64::from(grid.tile_width) * u64::from(grid.tile_height) * per_pixel <= limit);
        let mut covered = vec![0u8; (settings.width * settings.height) as usize];
        for tile in grid.tiles() {
            let (core, t) = (tile.core, tile.drawn);
            assert!(
                t.x0 + t.width <= drawn.width && t.y0 + t.height <= drawn.height,
                "{tile:?}"
            );
            let reach = |start: u32, apron: u32| (start * k).saturating_sub(apron);
            assert!(t.x0 <= reach(core.x0, grid.apron) && t.y0 <= reach(core.y0, grid.apron));
            let end =
                |start: u32, size: u32, frame: u32| ((start + size) * k + grid.apron).min(frame);
            assert!(
                t.x0 + t.width >= end(core.x0, core.width, drawn.width),
                "{tile:?}"
            );
            assert!(
                t.y0 + t.height >= end(core.y0, core.height, drawn.height),
                "{tile:?}"
            );
            for y in core.y0..core.y0 + core.height {
                for x in core.x0..core.x0 + core.width {
                    covered[(y * settings.width + x) as usize] += 1;
                }
            }
        }
        assert!(covered.iter().all(|&c| c == 1));
    }

    #[test]
    fn a_frame_that_fits_is_not_tiled_and_one_that_does_not_is_covered_once() {
        let small = settings(64, 48);
        assert!(matches!(TileGrid::plan(&small, 64 * 48 * 8), Ok(None)));
        let cases = [
            (settings(300, 200), 40_000 * 8),
            (
                FrameSettings {
                    quality: Quality::HIGH,
                    shading: Shading::EDL,
                    point_size: 3,
                    ..settings(257, 131)
                },
                9_000 * 16,
            ),
            (
                FrameSettings {
                    fill: Some(FillSettings::default()),
                    shading: Shading::PINTUS,
                    supersample: 2,
                    ..settings(301, 99)
                },
                40_000 * 8,
            ),
            (settings(MAX_IMAGE_SIDE, MAX_IMAGE_SIDE), 128 << 20),
        ];
        for (settings, limit) in cases {
            let grid = TileGrid::plan(&settings, limit)
                .expect("tileable")
                .expect("too large for one pass");
            assert!(grid.columns() * grid.rows() > 1, "{grid:?}");
            assert_covers(&settings, &grid, limit);
        }
    }

    #[test]
    fn the_apron_holds_every_screen_pass_reach() {
        let plain = settings(100, 100);
        assert_eq!(apron(&plain), 1);
        let all = FrameSettings {
            point_size: 2,
            fill: Some(FillSettings { kernel: 7 }),
            shading: Shading::Pintus {
                levels: 8,
                exponent: 1.5,
            },
            ..plain
        };
        // 2 for the splat, 3 + 14 for visibility and filling, 8 for the shading's levels.
        assert_eq!(apron(&all), 2 + 17 + 8);
        let edl = FrameSettings {
            shading: Shading::Edl {
                strength: 1.0,
                radius: 1.4,
            },
            ..plain
        };
        assert_eq!(apron(&edl), 1 + 2);
    }

    #[test]
    fn a_limit_below_the_smallest_tile_is_refused() {
        let result = TileGrid::plan(&settings(1000, 1000), 8 * 8);
        assert!(
            matches!(result, Err(RenderError::ImageTooLarge { .. })),
            "{result:?}"
        );
    }
}

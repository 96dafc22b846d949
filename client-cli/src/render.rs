//! `pointfarm render`: one frame or a turntable of a LAS/LAZ file, rendered locally.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use glam::DVec3;
use indicatif::{ProgressBar, ProgressStyle};
use pointfarm_render::camera::{Camera, Projection, DEFAULT_FOV_Y_DEG};
use pointfarm_render::cloud::PointCloud;
use pointfarm_render::color::{point_colors, ColorMode};
use pointfarm_render::encode;
use pointfarm_render::gpu::{AdapterChoice, GpuContext};
use pointfarm_render::ingest::load_point_cloud;
use pointfarm_render::raster::{
    AtomicsMode, FillSettings, FrameSettings, Quality, Renderer, Shading, Stage, StageTimings,
};

use crate::parse;

#[derive(Args)]
pub struct RenderArgs {
    /// LAS or LAZ file to render.
    pub(crate) input: PathBuf,
    /// Render on this pointfarm server instead of here (uploading the file if needed).
    #[arg(long, env = "POINTFARM_SERVER")]
    pub(crate) server: Option<String>,
    /// Bearer token for the server.
    #[arg(long, env = "POINTFARM_TOKEN", hide_env_values = true)]
    pub(crate) token: Option<String>,
    /// Supersampling anti-aliasing: render at K times the size and average (1 = off).
    #[arg(long, default_value_t = 1, value_name = "K")]
    pub(crate) supersample: u32,
    /// Also write each frame's linear depth as a 16-bit PNG (0 = no point, 1..65535 from
    /// near to far): FRAME.depth.png, or depth_00000.png, ... with --turntable.
    #[arg(long)]
    pub(crate) depth: bool,
    /// With --turntable: also assemble the frames into this video (needs ffmpeg).
    #[arg(long, requires = "turntable")]
    pub(crate) video: Option<PathBuf>,
    /// Frames per second of --video.
    #[arg(long, default_value_t = 30)]
    pub(crate) fps: u32,
    /// Server jobs: higher runs first.
    #[arg(long, default_value_t = 0)]
    pub(crate) priority: i32,
    /// Output PNG file; with --turntable, a directory for frame_00000.png, frame_00001.png, ...
    #[arg(short, long)]
    pub(crate) out: PathBuf,
    /// Image size in pixels.
    #[arg(long, default_value = "1280x720", value_parser = parse::size)]
    pub(crate) size: (u32, u32),
    /// Render N frames orbiting the cloud (around the vertical axis through the target).
    #[arg(long, value_name = "N")]
    pub(crate) turntable: Option<usize>,
    /// Camera position in the file's coordinates (default: an oblique view of the whole cloud).
    #[arg(long, value_parser = parse::vec3, value_name = "X,Y,Z")]
    pub(crate) camera_pos: Option<DVec3>,
    /// Point the camera looks at, in the file's coordinates (default: the cloud's centre).
    #[arg(long, value_parser = parse::vec3, value_name = "X,Y,Z")]
    pub(crate) camera_target: Option<DVec3>,
    /// Camera up direction.
    #[arg(long, value_parser = parse::vec3, value_name = "X,Y,Z", default_value = "0,0,1")]
    pub(crate) camera_up: DVec3,
    /// Vertical field of view in degrees (perspective).
    #[arg(long, default_value_t = DEFAULT_FOV_Y_DEG, value_parser = parse::positive)]
    pub(crate) fov: f64,
    /// Orthographic projection; the view height fits the cloud unless --ortho-height is given.
    #[arg(long)]
    pub(crate) ortho: bool,
    /// Height of the orthographic view in the file's units.
    #[arg(long, value_parser = parse::positive, requires = "ortho")]
    pub(crate) ortho_height: Option<f64>,
    /// Near clipping distance (default: fitted to the cloud).
    #[arg(long, value_parser = parse::positive)]
    pub(crate) near: Option<f64>,
    /// Far clipping distance (default: fitted to the cloud).
    #[arg(long, value_parser = parse::positive)]
    pub(crate) far: Option<f64>,
    /// Side of the square drawn for each point, in pixels.
    #[arg(long, default_value_t = 1)]
    pub(crate) point_size: u32,
    /// Background colour: #rrggbb, #rrggbbaa or transparent.
    #[arg(long, default_value = "#18181c", value_parser = parse::color)]
    pub(crate) background: [u8; 4],
    /// Colour points by: rgb (the file's colours, or intensity without them), intensity,
    /// elevation, classification, return, or one colour like #ff8000.
    #[arg(long = "color", visible_alias = "colour", default_value = "rgb", value_parser = parse::color_mode)]
    pub(crate) color: ColorMode,
    /// basic: the nearest point's colour; high: the average colour of the points near the
    /// front surface (less aliasing, smoother turntables; about two passes more).
    #[arg(long, value_enum, default_value = "basic")]
    pub(crate) quality: QualityArg,
    /// High quality: points up to this fraction behind the nearest depth are averaged.
    #[arg(long, default_value_t = 0.01)]
    pub(crate) depth_band: f32,
    /// Close the holes between points (Pintus et al.): points seen through gaps of a nearer
    /// surface are removed, then holes take the depth and colour of the surface around them.
    /// Silhouettes stay sharp.
    #[arg(long)]
    pub(crate) fill: bool,
    /// Filling: visibility kernel side in pixels, odd, 3 to 9 (implies --fill). Holes up to
    /// about a third of it close; raise it for sparse scans.
    #[arg(long, value_name = "N")]
    pub(crate) fill_kernel: Option<u32>,
    /// Screen-space shading: edl (Eye-Dome Lighting, shapes read without colour or normals),
    /// pintus (Pintus et al.'s shape depiction: directional light, ambient occlusion and
    /// lines from depth alone; best with --fill) or none.
    #[arg(long, value_enum, default_value = "none")]
    pub(crate) shading: ShadingArg,
    /// Pintus shading: number of smoothing levels (1 to 32); more adds broader, softer
    /// ambient shading.
    #[arg(long, default_value_t = Shading::DEFAULT_PINTUS_LEVELS)]
    pub(crate) pintus_levels: u32,
    /// Pintus shading: level k weighs 1 / (k + 1)^exponent (0 to 4); higher is sharper.
    #[arg(long, default_value_t = Shading::DEFAULT_PINTUS_EXPONENT)]
    pub(crate) pintus_exponent: f32,
    /// Eye-Dome Lighting: how strongly depth steps darken.
    #[arg(long, default_value_t = Shading::DEFAULT_EDL_STRENGTH)]
    pub(crate) edl_strength: f32,
    /// Eye-Dome Lighting: distance of the depth samples in pixels.
    #[arg(long, default_value_t = Shading::DEFAULT_EDL_RADIUS)]
    pub(crate) edl_radius: f32,
    /// Adapter: auto (hardware GPU if present, else lavapipe), hardware or software.
    #[arg(long, env = "POINTFARM_ADAPTER", default_value = "auto")]
    pub(crate) adapter: AdapterChoice,
    /// Atomics of the point pass: auto (64-bit where available) or 32 (the fallback path).
    #[arg(long, value_enum, default_value = "auto")]
    atomics: AtomicsArg,
}

#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum ShadingArg {
    None,
    Edl,
    Pintus,
}

impl RenderArgs {
    /// Filling as asked for: --fill, or --fill-kernel alone.
    pub(crate) fn fill_settings(&self) -> Option<FillSettings> {
        (self.fill || self.fill_kernel.is_some()).then(|| FillSettings {
            kernel: self.fill_kernel.unwrap_or(FillSettings::DEFAULT_KERNEL),
        })
    }
}

#[derive(Clone, Copy, ValueEnum)]
pub(crate) enum QualityArg {
    Basic,
    High,
}

#[derive(Clone, Copy, ValueEnum)]
enum AtomicsArg {
    Auto,
    #[value(name = "32")]
    Force32,
}

pub fn run(args: RenderArgs) -> Result<()> {
    let (width, height) = args.size;
    if args.turntable == Some(0) {
        bail!("--turntable needs at least one frame");
    }
    if let Some(server) = args.server.clone() {
        return crate::remote_render::run(&server, &args);
    }

    let started = Instant::now();
    let spinner = spinner(format!("reading {}", args.input.display()));
    let cloud = load_point_cloud(&args.input);
    spinner.finish_and_clear();
    let mut cloud = cloud?;
    cloud.colors = point_colors(&cloud, args.color);
    println!(
        "{}: {} points, colour from {:?}, read in {:.0} ms",
        args.input.display(),
        cloud.len(),
        cloud.color_source,
        started.elapsed().as_secs_f64() * 1e3
    );

    let gpu = Arc::new(GpuContext::new(args.adapter)?);
    println!("adapter: {}", gpu.describe());
    let mut renderer = Renderer::new(gpu);
    let base = FrameSettings {
        point_size: args.point_size,
        background: args.background,
        atomics: match args.atomics {
            AtomicsArg::Auto => AtomicsMode::Auto,
            AtomicsArg::Force32 => AtomicsMode::Force32,
        },
        quality: match args.quality {
            QualityArg::Basic => Quality::Basic,
            QualityArg::High => Quality::High {
                depth_band: args.depth_band,
            },
        },
        supersample: args.supersample,
        read_depth: args.depth,
        fill: args.fill_settings(),
        shading: match args.shading {
            ShadingArg::None => Shading::None,
            ShadingArg::Edl => Shading::Edl {
                strength: args.edl_strength,
                radius: args.edl_radius,
            },
            ShadingArg::Pintus => Shading::Pintus {
                levels: args.pintus_levels,
                exponent: args.pintus_exponent,
            },
        },
        ..FrameSettings::new(width, height, base_camera(&args, &cloud))
    };
    // Refuse bad sizes or cameras before the upload, with the reason.
    renderer.validate(&base)?;
    let resident = renderer.upload(&cloud)?;

    match args.turntable {
        None => {
            if args.out.is_dir() {
                bail!(
                    "{} is a directory; give a .png file (or use --turntable N)",
                    args.out.display()
                );
            }
            let mut frame = renderer.render(&resident, &base)?;
            encode::save_png(&mut frame, &args.out)
                .with_context(|| format!("writing {}", args.out.display()))?;
            if args.depth {
                save_depth(&frame, &args.out.with_extension("depth.png"), &base)?;
            }
            println!("{}  {}", args.out.display(), frame.timings);
        }
        Some(frames) => {
            std::fs::create_dir_all(&args.out)
                .with_context(|| format!("creating {}", args.out.display()))?;
            let progress = ProgressBar::new(frames as u64).with_style(
                ProgressStyle::with_template("{bar:40} {pos}/{len} frames, {eta} left")
                    .unwrap_or_else(|_| ProgressStyle::default_bar()),
            );
            let mut all = Vec::with_capacity(frames);
            for i in 0..frames {
                let camera = base.camera.orbit(360.0 * i as f64 / frames as f64);
                let mut frame = renderer.render(&resident, &FrameSettings { camera, ..base })?;
                let path = args.out.join(format!("frame_{i:05}.png"));
                encode::save_png(&mut frame, &path)
                    .with_context(|| format!("writing {}", path.display()))?;
                if args.depth {
                    save_depth(&frame, &args.out.join(format!("depth_{i:05}.png")), &base)?;
                }
                let line = format!("{}  {}", path.display(), frame.timings);
                if progress.is_hidden() {
                    println!("{line}"); // not a terminal: plain lines for logs and scripts
                } else {
                    progress.println(line);
                }
                all.push(frame.timings);
                progress.inc(1);
            }
            progress.finish_and_clear();
            print_summary(&args.out, &all);
            if let Some(video) = &args.video {
                crate::video::assemble(&args.out, video, args.fps)?;
            }
        }
    }
    Ok(())
}

/// The camera of the first frame: the user's position/target where given, the automatic
/// framing elsewhere.
fn base_camera(args: &RenderArgs, cloud: &PointCloud) -> Camera {
    let bounds = &cloud.bounds;
    let aspect = args.size.0 as f64 / args.size.1.max(1) as f64;
    let projection = if args.ortho {
        // `framing` fits the view height to the cloud.
        Projection::Orthographic { height: 1.0 }
    } else {
        Projection::Perspective {
            fov_y_deg: args.fov,
        }
    };
    let auto = Camera::framing(
        bounds,
        aspect,
        pointfarm_render::camera::AUTO_AZIMUTH_DEG,
        pointfarm_render::camera::AUTO_ELEVATION_DEG,
        projection,
    );
    let target = args.camera_target.unwrap_or(auto.target);
    let position = args
        .camera_pos
        .unwrap_or(target + (auto.position - auto.target));
    let mut camera = Camera::looking_at(position, target, bounds, auto.projection);
    camera.up = args.camera_up;
    if let Some(height) = args.ortho_height {
        camera.projection = Projection::Orthographic { height };
    }
    if let Some(near) = args.near {
        camera.near = near;
    }
    if let Some(far) = args.far {
        camera.far = far;
    }
    camera
}

fn save_depth(
    frame: &pointfarm_render::raster::Frame,
    path: &Path,
    settings: &FrameSettings,
) -> Result<()> {
    encode::save_depth_png16(frame, path, settings.camera.near, settings.camera.far)
        .with_context(|| format!("writing {}", path.display()))
}

fn print_summary(dir: &Path, frames: &[StageTimings]) {
    println!(
        "{} frames in {}; median per stage:",
        frames.len(),
        dir.display()
    );
    for stage in [
        Stage::Upload,
        Stage::Cull,
        Stage::Rasterize,
        Stage::Resolve,
        Stage::Shade,
        Stage::Downsample,
        Stage::Readback,
        Stage::Encode,
    ] {
        let mut ms: Vec<f64> = frames.iter().filter_map(|t| t.get(stage)).collect();
        if ms.is_empty() {
            continue;
        }
        ms.sort_by(f64::total_cmp);
        println!("  {:<10} {:>9.2} ms", stage.name(), ms[ms.len() / 2]);
    }
}

fn spinner(message: String) -> ProgressBar {
    let spinner = ProgressBar::new_spinner().with_message(message);
    spinner.enable_steady_tick(std::time::Duration::from_millis(100));
    spinner
}

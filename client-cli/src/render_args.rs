//! The arguments of `pointfarm render` and the one [`RenderRequest`] they describe, which
//! local rendering (`render`) and server rendering (`remote_render`) both start from. Every
//! default comes from the render crate's constants.

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::{Args, ValueEnum};
use glam::DVec3;
use pointfarm_render::camera::{AUTO_AZIMUTH_DEG, AUTO_ELEVATION_DEG, DEFAULT_FOV_Y_DEG};
use pointfarm_render::color::{ColorMode, ColorRamp, ColorRange};
use pointfarm_render::cut::CutOptions;
use pointfarm_render::encode::video::{
    VideoCodec, VideoPreset, DEFAULT_VIDEO_FPS, DEFAULT_VIDEO_PRESET, DEFAULT_VIDEO_QUALITY,
};
use pointfarm_render::gpu::AdapterChoice;
use pointfarm_render::raster::{
    AtomicsMode, FillSettings, Quality, Shading, DEFAULT_BACKGROUND, DEFAULT_DEPTH_BAND,
};
use pointfarm_render::request::{
    CameraPath, Lens, Point3, PointSize, RenderOptions, RenderRequest, StillCamera, Turntable,
    DEFAULT_SUPERSAMPLE, DEFAULT_UP, TURNTABLE_ELEVATION_RANGE,
};
use pointfarm_render::source::BuildUnseen;

use crate::credentials::ClientCredentials;
use crate::filter_args::FilterArgs;
use crate::parse::{self, codec_parser, Rgba};

#[derive(Args)]
pub struct RenderArgs {
    /// LAS/LAZ files or folders of them, rendered as one dataset (tiles or scan positions of
    /// one campaign: one origin, bounds and color decision); or one URL (https://, s3://, gs://,
    /// az://), read by range: a COPC file, or LAS/LAZ tiles (a file, or a prefix of them),
    /// streamed once into a store here (previewed by range first with --preview).
    #[arg(required_unless_present = "dataset", value_name = "INPUT")]
    pub(crate) inputs: Vec<PathBuf>,
    /// Render on this pointfarm server instead of here (uploading the files it lacks).
    #[arg(long, env = "POINTFARM_SERVER")]
    pub(crate) server: Option<String>,
    /// Render a dataset the server already has, by its id (`dataset register` or `dataset
    /// add` print it), instead of files: nothing is read or sent from here.
    #[arg(long, value_name = "ID", conflicts_with_all = ["inputs", "local"])]
    pub(crate) dataset: Option<String>,
    /// Render here, whatever --server or POINTFARM_SERVER say.
    #[arg(long)]
    pub(crate) local: bool,
    #[command(flatten)]
    pub(crate) credentials: ClientCredentials,
    /// Supersampling anti-aliasing: render at K times the size and average (1 = off).
    #[arg(long, default_value_t = DEFAULT_SUPERSAMPLE, value_name = "K")]
    supersample: u32,
    /// Also write each frame's linear depth as a 16-bit PNG (0 = no point, 1..65535 from
    /// near to far) beside it, FRAME.depth.png, with FRAME.depth.json giving near, far and
    /// the camera to turn it back into distances. Local only.
    #[arg(long)]
    depth: bool,
    /// With --turntable or --camera-path: also assemble this render's frames into a video
    /// (.mp4, .mov, .mkv, .webm, or .gif for quick looks). Needs ffmpeg, which is checked
    /// before rendering.
    #[arg(long, value_name = "FILE")]
    pub(crate) video: Option<PathBuf>,
    /// Frames per second of --video, and of a Potree camera animation's frames.
    #[arg(long, default_value_t = DEFAULT_VIDEO_FPS)]
    pub(crate) fps: u32,
    /// Codec of --video [default: h264, vp9 for .webm].
    #[arg(long, value_parser = codec_parser(), requires = "video")]
    pub(crate) video_codec: Option<VideoCodec>,
    /// Constant quality of --video, 0 (best, largest) to 51; about 18 looks lossless.
    #[arg(long, default_value_t = DEFAULT_VIDEO_QUALITY, value_name = "CRF", requires = "video")]
    pub(crate) video_quality: u32,
    /// x264/x265 preset of --video: a faster one makes a larger video sooner (ignored by VP9,
    /// AV1 and GIF).
    #[arg(long, default_value_t = DEFAULT_VIDEO_PRESET, value_name = "PRESET", requires = "video")]
    pub(crate) video_preset: VideoPreset,
    /// Print one JSON object per frame on standard output, and nothing else there: its file,
    /// size, the points of the dataset and those the point passes read, its stage timings;
    /// through a server, its file and the frame as the API reports it.
    #[arg(long)]
    pub(crate) json: bool,
    /// Server jobs: -100 to 100, higher runs first (`pointfarm jobs priority` changes it).
    #[arg(long, default_value_t = 0, allow_negative_numbers = true, value_parser = crate::admin::parse_priority)]
    pub(crate) priority: i32,
    /// Server jobs: what the job is called in listings (at most 128 characters).
    #[arg(long, value_name = "NAME")]
    pub(crate) name: Option<String>,
    /// Server jobs: a label to find the job by (`jobs ls --label`): KEY=VALUE, keys of
    /// a-z0-9_.- (repeatable, at most 32).
    #[arg(long = "label", value_name = "KEY=VALUE", value_parser = crate::admin::parse_label)]
    pub(crate) labels: Vec<(String, String)>,
    /// Server jobs: lease the frames only to workers with this tag (`worker --tag`;
    /// repeatable, all required).
    #[arg(long = "require-tag", value_name = "TAG")]
    pub(crate) require_tags: Vec<String>,
    /// Server jobs: lease the frames only to workers on a hardware GPU, never a software
    /// rasterizer.
    #[arg(long)]
    pub(crate) require_gpu: bool,
    /// Server jobs: lease no frame of this job until the job JOB has succeeded (repeatable,
    /// each must); if one fails or is cancelled, this job fails, naming it.
    #[arg(long = "after", value_name = "JOB")]
    pub(crate) after: Vec<String>,
    /// Server jobs: also write each final frame (and the video) under this object-storage
    /// prefix, as PREFIX/frame_NNNNN.png, by the server, which must allow it
    /// (`serve --allow-output-prefix`).
    #[arg(long, value_name = "s3://BUCKET/PREFIX", requires = "server")]
    pub(crate) output_url: Option<String>,
    /// Server jobs: submit, print the job's id on standard output (with --json, the job as a
    /// JSON line) and return at once, without following the job or fetching its frames
    /// (`pointfarm jobs watch ID` follows it, `pointfarm frames fetch ID` fetches them).
    #[arg(long, conflicts_with = "video")]
    pub(crate) detach: bool,
    /// Output image, in the format its extension names: .png, .jpg, .webp or .tif, 8 bits a
    /// channel (--depth writes each frame's depth as a 16-bit PNG beside it).
    /// With --turntable: a folder for frame_00000.png, frame_00001.png, ..., or a pattern
    /// such as frames/orbit_{:04}.jpg ({} for unpadded numbers).
    #[arg(short, long, value_name = "FILE|FOLDER|PATTERN")]
    pub(crate) out: PathBuf,
    /// Image size in pixels.
    #[arg(long, default_value = "1280x720", value_parser = parse::size)]
    size: (u32, u32),
    /// Render N frames orbiting the cloud (around the vertical axis through the target).
    #[arg(long, value_name = "N")]
    pub(crate) turntable: Option<u32>,
    /// Render the frames of a keyframed camera path written as JSON or TOML: `frames`,
    /// `interpolation` (spline or linear) and `keyframes`, each a `position` and `target` in
    /// the file's coordinates, optionally `up` and `fov_y_deg`. Or a Potree project
    /// (potree.json5): its first camera animation, its duration at --fps.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["turntable", "camera_pos", "camera_target", "camera_up", "view"])]
    camera_path: Option<PathBuf>,
    /// Camera position in the file's coordinates (default: the --view, framing the whole
    /// cloud). Each render prints the camera it chose as flags to start from.
    #[arg(long, value_parser = parse::vec3, value_name = "X,Y,Z", conflicts_with = "view")]
    camera_pos: Option<DVec3>,
    /// The automatic view's direction: oblique (from the south-south-east, 30 degrees up),
    /// top (from above, north up), front (from the south), side (from the east) or iso
    /// (isometric, from the south-east). A still frames the cloud tightly and centred; a
    /// turntable orbits its centre (from 89 degrees up at most).
    #[arg(long, value_enum, default_value = "oblique")]
    view: ViewArg,
    /// Point the camera looks at, in the file's coordinates (default: the cloud's centre).
    #[arg(long, value_parser = parse::vec3, value_name = "X,Y,Z")]
    camera_target: Option<DVec3>,
    /// Camera up direction [default: 0,0,1].
    #[arg(long, value_parser = parse::vec3, value_name = "X,Y,Z")]
    camera_up: Option<DVec3>,
    /// Vertical field of view in degrees (perspective).
    #[arg(long, default_value_t = DEFAULT_FOV_Y_DEG, value_parser = parse::positive)]
    fov: f64,
    /// Orthographic projection; the view height fits the cloud unless --ortho-height is given.
    #[arg(long)]
    ortho: bool,
    /// Height of the orthographic view in the file's units.
    #[arg(long, value_parser = parse::positive, requires = "ortho")]
    ortho_height: Option<f64>,
    /// Near clipping distance (default: fitted to the cloud).
    #[arg(long, value_parser = parse::positive)]
    near: Option<f64>,
    /// Far clipping distance (default: fitted to the cloud).
    #[arg(long, value_parser = parse::positive)]
    far: Option<f64>,
    /// Side of the square drawn for each point, in pixels, or auto: the cloud's point spacing
    /// as it projects at each point's depth (1 to 8 pixels), so surfaces read closed.
    #[arg(long, default_value = "auto", value_parser = parse::point_size)]
    point_size: PointSize,
    /// Draw each point as the disc its square bounds (from 4 pixels on).
    #[arg(long)]
    round_points: bool,
    /// Background color: #rrggbb, #rrggbbaa or transparent.
    #[arg(long, default_value_t = Rgba(DEFAULT_BACKGROUND), value_parser = parse::rgba)]
    background: Rgba,
    /// Color points by: rgb (the file's colors, or intensity without them), intensity,
    /// elevation, classification, return, or one color like #ff8000.
    #[arg(long = "color", visible_alias = "colour", default_value = "rgb", value_parser = parse::color_mode)]
    color: ColorMode,
    /// Elevation and intensity: color over this fixed range instead of the robust one of the
    /// data drawn, so tiles and frames rendered apart match: world Z in the file's units, or
    /// raw intensity, e.g. --range -12.5..340.
    #[arg(long, value_name = "MIN..MAX", value_parser = parse::color_range, allow_hyphen_values = true)]
    range: Option<ColorRange>,
    /// Elevation and intensity: the color ramp, viridis, inferno, turbo or grey [default:
    /// viridis for elevation, grey for intensity].
    #[arg(long, value_name = "RAMP", value_parser = parse::color_ramp)]
    ramp: Option<ColorRamp>,
    /// Also write the legend of the colors as a PNG: the ramp with its range's numbers
    /// (elevation, intensity), or the swatches and names of the classes or returns.
    #[arg(long, value_name = "FILE.png")]
    pub(crate) legend: Option<PathBuf>,
    /// basic: the nearest point's color; high: the average color of the points near the
    /// front surface (less aliasing, smoother turntables; about two passes more).
    #[arg(long, value_enum, default_value = "basic")]
    quality: QualityArg,
    /// High quality: points up to this fraction behind the nearest depth are averaged.
    #[arg(long, default_value_t = DEFAULT_DEPTH_BAND)]
    depth_band: f32,
    /// Close the holes between points (Pintus et al.): points seen through gaps of a nearer
    /// surface are removed, then holes take the depth and color of the surface around them.
    /// Silhouettes stay sharp.
    #[arg(long)]
    fill: bool,
    /// Filling: visibility kernel side in pixels, odd, 3 to 9 (implies --fill). Holes up to
    /// about a third of it close; raise it for sparse scans.
    #[arg(long, value_name = "N")]
    fill_kernel: Option<u32>,
    /// Screen-space shading: edl (Eye-Dome Lighting, shapes read without color or normals),
    /// pintus (Pintus et al.'s shape depiction: directional light, ambient occlusion and
    /// lines from depth alone; best with --fill) or none.
    #[arg(long, value_enum, default_value_t = ShadingArg::of(RenderOptions::default().shading))]
    shading: ShadingArg,
    /// Pintus shading: number of smoothing levels (1 to 32); more adds broader, softer
    /// ambient shading.
    #[arg(long, default_value_t = Shading::DEFAULT_PINTUS_LEVELS)]
    pintus_levels: u32,
    /// Pintus shading: level k weighs 1 / (k + 1)^exponent (0 to 4); higher is sharper.
    #[arg(long, default_value_t = Shading::DEFAULT_PINTUS_EXPONENT)]
    pintus_exponent: f32,
    /// Eye-Dome Lighting: how strongly depth steps darken.
    #[arg(long, default_value_t = Shading::DEFAULT_EDL_STRENGTH)]
    edl_strength: f32,
    /// Eye-Dome Lighting: distance of the depth samples in pixels.
    #[arg(long, default_value_t = Shading::DEFAULT_EDL_RADIUS)]
    edl_radius: f32,
    /// Adapter: auto (hardware GPU if present, else lavapipe), hardware or software. With
    /// --server the server's workers choose theirs.
    #[arg(long, env = "POINTFARM_ADAPTER", default_value = "auto")]
    pub(crate) adapter: AdapterChoice,
    /// Atomics of the point pass: auto (64-bit where available) or 32 (the fallback path).
    /// Local only.
    #[arg(long, value_enum, default_value = "auto")]
    atomics: AtomicsArg,
    /// Render from levels of detail: a node is refined while its point spacing covers more
    /// than PX pixels on screen, up to 32 points a pixel of the image (0: every point).
    /// Datasets of more than 20M points use them anyway, at 0.25 pixels. The store is built once and kept in --cache-dir (through a
    /// server, by the server, whose workers read the nodes they need from it). A single COPC
    /// file is always rendered this way, from its own hierarchy, without a store.
    #[arg(long, value_name = "PX", value_parser = parse::non_negative)]
    lod_error: Option<f64>,
    /// When the dataset's levels of detail must be built first, render every frame at once
    /// from a preview (the raw first point of each LAZ chunk, every 50,000th LAS record, read
    /// without decompressing) while the store builds on another thread, then render the
    /// final frames over them, into the same files (previews stop once the store is ready;
    /// the first frame is always previewed). Reports say which frames are previews and how
    /// complete their data was. A single COPC file, which needs no build, is previewed from
    /// coarse cuts of its own hierarchy, then its final frames are drawn with the nodes the
    /// previews read. With nothing else to build the final frames render at once. Through
    /// --server the job asks for previews: while the server builds the store, its workers
    /// render every frame from the server's chunk-start sample (of a COPC dataset, from its
    /// coarse cuts) and report them as previews with their completeness; the same job then
    /// renders each frame again as a final frame and succeeds only when all are final, which
    /// are the frames downloaded.
    #[arg(long)]
    pub(crate) preview: bool,
    /// When a keyframed camera path sees part of a dataset of many files whose store must be
    /// built first, the store is built camera first: from the files the first frame sees, then
    /// the rest of the path's, each frame drawn as soon as its files are in (from their header
    /// boxes, the frames' view frusta and point sizes). The files no frame sees are added to
    /// the store after the frames (after), or never (never: the store holds the path's files
    /// alone until a later render adds the rest). Through --server the job asks the same of
    /// the server: after, it grows the dataset's whole store from the store of the files the
    /// frames see; never, it builds that store alone for this job (a job that needs the
    /// whole store still gets it built), and `jobs show` says so.
    #[arg(long, value_name = "after|never", default_value = BuildUnseen::default().name(),
          value_parser = BuildUnseen::parse)]
    pub(crate) build_unseen: BuildUnseen,
    /// Levels of detail: host memory for the node cache and the store's build, e.g. 512MiB
    /// or 4GiB; on a software adapter (lavapipe) the GPU node cache's share too. Local only.
    #[arg(long, value_name = "SIZE", value_parser = parse::bytes)]
    memory_budget: Option<u64>,
    /// Levels of detail: GPU memory for the node cache (default 2GiB; on a software adapter
    /// half of --memory-budget). Local only.
    #[arg(long, value_name = "SIZE", value_parser = parse::bytes)]
    gpu_budget: Option<u64>,
    /// Where level-of-detail stores are kept between renders (default
    /// $XDG_CACHE_HOME/pointfarm or ~/.cache/pointfarm).
    #[arg(long, env = "POINTFARM_CACHE_DIR", value_name = "DIR")]
    pub(crate) cache_dir: Option<PathBuf>,
    /// The most disk the stores in --cache-dir may take together, e.g. 200GiB: before a
    /// build, the least recently used stores not in use are removed until it fits, and a
    /// dataset whose store alone needs more is refused (default: only the free disk bounds
    /// them).
    #[arg(long, env = "POINTFARM_CACHE_SIZE", value_name = "SIZE", value_parser = parse::bytes)]
    pub(crate) cache_size: Option<u64>,
    #[command(flatten, next_help_heading = "Filters")]
    filter: FilterArgs,
}

#[derive(Clone, Copy, ValueEnum)]
enum ViewArg {
    Oblique,
    Top,
    Front,
    Side,
    Iso,
}

impl ViewArg {
    /// Azimuth (degrees counter-clockwise from +X, where the camera is) and elevation.
    fn direction(self) -> (f64, f64) {
        match self {
            Self::Oblique => (AUTO_AZIMUTH_DEG, AUTO_ELEVATION_DEG),
            Self::Top => (-90.0, 90.0),
            Self::Front => (-90.0, 0.0),
            Self::Side => (0.0, 0.0),
            // The isometric elevation: atan(1 / sqrt(2)).
            Self::Iso => (-45.0, 35.264_389_682_754_654),
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum ShadingArg {
    None,
    Edl,
    Pintus,
}

impl ShadingArg {
    /// The flag's value for `shading`'s kind (its parameters have flags of their own).
    fn of(shading: Shading) -> Self {
        match shading {
            Shading::None => ShadingArg::None,
            Shading::Edl { .. } => ShadingArg::Edl,
            Shading::Pintus { .. } => ShadingArg::Pintus,
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum QualityArg {
    Basic,
    High,
}

#[derive(Clone, Copy, ValueEnum)]
enum AtomicsArg {
    Auto,
    #[value(name = "32")]
    Force32,
}

impl RenderArgs {
    /// The request these arguments describe, validated.
    /// What the inputs are called in messages: the one file or folder, or how many.
    pub(crate) fn inputs_label(&self) -> String {
        match (&self.dataset, self.inputs.as_slice()) {
            (Some(id), _) => format!("dataset {id}"),
            (None, [one]) => one.display().to_string(),
            (None, many) => format!("{} inputs", many.len()),
        }
    }

    pub(crate) fn request(&self) -> Result<RenderRequest> {
        if self.turntable == Some(0) {
            bail!("--turntable needs at least one frame");
        }
        let point = |v: Option<DVec3>| v.map(Point3::from);
        let up = self.camera_up.map_or(DEFAULT_UP, Point3::from);
        let (azimuth_deg, elevation_deg) = self.view.direction();
        let camera_path = match (&self.camera_path, self.turntable) {
            (Some(file), _) => crate::camera_path::read(file, self.fps)?,
            (None, None) => CameraPath::Still(StillCamera {
                position: point(self.camera_pos),
                target: point(self.camera_target),
                up,
                fov_y_deg: self.fov,
                azimuth_deg,
                elevation_deg,
            }),
            (None, Some(frames)) => CameraPath::Turntable(Turntable {
                center: point(self.camera_target),
                start: point(self.camera_pos),
                fov_y_deg: self.fov,
                up,
                azimuth_deg,
                elevation_deg: elevation_deg.clamp(
                    *TURNTABLE_ELEVATION_RANGE.start(),
                    *TURNTABLE_ELEVATION_RANGE.end(),
                ),
                ..Turntable::around_the_cloud(frames)
            }),
        };
        let request = RenderRequest {
            width: self.size.0,
            height: self.size.1,
            camera_path,
            lens: Lens {
                orthographic: self.ortho,
                ortho_height: self.ortho_height,
                near: self.near,
                far: self.far,
            },
            render: RenderOptions {
                point_size: self.point_size,
                round_points: self.round_points,
                quality: match self.quality {
                    QualityArg::Basic => Quality::Basic,
                    QualityArg::High => Quality::High {
                        depth_band: self.depth_band,
                    },
                },
                shading: match self.shading {
                    ShadingArg::None => Shading::None,
                    ShadingArg::Edl => Shading::Edl {
                        strength: self.edl_strength,
                        radius: self.edl_radius,
                    },
                    ShadingArg::Pintus => Shading::Pintus {
                        levels: self.pintus_levels,
                        exponent: self.pintus_exponent,
                    },
                },
                color_mode: self.color,
                color_range: self.range,
                color_ramp: self.ramp,
                background: self.background.0,
                // --fill, or --fill-kernel alone.
                fill: (self.fill || self.fill_kernel.is_some()).then(|| FillSettings {
                    kernel: self.fill_kernel.unwrap_or(FillSettings::DEFAULT_KERNEL),
                }),
                supersample: self.supersample,
                depth: self.depth,
                lod_error: self.lod_error,
                filter: self.filter.filter(),
            },
        };
        request.validate()?;
        Ok(request)
    }

    /// Whether the render writes a sequence of frames (a turntable or a camera path), not one.
    pub(crate) fn is_sequence(&self) -> bool {
        self.turntable.is_some() || self.camera_path.is_some()
    }

    /// The first option of this machine's node caches given, to name it where it does not
    /// apply.
    pub(crate) fn cache_flag(&self) -> Option<&'static str> {
        [
            ("--memory-budget", self.memory_budget.is_some()),
            ("--gpu-budget", self.gpu_budget.is_some()),
        ]
        .into_iter()
        .find_map(|(flag, given)| given.then_some(flag))
    }

    /// Whether the arguments ask for levels of detail: a pixel error, or this machine's node
    /// caches' budgets, which only a cut has.
    pub(crate) fn levels_of_detail_asked(&self) -> bool {
        self.lod_error.is_some() || self.cache_flag().is_some()
    }

    /// The cut options the arguments describe, for a dataset whose frames are cuts
    /// ([`pointfarm_render::cut::frame_points`]).
    pub(crate) fn lod_options(&self) -> Result<CutOptions> {
        let defaults = CutOptions::default();
        let options = CutOptions {
            lod_error: self.lod_error.unwrap_or(defaults.lod_error),
            memory_budget_bytes: self.memory_budget.unwrap_or(defaults.memory_budget_bytes),
            gpu_budget_bytes: self.gpu_budget,
        };
        options.validate()?;
        Ok(options)
    }

    /// The atomics of the local point pass (a property of this machine's adapter, not of
    /// the request).
    pub(crate) fn atomics(&self) -> AtomicsMode {
        match self.atomics {
            AtomicsArg::Auto => AtomicsMode::Auto,
            AtomicsArg::Force32 => AtomicsMode::Force32,
        }
    }
}

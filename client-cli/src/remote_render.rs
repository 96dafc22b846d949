//! `pointfarm render --server URL`: the local render's options, carried out by a daemon.
//! Uploads the file if the server lacks it, submits, follows with a progress bar and
//! downloads the frames.

use anyhow::{bail, Context, Result};
use pointfarm_proto::v1 as pb;
use pointfarm_render::color::ColorMode;

use crate::remote::{require_success, timings_line, Client};
use crate::render::{QualityArg, RenderArgs, ShadingArg};

fn vec3(v: glam::DVec3) -> pb::Vec3 {
    pb::Vec3 {
        x: v.x,
        y: v.y,
        z: v.z,
    }
}

fn color(rgba: [u8; 4]) -> pb::Color {
    pb::Color {
        rgba: u32::from_be_bytes(rgba),
    }
}

/// The job a set of render options describes.
fn submission(args: &RenderArgs, dataset_id: String) -> Result<pb::SubmitJobRequest> {
    if args.ortho || args.near.is_some() || args.far.is_some() {
        bail!("--ortho, --near and --far are not available through a server yet; render locally");
    }
    let frames = args.turntable.unwrap_or(1) as u32;
    let path = match (args.camera_pos, args.turntable) {
        // A fixed camera: one keyframe, held.
        (Some(position), None) => {
            let target = args
                .camera_target
                .context("--camera-pos needs --camera-target with --server")?;
            let key = pb::Keyframe {
                position: Some(vec3(position)),
                target: Some(vec3(target)),
                up: Some(vec3(args.camera_up)),
                fov_y_deg: args.fov,
            };
            pb::camera_path::Path::Keyframes(pb::KeyframePath {
                keyframes: vec![key, key],
                frames: 1,
                interpolation: pb::Interpolation::Linear as i32,
            })
        }
        // An orbit through the given position around the target.
        (Some(position), Some(_)) => {
            let target = args
                .camera_target
                .context("--camera-pos needs --camera-target with --server")?;
            let offset = position - target;
            let radius = offset.length();
            pb::camera_path::Path::Turntable(pb::Turntable {
                frames,
                center: Some(vec3(target)),
                radius: Some(radius),
                elevation_deg: Some(
                    (offset.z / radius.max(f64::MIN_POSITIVE))
                        .asin()
                        .to_degrees(),
                ),
                degrees: None,
                fov_y_deg: Some(args.fov),
            })
        }
        (None, _) => pb::camera_path::Path::Turntable(pb::Turntable {
            frames,
            center: args.camera_target.map(vec3),
            fov_y_deg: Some(args.fov),
            ..Default::default()
        }),
    };
    let (color_mode, fixed_color) = match args.color {
        ColorMode::Rgb => (pb::ColorMode::Rgb, None),
        ColorMode::Intensity => (pb::ColorMode::Intensity, None),
        ColorMode::Elevation => (pb::ColorMode::Elevation, None),
        ColorMode::Classification => (pb::ColorMode::Classification, None),
        ColorMode::ReturnNumber => (pb::ColorMode::ReturnNumber, None),
        ColorMode::Fixed([r, g, b]) => (pb::ColorMode::Fixed, Some(color([r, g, b, 255]))),
    };
    let render = pb::RenderOptions {
        point_size: args.point_size,
        quality: match args.quality {
            QualityArg::Basic => pb::Quality::Basic,
            QualityArg::High => pb::Quality::High,
        } as i32,
        depth_band: Some(args.depth_band),
        shading: match args.shading {
            ShadingArg::None => pb::Shading::None,
            ShadingArg::Edl => pb::Shading::Edl,
            ShadingArg::Pintus => pb::Shading::Pintus,
        } as i32,
        fill: args
            .fill_settings()
            .map(|f| pb::FillOptions { kernel: f.kernel }),
        pintus_levels: Some(args.pintus_levels),
        pintus_exponent: Some(args.pintus_exponent),
        edl_strength: Some(args.edl_strength),
        edl_radius: Some(args.edl_radius),
        color_mode: color_mode as i32,
        fixed_color,
        background: Some(color(args.background)),
    };
    let nonce = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    Ok(pb::SubmitJobRequest {
        request_id: format!("cli-{}-{nonce}", std::process::id()),
        dataset_id,
        camera_path: Some(pb::CameraPath { path: Some(path) }),
        width: args.size.0,
        height: args.size.1,
        render: Some(render),
        priority: args.priority,
    })
}

pub fn run(server: &str, args: &RenderArgs) -> Result<()> {
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async {
        let mut client = Client::connect(server, args.token.as_deref()).await?;
        let dataset = client.ensure_dataset(&args.input).await?;
        println!(
            "{}: dataset {} on {server}",
            args.input.display(),
            dataset.id
        );
        let job = client
            .jobs
            .submit_job(submission(args, dataset.id)?)
            .await
            .map_err(crate::remote::status_error)?
            .into_inner();
        println!("job {} submitted: {} frames", job.id, job.frames_total);
        let finished = client.follow(&job.id, false).await?;
        require_success(&finished)?;
        if args.turntable.is_some() {
            let written = client.fetch_frames(&job.id, 0, &args.out).await?;
            println!("{} frames in {}", written.len(), args.out.display());
            if let Some(video) = &args.video {
                crate::video::assemble(&args.out, video, args.fps)?;
            }
        } else {
            let temp = tempdir_beside(&args.out)?;
            let written = client.fetch_frames(&job.id, 0, &temp).await?;
            let frame = written.first().context("the server returned no frame")?;
            std::fs::rename(frame, &args.out)
                .with_context(|| format!("writing {}", args.out.display()))?;
            let _ = std::fs::remove_dir_all(&temp);
            println!("{}", args.out.display());
        }
        let details = client
            .jobs
            .get_job(pb::GetJobRequest { id: job.id.clone() })
            .await
            .map_err(crate::remote::status_error)?
            .into_inner();
        if let Some(first) = details.frames.first() {
            println!(
                "frame {} on the server: {}",
                first.index,
                timings_line(&first.timings)
            );
        }
        Ok(())
    })
}

/// A fresh folder next to `file` (same file system, so a rename can move frames into place).
fn tempdir_beside(file: &std::path::Path) -> Result<std::path::PathBuf> {
    let parent = file
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(std::path::Path::new("."));
    let dir = parent.join(format!(".pointfarm-fetch-{}", std::process::id()));
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    Ok(dir)
}

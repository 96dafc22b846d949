//! `pointfarm bench --copc POINTS --copc-s3`: the first frame of a COPC file read from an S3
//! server against the same file read from the local disk, both from cold caches.
//!
//! The terrain is built and exported once into the inputs folder (kept there and reused when
//! one is given) and uploaded once to an `s3s-fs` server on loopback, whose bucket keeps it as
//! a plain file. Each round renders one full view with each side in turn, alternating which
//! goes first, so a drift of the machine's speed reaches both alike; before every frame the
//! local file and the server's file are dropped from the OS's page cache, and every frame
//! starts from a fresh opening (header, root page, color sample) with empty node caches and,
//! by URL, a fresh client with no range cache; one coarse frame, not measured, comes first,
//! so that neither side pays for the renderer's first use. A frame's time runs from the opening to the
//! image; by URL it also counts what was fetched against the compressed bytes of the nodes
//! drawn, and its image is compared with the local one pixel for pixel.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use pointfarm_render::copc::{open_copc, open_copc_url, CopcDataset};
use pointfarm_render::gpu::{AdapterChoice, GpuContext};
use pointfarm_render::remote::{ObjectUrl, RemoteClient, RemoteSettings};
use serde::Serialize;

use super::s3_server::S3Server;
use super::ObjectStorageError;
use crate::copc::{drop_page_cache, mib, render_full_view, write_copc, CopcOptions};
use crate::scratch::{load_average, progress_log, scratch_dir};
use crate::stats::median;

/// The bucket the file is uploaded to.
const BUCKET: &str = "pointfarm-bench";
/// The pixel error of the unmeasured frame before the rounds: coarse, so it reads little.
const WARM_UP_LOD_ERROR: f64 = 8.0;
/// Rounds of one local and one S3 frame when not told.
pub const COPC_S3_ROUNDS: usize = 3;

/// What to generate and measure.
#[derive(Debug, Clone)]
pub struct CopcS3Options {
    /// The terrain, the image and the pixel error (the first of `lod_errors`).
    pub copc: CopcOptions,
    pub rounds: usize,
    /// The `s3s-fs` binary.
    pub s3s_fs: PathBuf,
    pub adapter: AdapterChoice,
    /// A folder the COPC file and the server's bucket are kept in and reused from; a scratch
    /// folder removed afterwards when None.
    pub inputs: Option<PathBuf>,
}

/// Which copy of the file a frame read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Side {
    Local,
    S3,
}

/// One first frame from cold caches.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct ColdFrame {
    pub side: Side,
    pub round: usize,
    /// From the opening to the image, and the opening alone.
    pub ms: f64,
    pub open_ms: f64,
    pub nodes: u64,
    pub points: u64,
    /// Compressed bytes of the nodes drawn.
    pub node_bytes: u64,
    /// By URL: requests and payload bytes fetched, the opening's included.
    pub requests: u64,
    pub fetched_bytes: u64,
    /// The machine's 1-minute load average before the frame.
    pub load_average: Option<f64>,
}

/// What `--copc-s3` measured.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct CopcS3Result {
    pub points: u64,
    pub width: u32,
    pub height: u32,
    pub lod_error: f64,
    pub file_bytes: u64,
    /// Seconds the upload took; None when the object was already there.
    pub upload_s: Option<f64>,
    pub frames: Vec<ColdFrame>,
    pub local_median_ms: f64,
    pub s3_median_ms: f64,
    /// The S3 frames' median time over the local frames'.
    pub time_ratio: f64,
    /// The S3 frames' median bytes fetched over the bytes of the nodes drawn.
    pub fetched_ratio: f64,
    /// Every S3 frame's image is the local frame's, pixel for pixel.
    pub same_images: bool,
}

/// Runs `--copc-s3`. The server's endpoint and credentials are set in this process's
/// environment before the GPU is opened, which is why the GPU is opened here.
pub fn measure(
    options: &CopcS3Options,
    progress: &mut dyn FnMut(&str),
) -> Result<CopcS3Result, ObjectStorageError> {
    let mut log = progress_log("copc-s3", progress);
    let scratch = match &options.inputs {
        Some(_) => None,
        None => Some(scratch_dir(
            options.copc.scratch_parent.as_deref(),
            "copc-s3",
        )?),
    };
    let dir = match (&options.inputs, &scratch) {
        (Some(inputs), _) => inputs.clone(),
        (None, Some(scratch)) => scratch.path().to_path_buf(),
        (None, None) => unreachable!("a scratch folder is made without an inputs folder"),
    };
    let copc = &options.copc;
    let name = format!("terrain-{}-{}.copc.laz", copc.points, copc.seed);
    let path = dir.join(&name);
    if path.is_file() {
        log(format!("copc-s3: reusing {}", path.display()));
    } else {
        let partial = dir.join(format!("{name}.partial"));
        std::fs::create_dir_all(&dir).map_err(|e| setup(&dir, e))?;
        write_copc(copc, &dir, &partial, &mut log)?;
        std::fs::rename(&partial, &path).map_err(|e| setup(&path, e))?;
    }
    let file_bytes = std::fs::metadata(&path).map_err(|e| setup(&path, e))?.len();

    let server = S3Server::start(&options.s3s_fs, &dir.join("s3"), BUCKET)?;
    server.export_environment();
    let url = ObjectUrl::parse(&format!("s3://{BUCKET}/{name}"))?;
    let stored = server.stored(BUCKET, &name);
    let upload_s = upload_once(&path, &url, &stored, file_bytes, &mut log)?;

    let gpu = Arc::new(GpuContext::new(options.adapter)?);
    log(format!("copc-s3: adapter {}", gpu.describe()));
    let lod_error = copc
        .lod_errors
        .first()
        .copied()
        .unwrap_or(pointfarm_render::cut::DEFAULT_LOD_ERROR_PX);
    // The process's first frame also sets up the renderer's pipelines; it is not measured.
    let warm_up = open_copc(&path)?;
    render_full_view(&gpu, &warm_up.dataset, copc, WARM_UP_LOD_ERROR)?;
    drop(warm_up);
    let mut frames = Vec::with_capacity(options.rounds * 2);
    let mut reference = None;
    let mut same_images = true;
    for round in 0..options.rounds {
        let order = if round % 2 == 0 {
            [Side::Local, Side::S3]
        } else {
            [Side::S3, Side::Local]
        };
        for side in order {
            drop_page_cache(&path)?;
            drop_page_cache(&stored)?;
            let (frame, image) = cold_frame(&gpu, copc, lod_error, side, round, &path, &url)?;
            log(format!(
                "copc-s3: round {round} {side:?}: {:.0} ms (open {:.0} ms), {} nodes, {:.1} MiB \
                 of nodes, {:.1} MiB fetched in {} requests, load {:?}",
                frame.ms,
                frame.open_ms,
                frame.nodes,
                mib(frame.node_bytes),
                mib(frame.fetched_bytes),
                frame.requests,
                frame.load_average
            ));
            // Round 0 renders the local side first: its image is the one every frame matches.
            match &reference {
                Some(reference) => same_images &= *reference == image,
                None => reference = Some(image),
            }
            frames.push(frame);
        }
    }
    summarize(
        options,
        lod_error,
        file_bytes,
        upload_s,
        frames,
        same_images,
    )
}

/// Uploads the file unless the server already holds an object of its size; the seconds the
/// upload took.
fn upload_once(
    path: &Path,
    url: &ObjectUrl,
    stored: &Path,
    file_bytes: u64,
    log: &mut dyn FnMut(String),
) -> Result<Option<f64>, ObjectStorageError> {
    let client = RemoteClient::new(RemoteSettings::default())?;
    let held = std::fs::metadata(stored).is_ok_and(|m| m.len() == file_bytes)
        && client
            .open(url)
            .is_ok_and(|object| object.size() == file_bytes);
    if held {
        log(format!("copc-s3: {url} already uploaded"));
        return Ok(None);
    }
    let started = Instant::now();
    client.upload_file(path, url)?;
    let upload_s = started.elapsed().as_secs_f64();
    log(format!(
        "copc-s3: uploaded {:.1} MiB to {url} in {upload_s:.1} s",
        mib(file_bytes)
    ));
    Ok(Some(upload_s))
}

/// Opens one side's copy and renders its full view from empty caches.
fn cold_frame(
    gpu: &Arc<GpuContext>,
    options: &CopcOptions,
    lod_error: f64,
    side: Side,
    round: usize,
    path: &Path,
    url: &ObjectUrl,
) -> Result<(ColdFrame, Vec<u8>), ObjectStorageError> {
    let load_average = load_average();
    let started = Instant::now();
    let (copc, client): (CopcDataset, _) = match side {
        Side::Local => (open_copc(path)?, None),
        Side::S3 => {
            let client = RemoteClient::new(RemoteSettings::default())?;
            (open_copc_url(&client, url)?, Some(client))
        }
    };
    let open_ms = started.elapsed().as_secs_f64() * 1e3;
    let (frame, report, _) = render_full_view(gpu, &copc.dataset, options, lod_error)?;
    let ms = started.elapsed().as_secs_f64() * 1e3;
    let fetched = client.map(|client| client.counts()).unwrap_or_default();
    let cold = ColdFrame {
        side,
        round,
        ms,
        open_ms,
        nodes: report.counts.nodes,
        points: report.counts.points_rendered,
        node_bytes: report.counts.bytes_read,
        requests: fetched.requests,
        fetched_bytes: fetched.bytes,
        load_average,
    };
    Ok((cold, frame.image.into_raw()))
}

fn summarize(
    options: &CopcS3Options,
    lod_error: f64,
    file_bytes: u64,
    upload_s: Option<f64>,
    frames: Vec<ColdFrame>,
    same_images: bool,
) -> Result<CopcS3Result, ObjectStorageError> {
    let of_side = |side: Side, figure: fn(&ColdFrame) -> f64| {
        median(
            frames
                .iter()
                .filter(|f| f.side == side)
                .map(figure)
                .collect(),
        )
    };
    let local_median_ms = of_side(Side::Local, |f| f.ms);
    let s3_median_ms = of_side(Side::S3, |f| f.ms);
    if local_median_ms.is_nan() || s3_median_ms.is_nan() {
        return Err(crate::BenchError::NoFrames.into());
    }
    let fetched_ratio = of_side(Side::S3, |f| {
        f.fetched_bytes as f64 / f.node_bytes.max(1) as f64
    });
    Ok(CopcS3Result {
        points: options.copc.points,
        width: options.copc.width,
        height: options.copc.height,
        lod_error,
        file_bytes,
        upload_s,
        local_median_ms,
        s3_median_ms,
        time_ratio: s3_median_ms / local_median_ms,
        fetched_ratio,
        same_images,
        frames,
    })
}

fn setup(path: &Path, error: std::io::Error) -> ObjectStorageError {
    ObjectStorageError::Setup(format!("{}: {error}", path.display()))
}

/// The result as markdown.
pub fn markdown(r: &CopcS3Result) -> String {
    let mut md = format!(
        "{} points of terrain, one COPC file of {:.1} MiB; a {}x{} full view at {} px from cold \
         caches, local disk against s3s-fs on loopback, alternated.\n\n\
         | round | side | first frame | open | nodes | MiB of nodes | MiB fetched | requests | load |\n\
         |---:|---|---:|---:|---:|---:|---:|---:|---:|\n",
        r.points,
        mib(r.file_bytes),
        r.width,
        r.height,
        r.lod_error
    );
    for f in &r.frames {
        md.push_str(&format!(
            "| {} | {:?} | {:.2} s | {:.0} ms | {} | {:.1} | {:.1} | {} | {} |\n",
            f.round,
            f.side,
            f.ms / 1e3,
            f.open_ms,
            f.nodes,
            mib(f.node_bytes),
            mib(f.fetched_bytes),
            f.requests,
            f.load_average.map_or("-".into(), |l| format!("{l:.2}")),
        ));
    }
    md.push_str(&format!(
        "\nMedians: local {:.2} s, S3 {:.2} s, S3 / local {:.3}x; bytes fetched / bytes of nodes \
         drawn {:.3}x; images {}.\n",
        r.local_median_ms / 1e3,
        r.s3_median_ms / 1e3,
        r.time_ratio,
        r.fetched_ratio,
        if r.same_images {
            "identical"
        } else {
            "DIFFERENT"
        }
    ));
    md
}

//! `pointfarm bench`: the PointList baseline and the compute rasterizer's modes on the same
//! workloads, in one run on one adapter; prints tables and writes JSON, markdown and a plot.
//! The harness is the `pointfarm-bench` crate; this module parses the flags and prints.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use pointfarm_bench::json::RunContext;
use pointfarm_bench::{self as bench, BenchOptions, ComputeMode, HEADLINE_WORKLOAD};
use pointfarm_render::gpu::{AdapterChoice, GpuContext};

use crate::parse;

#[derive(Args)]
pub struct BenchArgs {
    /// A run of a few minutes on a 2-core software adapter: fewer frames, smaller cuboid planes.
    #[arg(long)]
    quick: bool,
    /// Write the figures as JSON to FILE.
    #[arg(long, value_name = "FILE")]
    json: Option<PathBuf>,
    /// Write the tables as markdown to FILE.
    #[arg(long, value_name = "FILE")]
    markdown: Option<PathBuf>,
    /// Write a PNG plot of frame time against points in view and against overdraw to FILE.
    #[arg(long, value_name = "FILE")]
    plot: Option<PathBuf>,
    /// Only these workloads (comma-separated), e.g. `uniform-10m,cuboid-k64`; a name also
    /// selects its other views (`uniform-10m` selects `uniform-10m-corner` and `uniform-10m-partial`).
    #[arg(long, value_delimiter = ',', value_name = "NAMES")]
    only: Vec<String>,
    /// Also render a cube of POINTS points (100 million when no count is given), generated and
    /// uploaded segment by segment, and report the host's memory peak during its ingest (100M
    /// points need about 4 GiB on a software adapter). Accepts `1000000000`, `1_000_000_000`.
    #[arg(long, value_name = "POINTS", value_parser = parse_point_count)]
    huge: Option<Option<usize>>,
    /// Points of the cube written as LAZ for the ingest figures (decoding on all cores and on
    /// one, and loading from the dataset cache), besides the real scans: 10 million by
    /// default, 2 million with `--quick`. Select only those figures with `--only ingest`.
    #[arg(long, value_name = "POINTS", value_parser = parse_point_count)]
    ingest_points: Option<usize>,
    /// Measure the basic mode only (not high quality, the 32-bit atomics path, nor fill with
    /// EDL or Pintus shading).
    #[arg(long, conflicts_with = "modes")]
    basic_only: bool,
    /// The compute modes measured besides the basic mode (comma-separated); all by default.
    #[arg(long, value_delimiter = ',', value_name = "MODES")]
    modes: Vec<BenchMode>,
    /// Image size in pixels (default 1920x1080; 64x48 with --service-load).
    #[arg(long, value_parser = parse::size)]
    size: Option<(u32, u32)>,
    /// Directory of the real scans (lone-star.laz, autzen_trim.laz); missing ones are skipped.
    #[arg(long, default_value = "../shared/data")]
    data: PathBuf,
    /// Time every stage with host clocks, even where the adapter has GPU timestamps (always so
    /// on a software adapter, whose timestamps under-report compute passes).
    #[arg(long)]
    host_clocks: bool,
    /// Adapter: auto (hardware GPU if present, else lavapipe), hardware or software.
    #[arg(long, env = "POINTFARM_ADAPTER", default_value = "auto")]
    adapter: AdapterChoice,
    /// Measure the daemon's scheduler instead of the renderer: leasing a frame with no job
    /// history and with up to 10,000 finished jobs (1,000 with --quick). Needs no GPU.
    #[arg(long, conflicts_with_all = ["only", "huge", "modes", "basic_only", "plot"])]
    scheduler: bool,
    /// Measure building the level-of-detail store of a campaign instead of the renderer:
    /// POINTS points of generated terrain (20 million when no count is given, 4 million with
    /// --quick) split into --campaign-files tiles, written as LAZ and, when the disk holds it,
    /// as LAS (34 B a point); each kind read through the dataset source, then built into a
    /// fresh store, with its stages, peak memory and disk. Needs no GPU.
    #[arg(
        long,
        value_name = "POINTS",
        value_parser = parse_point_count,
        conflicts_with_all = ["only", "huge", "modes", "basic_only", "plot", "scheduler"]
    )]
    campaign: Option<Option<usize>>,
    /// Files (tiles) of the --campaign and of --published-store.
    #[arg(long, value_name = "N", default_value_t = bench::campaign::CAMPAIGN_FILES)]
    campaign_files: usize,
    /// With --campaign: after the LAZ build, render a --size turntable of N frames (12 when
    /// no count is given) of its store cut by cut, from a cold cache with read-ahead, within
    /// --cut-memory-budget; needs a GPU (or lavapipe). With --cuts: the frames of the
    /// out-of-core turntable (12, 6 with --quick).
    #[arg(long, value_name = "N")]
    cut_frames: Option<Option<usize>>,
    /// The memory budget of the --cut-frames turntable and of --cuts' cuts (not the
    /// out-of-core turntable's 512 MiB), in bytes (`4GiB`, `512MiB` accepted).
    #[arg(long, value_name = "BYTES", value_parser = parse_bytes,
          default_value_t = bench::cuts::TURNTABLE_MEMORY_BUDGET)]
    cut_memory_budget: u64,
    /// Measure rendering level-of-detail stores cut by cut: the full views of a 10M- and a
    /// 100M-point terrain (2M and 20M with --quick), a turntable of the larger within 512 MiB,
    /// the fidelity of the default pixel error against 0 in every mode (the real scans, the
    /// smaller terrain, a 10M cube, 2M with --quick), and the cube resident against as a cut.
    #[arg(long, conflicts_with_all = ["only", "huge", "modes", "basic_only", "plot", "scheduler", "campaign"])]
    cuts: bool,
    /// With --cuts: points of the smaller and the larger terrain, e.g. `10000000,100000000`.
    #[arg(long, value_name = "SMALL,LARGE", value_delimiter = ',', value_parser = parse_point_count, requires = "cuts")]
    cut_points: Vec<usize>,
    /// Measure a COPC file's first frame against decoding it whole: POINTS points of generated
    /// terrain (100 million when no count is given, 10 million with --quick) built and
    /// exported as one COPC file; every point decoded as plain LAZ on all cores; the file
    /// opened and one --size full view rendered node by node at the default pixel error from
    /// empty caches (the file's pages dropped from the OS's cache before each), within
    /// --cut-memory-budget; and that pixel error's fidelity against 0 in every mode.
    #[arg(
        long,
        value_name = "POINTS",
        value_parser = parse_point_count,
        conflicts_with_all = ["only", "huge", "modes", "basic_only", "plot", "scheduler", "campaign", "cuts"]
    )]
    copc: Option<Option<usize>>,
    /// With --copc: the pixel errors whose first frames are measured (comma-separated), each
    /// from empty caches; the fidelity is measured at the first. The renderer's default alone
    /// when not given.
    #[arg(long, value_name = "PX,…", value_delimiter = ',', value_parser = parse::non_negative, requires = "copc")]
    copc_lod_errors: Vec<f64>,
    #[command(flatten)]
    object_storage: Box<ObjectStorageArgs>,
    /// Measure the service instead of the renderer: a real `pointfarm serve` on loopback with
    /// its embedded worker, a generated dataset registered, --service-jobs jobs of
    /// --service-frames-per-job frames (at --size, 64x48 by default) submitted from
    /// --service-clients clients, each with a connection of its own, and polled with GetJob
    /// until done: frames a second, SubmitJob and GetJob latency. Then a daemon without a
    /// worker, and this command leasing frames from it as a worker and handing them back:
    /// LeaseFrame latency. The daemons are stopped (SIGTERM) and their folders removed.
    #[arg(long, conflicts_with_all = ["only", "huge", "modes", "basic_only", "plot", "scheduler", "campaign", "cuts", "copc", "published_store"])]
    service_load: bool,
    /// With --service-load: jobs submitted.
    #[arg(long, value_name = "N", default_value_t = bench::service_load::DEFAULT_JOBS, requires = "service_load")]
    service_jobs: u32,
    /// With --service-load: frames of each job (a turntable).
    #[arg(long, value_name = "N", default_value_t = bench::service_load::DEFAULT_FRAMES_PER_JOB, requires = "service_load")]
    service_frames_per_job: u32,
    /// With --service-load: clients submitting and polling at once.
    #[arg(long, value_name = "N", default_value_t = bench::service_load::DEFAULT_CLIENTS, requires = "service_load")]
    service_clients: u32,
    /// With --service-load: measured leases.
    #[arg(long, value_name = "N", default_value_t = bench::service_load::DEFAULT_LEASES, requires = "service_load")]
    service_leases: u32,
    /// With --service-load: runs of each daemon binary, the binaries in turn.
    #[arg(long, value_name = "N", default_value_t = 1, requires = "service_load")]
    service_runs: u32,
    /// With --service-load: the `pointfarm` binary whose `serve` is measured (repeatable: the
    /// binaries are run alternately, each against the same load generator, and compared with
    /// the first); this binary when not given.
    #[arg(long, value_name = "PATH", requires = "service_load")]
    daemon_binary: Vec<PathBuf>,
}

/// The object-storage benchmarks' flags (boxed: a command's arguments stay small).
#[derive(Args)]
struct ObjectStorageArgs {
    /// With --copc: the file read from an S3 server on loopback (--s3s-fs) against the same
    /// file on the local disk instead: one --size full view at the first of --copc-lod-errors,
    /// each side in turn for --object-storage-rounds rounds, every frame from cold caches (the
    /// file and the server's copy dropped from the OS's cache, a fresh opening and client);
    /// times, bytes fetched against the nodes drawn, and the images compared.
    #[arg(long, requires = "copc")]
    copc_s3: bool,
    /// With --copc-s3: rounds of one local and one S3 first frame.
    #[arg(long, value_name = "N", default_value_t = bench::object_storage::copc_s3::COPC_S3_ROUNDS, requires = "copc_s3")]
    object_storage_rounds: usize,
    /// Measure the daemon out of the data path: POINTS points of generated terrain (1 billion
    /// when no count is given) in --campaign-files LAZ tiles registered with a `pointfarm serve
    /// --store-url` that publishes the store it builds to an S3 server on loopback (--s3s-fs);
    /// two `pointfarm worker` processes new to the dataset then render a cold --size turntable
    /// of --published-frames frames from the bucket. The daemon's and the workers' CPU time
    /// over the job, the node records the daemon served, and the frames against a local render.
    #[arg(
        long,
        value_name = "POINTS",
        value_parser = parse_point_count,
        conflicts_with_all = ["only", "huge", "modes", "basic_only", "plot", "scheduler", "campaign", "cuts", "copc"]
    )]
    published_store: Option<Option<usize>>,
    /// With --published-store: frames of the measured turntable.
    #[arg(long, value_name = "N", default_value_t = bench::object_storage::published::PUBLISHED_FRAMES, requires = "published_store")]
    published_frames: usize,
    /// The `s3s-fs` binary of --copc-s3 and --published-store.
    #[arg(
        long,
        value_name = "PATH",
        env = "POINTFARM_TEST_S3S_FS",
        default_value = "target/tools/bin/s3s-fs"
    )]
    s3s_fs: PathBuf,
    /// With --copc-s3 or --published-store: a folder the generated inputs (the COPC file and
    /// its bucket, the campaign's tiles) are written into once and reused from by later runs;
    /// they are written into the scratch folder and removed when not given.
    #[arg(long, value_name = "DIR")]
    inputs_dir: Option<PathBuf>,
}

/// The image size of the renderer's benchmarks when --size is not given.
const DEFAULT_SIZE: (u32, u32) = (1920, 1080);

/// A byte count: a number with an optional KiB, MiB or GiB suffix.
fn parse_bytes(text: &str) -> Result<u64, String> {
    let text = text.trim().replace('_', "");
    let (number, unit) = match text.find(|c: char| c.is_ascii_alphabetic()) {
        Some(i) => text.split_at(i),
        None => (text.as_str(), ""),
    };
    let shift = match unit.to_ascii_lowercase().as_str() {
        "" | "b" => 0,
        "kib" | "k" => 10,
        "mib" | "m" => 20,
        "gib" | "g" => 30,
        other => return Err(format!("unknown unit '{other}': use KiB, MiB or GiB")),
    };
    let n: u64 = number
        .trim()
        .parse()
        .map_err(|e| format!("'{text}' is not a byte count: {e}"))?;
    n.checked_mul(1 << shift)
        .ok_or_else(|| format!("'{text}' is too large"))
}

/// A compute mode besides the basic one, as `--modes` names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum BenchMode {
    /// High quality (Schütz & Wimmer's averaging).
    Hq,
    /// The basic mode on the 32-bit atomics path.
    #[value(name = "basic-32")]
    Basic32,
    /// Eye-Dome Lighting.
    Edl,
    /// Fill (Pintus et al.) and Eye-Dome Lighting.
    FillEdl,
    /// Fill and Pintus et al.'s shading.
    FillPintus,
}

impl From<BenchMode> for ComputeMode {
    fn from(mode: BenchMode) -> Self {
        match mode {
            BenchMode::Hq => ComputeMode::HighQuality,
            BenchMode::Basic32 => ComputeMode::BasicAtomic32,
            BenchMode::Edl => ComputeMode::Edl,
            BenchMode::FillEdl => ComputeMode::FillEdl,
            BenchMode::FillPintus => ComputeMode::FillPintus,
        }
    }
}

/// A point count, with optional `_` separators; at least one point.
fn parse_point_count(text: &str) -> Result<usize, String> {
    match text.replace('_', "").parse::<usize>() {
        Ok(0) => Err("at least one point is needed".into()),
        Ok(n) => Ok(n),
        Err(e) => Err(format!("'{text}' is not a point count: {e}")),
    }
}

pub fn run(args: BenchArgs) -> Result<()> {
    let started = Instant::now();
    if args.scheduler {
        return run_scheduler(&args, started);
    }
    if let Some(points) = args.campaign {
        return run_campaign(&args, points, started);
    }
    if args.cuts {
        return run_cuts(&args, started);
    }
    if let Some(points) = args.copc {
        if args.object_storage.copc_s3 {
            return run_copc_s3(&args, points, started);
        }
        return run_copc(&args, points, started);
    }
    if let Some(points) = args.object_storage.published_store {
        return run_published_store(&args, points, started);
    }
    if args.service_load {
        return run_service_load(&args, started);
    }
    let (width, height) = args.size.unwrap_or(DEFAULT_SIZE);
    let defaults = if args.quick {
        BenchOptions::quick(width, height, args.data.clone())
    } else {
        BenchOptions::full(width, height, args.data.clone())
    };
    let options = BenchOptions {
        ingest_points: args.ingest_points.or(defaults.ingest_points),
        host_clocks: args.host_clocks,
        modes: if args.basic_only {
            Vec::new()
        } else if args.modes.is_empty() {
            ComputeMode::ALL.to_vec()
        } else {
            args.modes.iter().map(|&mode| mode.into()).collect()
        },
        only: args.only.clone(),
        huge: args.huge.map(|points| points.unwrap_or(bench::HUGE_POINTS)),
        ..defaults.clone()
    };
    if args.plot.is_some() {
        bench::plot::check_font()?;
    }
    let gpu = Arc::new(GpuContext::new(args.adapter)?);
    outln!("adapter: {}", gpu.describe());
    let settle = match bench::settle_after_baseline(gpu.adapter_info.device_type) {
        Some(settle) => format!(
            "; the first compute method after PointList for {} ms",
            settle.as_millis()
        ),
        None => String::new(),
    };
    outln!(
        "{width}x{height}, {} warm-up + {} measured rounds per workload; in a round each method \
         renders unmeasured frames for {} ms (1 to {} frames{settle}), then the measured one",
        options.rounds.warmup_frames,
        options.rounds.frames,
        bench::WARM_IN_A_ROW.as_millis(),
        bench::MAX_WARM_FRAMES,
    );
    let report = bench::run(gpu, &options, &mut progress)?;

    let markdown = bench::markdown::tables(&report);
    outln!("\n{markdown}");
    if let Some(speedup) = report.speedup_vs_pointlist {
        outln!("speedup_vs_pointlist ({HEADLINE_WORKLOAD}): {speedup:.2}x");
    }
    if let Some(warning) = report.timestamp_warning() {
        eprintln!("warning: {warning}");
    }

    if let Some(path) = &args.markdown {
        std::fs::write(path, &markdown).with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(path) = &args.json {
        let context = RunContext {
            command: std::env::args().collect::<Vec<_>>().join(" "),
            quick: args.quick,
            started,
        };
        bench::json::write(path, &report, &context)?;
    }
    if let Some(path) = &args.plot {
        bench::plot::write(&report, path)?;
    }
    outln!("done in {:.0} s", started.elapsed().as_secs_f64());
    Ok(())
}

/// `--scheduler`: the lease latency against the job history.
fn run_scheduler(args: &BenchArgs, started: Instant) -> Result<()> {
    use bench::scheduler::{self, FULL_HISTORY_JOBS};
    let longest = if args.quick {
        FULL_HISTORY_JOBS / 10
    } else {
        FULL_HISTORY_JOBS
    };
    let samples = if args.quick { 50 } else { 500 };
    let histories = [0, longest / 10, longest];
    let results = scheduler::measure(&histories, samples, &mut progress)?;
    let markdown = scheduler::markdown(&results);
    finish_as(args, started, &markdown, "scheduler", &results)
}

/// `--campaign`: building the level-of-detail store of a campaign of many files.
fn run_campaign(args: &BenchArgs, points: Option<usize>, started: Instant) -> Result<()> {
    use bench::campaign::{self, CampaignOptions, CAMPAIGN_POINTS, CAMPAIGN_QUICK_POINTS};
    let default = if args.quick {
        CAMPAIGN_QUICK_POINTS
    } else {
        CAMPAIGN_POINTS
    };
    let points = points.map_or(default, |n| n as u64);
    let (width, height) = args.size.unwrap_or(DEFAULT_SIZE);
    let options = CampaignOptions {
        turntable: args.cut_frames.map(|frames| bench::cuts::TurntableOptions {
            width,
            height,
            memory_budget_bytes: args.cut_memory_budget,
            ..bench::cuts::TurntableOptions::new(frames.unwrap_or(bench::cuts::TURNTABLE_FRAMES))
        }),
        ..CampaignOptions::new(points, args.campaign_files)
    };
    let gpu = match options.turntable {
        Some(_) => {
            let gpu = Arc::new(GpuContext::new(args.adapter)?);
            outln!("adapter: {}", gpu.describe());
            Some(gpu)
        }
        None => None,
    };
    let result = campaign::measure_with_frames(&options, gpu.as_ref(), &mut progress)?;
    let markdown = bench::markdown::campaign_tables(&result);
    finish(args, started, &markdown, |path, context| {
        Ok(bench::json::write_campaign(path, &result, context)?)
    })
}

/// `--cuts`: rendering level-of-detail stores cut by cut.
fn run_cuts(args: &BenchArgs, started: Instant) -> Result<()> {
    use bench::cuts::{self, CutsOptions};
    let (width, height) = args.size.unwrap_or(DEFAULT_SIZE);
    let defaults = if args.quick {
        CutsOptions::quick(width, height, args.data.clone())
    } else {
        CutsOptions::full(width, height, args.data.clone())
    };
    let (small_points, large_points) = match args.cut_points.as_slice() {
        [] => (defaults.small_points, defaults.large_points),
        [small, large] => (*small as u64, *large as u64),
        _ => anyhow::bail!("--cut-points takes two counts, SMALL,LARGE"),
    };
    let options = CutsOptions {
        small_points,
        large_points,
        out_of_core_frames: args.cut_frames.map_or(defaults.out_of_core_frames, |n| {
            n.unwrap_or(cuts::TURNTABLE_FRAMES)
        }),
        memory_budget_bytes: args.cut_memory_budget,
        ..defaults
    };
    let gpu = Arc::new(GpuContext::new(args.adapter)?);
    outln!("adapter: {}", gpu.describe());
    let result = cuts::measure(&gpu, &options, &mut progress)?;
    let markdown = cuts::markdown::cuts_tables(&result);
    finish(args, started, &markdown, |path, context| {
        Ok(bench::json::write_cuts(path, &result, context)?)
    })
}

/// `--copc`: a COPC file's first frame against decoding it whole.
fn run_copc(args: &BenchArgs, points: Option<usize>, started: Instant) -> Result<()> {
    use bench::copc;
    let options = copc_options(args, points);
    let gpu = Arc::new(GpuContext::new(args.adapter)?);
    outln!("adapter: {}", gpu.describe());
    let result = copc::measure(&gpu, &options, &mut progress)?;
    finish(args, started, &copc::markdown(&result), |path, context| {
        Ok(bench::json::write_copc(path, &result, context)?)
    })
}

/// The terrain, image and pixel errors of `--copc`, with or without `--copc-s3`.
fn copc_options(args: &BenchArgs, points: Option<usize>) -> bench::copc::CopcOptions {
    use bench::copc::{self, CopcOptions};
    let default_points = if args.quick {
        copc::COPC_QUICK_POINTS
    } else {
        copc::COPC_POINTS
    };
    let (width, height) = args.size.unwrap_or(DEFAULT_SIZE);
    let defaults = CopcOptions::new(points.map_or(default_points, |n| n as u64), width, height);
    CopcOptions {
        memory_budget_bytes: args.cut_memory_budget,
        lod_errors: if args.copc_lod_errors.is_empty() {
            defaults.lod_errors.clone()
        } else {
            args.copc_lod_errors.clone()
        },
        ..defaults
    }
}

/// `--copc --copc-s3`: a COPC file's first frame from an S3 server against the local disk.
fn run_copc_s3(args: &BenchArgs, points: Option<usize>, started: Instant) -> Result<()> {
    use bench::object_storage::copc_s3::{self, CopcS3Options};
    let copc = copc_options(args, points);
    let options = CopcS3Options {
        copc,
        rounds: args.object_storage.object_storage_rounds,
        s3s_fs: args.object_storage.s3s_fs.clone(),
        adapter: args.adapter,
        inputs: args.object_storage.inputs_dir.clone(),
    };
    let result = copc_s3::measure(&options, &mut progress)?;
    finish_as(
        args,
        started,
        &copc_s3::markdown(&result),
        "copcS3",
        &result,
    )
}

/// `--published-store`: workers reading a store published to object storage, and the daemon's
/// CPU time against theirs.
fn run_published_store(args: &BenchArgs, points: Option<usize>, started: Instant) -> Result<()> {
    use bench::object_storage::published::{self, PublishedOptions, PUBLISHED_POINTS};
    let (width, height) = args.size.unwrap_or(DEFAULT_SIZE);
    let points = points.map_or(PUBLISHED_POINTS, |n| n as u64);
    let this = std::env::current_exe().context("finding the pointfarm binary")?;
    let defaults = PublishedOptions::new(
        points,
        args.campaign_files,
        this,
        args.object_storage.s3s_fs.clone(),
    );
    let options = PublishedOptions {
        frames: args.object_storage.published_frames,
        width,
        height,
        inputs: args.object_storage.inputs_dir.clone(),
        ..defaults
    };
    let result = published::measure(&options, &mut progress)?;
    finish_as(
        args,
        started,
        &published::markdown(&result),
        "publishedStore",
        &result,
    )
}

/// `--service-load`: real daemon processes under many clients, and leasing as a worker.
fn run_service_load(args: &BenchArgs, started: Instant) -> Result<()> {
    use bench::service_load::{self, ServiceLoad, ServiceLoadOptions};
    let this = std::env::current_exe().context("finding the pointfarm binary")?;
    let (width, height) = args.size.unwrap_or(service_load::DEFAULT_SIZE);
    let options = ServiceLoadOptions {
        daemon_binaries: if args.daemon_binary.is_empty() {
            vec![this]
        } else {
            args.daemon_binary.clone()
        },
        runs: args.service_runs,
        load: ServiceLoad {
            jobs: args.service_jobs,
            frames_per_job: args.service_frames_per_job,
            clients: args.service_clients,
            leases: args.service_leases,
            width,
            height,
        },
        adapter: args.adapter.to_string(),
    };
    let result = service_load::measure(&options, &mut progress)?;
    finish(
        args,
        started,
        &service_load::markdown(&result),
        |path, context| Ok(service_load::write_json(path, &result, context)?),
    )
}

/// Shows a benchmark's progress lines on stderr, indented, beside its tables on stdout.
fn progress(line: &str) {
    eprintln!("  {line}");
}

/// [`finish`] with the results written to `--json` as `key` ([`write_json_as`]).
fn finish_as(
    args: &BenchArgs,
    started: Instant,
    markdown: &str,
    key: &str,
    value: &impl serde::Serialize,
) -> Result<()> {
    finish(args, started, markdown, |path, context| {
        write_json_as(path, context, key, value)
    })
}

/// Writes `value` to `path` as the JSON object `{"command": ..., key: value}`.
fn write_json_as(
    path: &Path,
    context: &RunContext,
    key: &str,
    value: &impl serde::Serialize,
) -> Result<()> {
    let json = serde_json::json!({ "command": context.command, key: value });
    std::fs::write(path, serde_json::to_vec_pretty(&json)?)
        .with_context(|| format!("writing {}", path.display()))
}

/// Prints a benchmark's tables, writes them to `--markdown` and its results to `--json` (with
/// `write_json`), and says how long it took.
fn finish(
    args: &BenchArgs,
    started: Instant,
    markdown: &str,
    write_json: impl FnOnce(&Path, &RunContext) -> Result<()>,
) -> Result<()> {
    outln!("\n{markdown}");
    if let Some(path) = &args.markdown {
        std::fs::write(path, markdown).with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(path) = &args.json {
        let context = RunContext {
            command: std::env::args().collect::<Vec<_>>().join(" "),
            quick: args.quick,
            started,
        };
        write_json(path, &context)?;
    }
    outln!("done in {:.0} s", started.elapsed().as_secs_f64());
    Ok(())
}

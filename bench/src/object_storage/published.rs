//! `pointfarm bench --published-store POINTS`: the daemon out of the data path. A daemon
//! started with `serve --store-url s3://…` (no embedded worker) builds the level-of-detail
//! store of a campaign of LAZ tiles and publishes it to an `s3s-fs` server on loopback; two
//! `pointfarm worker` processes, new to the dataset (empty caches, the bucket's files dropped
//! from the OS's page cache), then render a turntable of it, reading the nodes from the bucket.
//!
//! Measured over that job, from its submission to its last frame fetched: the CPU time of the
//! daemon and of each worker (`utime + stime` of `/proc/PID/stat`), the node records the
//! daemon served (its metric, which stays 0 when the workers read only the bucket), and the
//! frames against the same turntable rendered here by `pointfarm render` from the tiles,
//! pixel for pixel. The store is built by a first, small job with a worker of its own, stopped
//! before the measured job.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde::Serialize;

use super::s3_server::S3Server;
use super::ObjectStorageError;
use crate::campaign::write_campaign;
use crate::copc::drop_page_cache;
use crate::scratch::{load_average, progress_log, scratch_dir};
use crate::serve::{listens_within, serve_command};

/// The bucket stores are published to, and the prefix in it.
const BUCKET: &str = "pointfarm-stores";
const STORE_URL: &str = "s3://pointfarm-stores/farm";
/// Worker processes rendering the measured job.
pub const PUBLISHED_WORKERS: usize = 2;
/// Frames of the measured turntable when not told.
pub const PUBLISHED_FRAMES: usize = 12;
/// Points of `--published-store` given bare: the campaign of the target.
pub const PUBLISHED_POINTS: u64 = 1_000_000_000;
/// The pixel error of every job: always from levels of detail, whatever the size.
const LOD_ERROR: &str = "0.25";
/// The daemon's count of node records it served to workers.
const RECORDS_SERVED: &str = "pointfarm_store_records_served_total";
/// How long a daemon may take to listen, and workers to finish starting.
const START_TIMEOUT: Duration = Duration::from_secs(60);
const WORKER_SETTLE: Duration = Duration::from_secs(5);
/// The longest the store may take to build and publish.
const PUBLISH_TIMEOUT: Duration = Duration::from_secs(4 * 3600);

/// What to generate and run.
#[derive(Debug, Clone)]
pub struct PublishedOptions {
    pub points: u64,
    pub files: usize,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub seed: u64,
    /// The `pointfarm` binary whose `serve`, `worker` and `render` run.
    pub pointfarm: PathBuf,
    pub s3s_fs: PathBuf,
    /// A folder the tiles are kept in and reused from; written into the scratch folder
    /// otherwise.
    pub inputs: Option<PathBuf>,
    /// Where the scratch folder is made (the system's temporary folder by default).
    pub scratch_parent: Option<PathBuf>,
}

impl PublishedOptions {
    /// The campaign's terrain (its seed) in `files` tiles, the default frames at 1920x1080,
    /// in the scratch folder.
    pub fn new(points: u64, files: usize, pointfarm: PathBuf, s3s_fs: PathBuf) -> Self {
        Self {
            points,
            files,
            frames: PUBLISHED_FRAMES,
            width: 1920,
            height: 1080,
            seed: crate::campaign::CampaignOptions::new(points, files).seed,
            pointfarm,
            s3s_fs,
            inputs: None,
            scratch_parent: None,
        }
    }
}

/// CPU seconds (user and system) of one process over the measured job.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct ProcessCpu {
    pub name: String,
    pub cpu_s: f64,
}

/// What `--published-store` measured.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct PublishedResult {
    pub points: u64,
    pub files: usize,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    /// From the first job's submission to the store published.
    pub build_and_publish_s: f64,
    /// Bytes of the published objects.
    pub published_bytes: u64,
    /// The measured job, from its submission to its last frame fetched.
    pub job_s: f64,
    pub daemon: ProcessCpu,
    pub workers: Vec<ProcessCpu>,
    /// The daemon's CPU over the workers' summed.
    pub daemon_share: f64,
    /// Node records the daemon served during the measured job.
    pub records_served: f64,
    /// Frames identical to the local render's, of `frames`.
    pub identical_frames: usize,
    pub load_average_before: Option<f64>,
    pub load_average_after: Option<f64>,
}

/// Runs `--published-store`, stopping every process and removing the scratch folder after.
pub fn measure(
    options: &PublishedOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<PublishedResult, ObjectStorageError> {
    let mut log = progress_log("published-store", progress);
    let scratch = scratch_dir(options.scratch_parent.as_deref(), "published-store")?;
    let dir = scratch.path();
    log(format!("published-store: scratch folder {}", dir.display()));
    let tiles = tiles_folder(options, dir, &mut log)?;
    let server = S3Server::start(&options.s3s_fs, &dir.join("s3"), BUCKET)?;
    let farm = Farm {
        options,
        server: &server,
        dir: dir.to_path_buf(),
    };
    let (address, metrics) = (free_address()?, free_address()?);
    let daemon_log = dir.join("serve.log");
    let daemon = farm.daemon(&address, &metrics, &tiles, &daemon_log)?;
    let id = farm.register(&address, &tiles)?;

    let started = Instant::now();
    let builder = farm.worker(&address, "builder")?;
    farm.render_job(&address, &id, 1, (64, 48), "build")?;
    wait_for_published(&daemon_log, &daemon)?;
    let build_and_publish_s = started.elapsed().as_secs_f64();
    drop(builder);
    let published = server.stored_files(BUCKET);
    let published_bytes = published
        .iter()
        .filter_map(|path| std::fs::metadata(path).ok())
        .map(|m| m.len())
        .sum();
    log(format!(
        "published-store: built and published in {build_and_publish_s:.1} s, {} objects, \
         {published_bytes} bytes",
        published.len()
    ));

    let workers = (0..PUBLISHED_WORKERS)
        .map(|i| farm.worker(&address, &format!("reader-{i}")))
        .collect::<Result<Vec<_>, _>>()?;
    std::thread::sleep(WORKER_SETTLE);
    for path in &published {
        drop_page_cache(path)?;
    }
    let served_before = scrape(&metrics, RECORDS_SERVED)?;
    let load_average_before = load_average();
    let daemon_before = cpu_seconds(daemon.id())?;
    let workers_before = workers
        .iter()
        .map(|w| cpu_seconds(w.id()))
        .collect::<Result<Vec<_>, _>>()?;
    let job_started = Instant::now();
    let size = (options.width, options.height);
    let out = farm.render_job(&address, &id, options.frames, size, "published")?;
    let job_s = job_started.elapsed().as_secs_f64();
    let daemon_cpu = cpu_seconds(daemon.id())? - daemon_before;
    let worker_cpus: Vec<ProcessCpu> = workers
        .iter()
        .zip(workers_before)
        .enumerate()
        .map(|(i, (w, before))| {
            Ok(ProcessCpu {
                name: format!("reader-{i}"),
                cpu_s: cpu_seconds(w.id())? - before,
            })
        })
        .collect::<Result<_, ObjectStorageError>>()?;
    let load_average_after = load_average();
    let records_served = scrape(&metrics, RECORDS_SERVED)? - served_before;
    let workers_cpu: f64 = worker_cpus.iter().map(|w| w.cpu_s).sum();
    log(format!(
        "published-store: {} frames in {job_s:.1} s; daemon {daemon_cpu:.2} s of CPU, workers \
         {workers_cpu:.2} s; {records_served} records served by the daemon",
        options.frames
    ));
    drop(workers);
    drop(daemon);
    // The published copy and the daemon's own are not read again: removed before the local
    // render builds its store, a campaign of a billion points needs its store on disk twice at
    // the most, not three times.
    drop(server);
    for folder in [dir.join("s3"), dir.join("daemon")] {
        std::fs::remove_dir_all(&folder).map_err(|e| io(&folder, e))?;
    }

    let local = local_render(options, dir, &tiles, size)?;
    let identical_frames = identical_frames(&out, &local, options.frames)?;
    log(format!(
        "published-store: {identical_frames} of {} frames identical to the local render",
        options.frames
    ));
    Ok(PublishedResult {
        points: options.points,
        files: options.files,
        frames: options.frames,
        width: options.width,
        height: options.height,
        build_and_publish_s,
        published_bytes,
        job_s,
        daemon: ProcessCpu {
            name: "daemon".into(),
            cpu_s: daemon_cpu,
        },
        daemon_share: daemon_cpu / workers_cpu,
        workers: worker_cpus,
        records_served,
        identical_frames,
        load_average_before,
        load_average_after,
    })
}

/// The campaign's tiles: kept in `options.inputs` (written there once, reused after) or
/// written into the scratch folder.
fn tiles_folder(
    options: &PublishedOptions,
    scratch: &Path,
    log: &mut dyn FnMut(String),
) -> Result<PathBuf, ObjectStorageError> {
    let name = format!(
        "campaign-{}-{}-{}",
        options.points, options.files, options.seed
    );
    let folder = match &options.inputs {
        Some(inputs) => inputs.join(&name),
        None => scratch.join(&name),
    };
    let done = folder.with_extension("written");
    if done.is_file() {
        log(format!("published-store: reusing {}", folder.display()));
        return Ok(folder);
    }
    let _ = std::fs::remove_dir_all(&folder);
    std::fs::create_dir_all(&folder).map_err(|e| io(&folder, e))?;
    let started = Instant::now();
    let files = write_campaign(&folder, options.points, options.files, options.seed, false)?;
    std::fs::write(&done, b"").map_err(|e| io(&done, e))?;
    log(format!(
        "published-store: {} points written in {} LAZ tiles in {:.1} s",
        files.points,
        files.laz.len(),
        started.elapsed().as_secs_f64()
    ));
    Ok(folder)
}

/// The processes of one run, and where they keep their files.
struct Farm<'a> {
    options: &'a PublishedOptions,
    server: &'a S3Server,
    dir: PathBuf,
}

impl Farm<'_> {
    /// The `pointfarm` binary with the S3 server's endpoint and credentials.
    fn pointfarm(&self) -> Command {
        let mut command = Command::new(&self.options.pointfarm);
        command.envs(self.server.environment());
        command
    }

    fn daemon(
        &self,
        address: &str,
        metrics: &str,
        tiles: &Path,
        log: &Path,
    ) -> Result<Killed, ObjectStorageError> {
        let data = self.dir.join("daemon");
        let mut command =
            serve_command(self.pointfarm(), address, &data, log).map_err(|e| io(log, e))?;
        let child = command
            .arg("--data-root")
            .arg(tiles)
            .args(["--no-embedded-worker", "--store-url", STORE_URL])
            .args(["--metrics-listen", metrics])
            .spawn()
            .map_err(|e| ObjectStorageError::Setup(format!("starting the daemon: {e}")))?;
        let daemon = Killed(child);
        if !listens_within(address, START_TIMEOUT) {
            return Err(ObjectStorageError::Setup(format!(
                "the daemon did not listen on {address}: {}",
                log_tail(log)
            )));
        }
        Ok(daemon)
    }

    /// Registers the tiles' folder; the dataset's id.
    fn register(&self, address: &str, tiles: &Path) -> Result<String, ObjectStorageError> {
        let mut command = self.pointfarm();
        command
            .args(["dataset", "register", "--json", "--server", address])
            .arg(tiles);
        let output = run(command, "dataset register")?;
        let dataset: serde_json::Value = serde_json::from_slice(&output)
            .map_err(|e| ObjectStorageError::Setup(format!("dataset register's JSON: {e}")))?;
        dataset["id"]
            .as_str()
            .map(str::to_owned)
            .ok_or_else(|| ObjectStorageError::Setup(format!("no dataset id in {dataset}")))
    }

    fn worker(&self, address: &str, name: &str) -> Result<Killed, ObjectStorageError> {
        let cache = self.dir.join(name);
        let log = self.dir.join(format!("{name}.log"));
        let log_file = std::fs::File::create(&log).map_err(|e| io(&log, e))?;
        let child = self
            .pointfarm()
            .args(["worker", "--server", address, "--name", name, "--cache-dir"])
            .arg(&cache)
            .stdout(Stdio::null())
            .stderr(log_file)
            .spawn()
            .map_err(|e| ObjectStorageError::Setup(format!("starting worker {name}: {e}")))?;
        Ok(Killed(child))
    }

    /// A turntable of `frames` frames of dataset `id` through the daemon, its frames fetched
    /// into the folder `name`, which is returned.
    fn render_job(
        &self,
        address: &str,
        id: &str,
        frames: usize,
        (width, height): (u32, u32),
        name: &str,
    ) -> Result<PathBuf, ObjectStorageError> {
        let out = self.dir.join(name);
        let mut command = self.pointfarm();
        command
            .args(["render", "--server", address, "--dataset", id])
            .args(turntable(frames, width, height))
            .arg("--out")
            .arg(&out);
        run(command, "render --server")?;
        Ok(out)
    }
}

/// The same turntable rendered here from the tiles into `dir/local`, its store built in a cache
/// of its own.
fn local_render(
    options: &PublishedOptions,
    dir: &Path,
    tiles: &Path,
    (width, height): (u32, u32),
) -> Result<PathBuf, ObjectStorageError> {
    let out = dir.join("local");
    let mut command = Command::new(&options.pointfarm);
    command
        .arg("render")
        .arg(tiles)
        .args(turntable(options.frames, width, height))
        .arg("--cache-dir")
        .arg(dir.join("local-cache"))
        .arg("--out")
        .arg(&out);
    run(command, "render")?;
    Ok(out)
}

/// The turntable options of every job and render of the benchmark.
fn turntable(frames: usize, width: u32, height: u32) -> Vec<String> {
    vec![
        "--turntable".into(),
        frames.to_string(),
        "--size".into(),
        format!("{width}x{height}"),
        "--lod-error".into(),
        LOD_ERROR.into(),
    ]
}

/// A child process killed and reaped when dropped.
struct Killed(Child);

impl Killed {
    fn id(&self) -> u32 {
        self.0.id()
    }
}

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Runs `command` to its end; its standard output, or an error with its standard error.
fn run(mut command: Command, what: &str) -> Result<Vec<u8>, ObjectStorageError> {
    let output = command
        .stdin(Stdio::null())
        .output()
        .map_err(|e| ObjectStorageError::Setup(format!("running pointfarm {what}: {e}")))?;
    if !output.status.success() {
        return Err(ObjectStorageError::Setup(format!(
            "pointfarm {what} failed ({}): {}",
            output.status,
            String::from_utf8_lossy(&output.stderr)
        )));
    }
    Ok(output.stdout)
}

/// Waits until the daemon's log says a store was published.
fn wait_for_published(log: &Path, daemon: &Killed) -> Result<(), ObjectStorageError> {
    let started = Instant::now();
    loop {
        let text = std::fs::read_to_string(log).unwrap_or_default();
        if text.contains("store published") {
            return Ok(());
        }
        if started.elapsed() > PUBLISH_TIMEOUT
            || !Path::new(&format!("/proc/{}", daemon.id())).exists()
        {
            return Err(ObjectStorageError::Setup(format!(
                "the store was not published: {}",
                log_tail(log)
            )));
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// How many of `frames` turntable frames are the same image in both folders.
fn identical_frames(a: &Path, b: &Path, frames: usize) -> Result<usize, ObjectStorageError> {
    let mut same = 0;
    for index in 0..frames {
        let name = format!("frame_{index:05}.png");
        let read = |dir: &Path| {
            let path = dir.join(&name);
            image::open(&path)
                .map(|image| image.to_rgba8())
                .map_err(|e| ObjectStorageError::Setup(format!("{}: {e}", path.display())))
        };
        same += usize::from(read(a)? == read(b)?);
    }
    Ok(same)
}

/// User and system CPU seconds of process `pid` so far, from `/proc/PID/stat`.
fn cpu_seconds(pid: u32) -> Result<f64, ObjectStorageError> {
    let path = format!("/proc/{pid}/stat");
    let stat = std::fs::read_to_string(&path).map_err(|e| io(Path::new(&path), e))?;
    parse_cpu_ticks(&stat)
        .map(|ticks| ticks as f64 / clock_ticks_per_second())
        .ok_or_else(|| ObjectStorageError::Setup(format!("{path}: no CPU times in {stat:?}")))
}

/// `utime + stime` of a `/proc/PID/stat` line, in clock ticks: the 14th and 15th fields,
/// counted after the command's name, which may hold spaces and parentheses.
fn parse_cpu_ticks(stat: &str) -> Option<u64> {
    let after_name = &stat[stat.rfind(')')? + 1..];
    let fields: Vec<&str> = after_name.split_whitespace().collect();
    let utime: u64 = fields.get(11)?.parse().ok()?;
    let stime: u64 = fields.get(12)?.parse().ok()?;
    Some(utime + stime)
}

fn clock_ticks_per_second() -> f64 {
    rustix::param::clock_ticks_per_second() as f64
}

/// The value of the Prometheus counter `name` at `address`'s `/metrics` (0 when absent).
fn scrape(address: &str, name: &str) -> Result<f64, ObjectStorageError> {
    let failed =
        |e: std::io::Error| ObjectStorageError::Setup(format!("metrics at {address}: {e}"));
    let mut stream = TcpStream::connect(address).map_err(failed)?;
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .map_err(failed)?;
    write!(stream, "GET /metrics HTTP/1.0\r\nHost: {address}\r\n\r\n").map_err(failed)?;
    let mut text = String::new();
    stream.read_to_string(&mut text).map_err(failed)?;
    Ok(text
        .lines()
        .filter(|line| line.starts_with(name))
        .filter_map(|line| line.rsplit(' ').next()?.parse::<f64>().ok())
        .sum())
}

fn free_address() -> Result<String, ObjectStorageError> {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|listener| listener.local_addr())
        .map(|address| address.to_string())
        .map_err(|e| ObjectStorageError::Setup(format!("a free loopback port: {e}")))
}

fn log_tail(log: &Path) -> String {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(20)..].join("\n")
}

fn io(path: &Path, error: std::io::Error) -> ObjectStorageError {
    ObjectStorageError::Setup(format!("{}: {error}", path.display()))
}

/// The result as markdown.
pub fn markdown(r: &PublishedResult) -> String {
    let workers: Vec<String> = r
        .workers
        .iter()
        .map(|w| format!("{} {:.2} s", w.name, w.cpu_s))
        .collect();
    format!(
        "{} points in {} LAZ tiles; the store built and published to s3s-fs in {:.1} s \
         ({:.1} MiB); a cold {}-frame {}x{} turntable by {} workers in {:.1} s (load {} before, \
         {} after).\n\n\
         | daemon CPU | workers' CPU | daemon / workers | records the daemon served | frames identical to a local render |\n\
         |---:|---|---:|---:|---:|\n\
         | {:.2} s | {} | {:.2}% | {} | {} of {} |\n",
        r.points,
        r.files,
        r.build_and_publish_s,
        r.published_bytes as f64 / (1u64 << 20) as f64,
        r.frames,
        r.width,
        r.height,
        r.workers.len(),
        r.job_s,
        r.load_average_before.map_or("-".into(), |l| format!("{l:.2}")),
        r.load_average_after.map_or("-".into(), |l| format!("{l:.2}")),
        r.daemon.cpu_s,
        workers.join(", "),
        r.daemon_share * 100.0,
        r.records_served,
        r.identical_frames,
        r.frames,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_ticks_are_read_after_a_name_with_spaces_and_parentheses() {
        let stat = "4242 (pointfarm (w 1)) S 1 4242 4242 0 -1 4194560 500 0 0 0 \
                    731 69 0 0 20 0 9 0 100 1000 100 18446744073709551615";
        assert_eq!(parse_cpu_ticks(stat), Some(800));
        assert_eq!(parse_cpu_ticks("4242 (cut"), None);
    }
}

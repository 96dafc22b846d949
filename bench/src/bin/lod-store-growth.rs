//! A campaign that grows through a real `pointfarm serve`: what making the store of a dataset
//! of `--files` LAZ tiles costs when the daemon grows it from the store of the same tiles less
//! the inner one, against the daemon building it whole. A daemon renders the tiles but the
//! inner one (`pointfarm render --server`: the files uploaded, the store built whole), then all
//! of them (the inner tile uploaded, the dataset composed, its store grown); a second daemon,
//! fresh, renders all of them (built whole). The times are the daemons' own log lines: `levels
//! of detail built` (a whole build) and `updated the store of` (the copy, the update and the
//! checks; its `update_seconds` is the update alone), so what the client and the upload take
//! is left out. docs/perf/lod-store-update.md has its figures.
//!
//! ```text
//! lod-store-growth --pointfarm PATH [--points N] [--files N] [--rounds N] [--budget-mib N]
//!                  [--dir DIR]
//! ```

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitCode, Stdio};
use std::time::{Duration, Instant};

use pointfarm_bench::campaign::{grid, CampaignFlags, ScratchCampaign};
use pointfarm_bench::cli::{exit_code, parse_flags};
use pointfarm_bench::daemon_log::number_after;

const USAGE: &str = "usage: lod-store-growth --pointfarm PATH [--points N] [--files N] \
                     [--rounds N] [--budget-mib N] [--dir DIR]";
/// The longest a render (its store built or grown) may take.
const RENDER_TIMEOUT: Duration = Duration::from_secs(3600);

struct Args {
    campaign: CampaignFlags,
    rounds: usize,
    pointfarm: Option<PathBuf>,
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    exit_code(
        "lod-store-growth",
        parse(&args).and_then(|args| measure(&args)),
    )
}

fn parse(args: &[String]) -> Result<Args, String> {
    let mut parsed = Args {
        campaign: CampaignFlags::new(21_000_000, 21),
        rounds: 1,
        pointfarm: None,
    };
    parse_flags(args, USAGE, |flag, value| {
        match flag {
            "--rounds" => parsed.rounds = value.number()?.max(1) as usize,
            "--pointfarm" => parsed.pointfarm = Some(value.path()),
            _ => return parsed.campaign.apply(flag, &value),
        }
        Ok(true)
    })?;
    parsed.campaign.check_inner_tile()?;
    if parsed.pointfarm.is_none() {
        return Err(format!("--pointfarm is needed\n{USAGE}"));
    }
    Ok(parsed)
}

/// A `pointfarm serve` on loopback, its log in a file, stopped when dropped.
struct Serve {
    child: Child,
    address: String,
    log: PathBuf,
}

impl Serve {
    fn start(pointfarm: &Path, data: &Path, budget_mib: u64) -> Result<Self, String> {
        std::fs::create_dir_all(data).map_err(|e| e.to_string())?;
        let address = TcpListener::bind("127.0.0.1:0")
            .and_then(|listener| listener.local_addr())
            .map_err(|e| format!("a free loopback port: {e}"))?
            .to_string();
        let log = data.with_extension("log");
        let log_file = std::fs::File::create(&log).map_err(|e| e.to_string())?;
        let child = Command::new(pointfarm)
            .args(["serve", "--listen", &address, "--data-dir"])
            .arg(data)
            .arg(format!("--store-memory-budget={budget_mib}MiB"))
            .env("RUST_LOG", "warn,pointfarm=info")
            .env("NO_COLOR", "1")
            .stdout(Stdio::null())
            .stderr(log_file)
            .spawn()
            .map_err(|e| format!("starting {}: {e}", pointfarm.display()))?;
        let serve = Self {
            child,
            address,
            log,
        };
        let started = Instant::now();
        while std::net::TcpStream::connect(&serve.address).is_err() {
            if started.elapsed() > Duration::from_secs(60) {
                return Err(format!("the daemon did not listen:\n{}", serve.log_text()));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        Ok(serve)
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Renders `tiles` through this daemon, from levels of detail, into `out`.
    fn render(&self, pointfarm: &Path, tiles: &Path, out: &Path) -> Result<(), String> {
        let output = Command::new(pointfarm)
            .arg("render")
            .arg(tiles)
            .arg("--out")
            .arg(out)
            .args(["--size=200x150", "--lod-error=0"])
            .arg(format!("--server=http://{}", self.address))
            .output()
            .map_err(|e| e.to_string())?;
        if !output.status.success() {
            return Err(format!(
                "render of {} failed: {}\n--- daemon:\n{}",
                tiles.display(),
                String::from_utf8_lossy(&output.stderr),
                self.log_text()
            ));
        }
        Ok(())
    }

    /// The numbers `fields` of the daemon's first line saying `message`, waited for.
    fn said<const N: usize>(&self, message: &str, fields: [&str; N]) -> Result<[f64; N], String> {
        let started = Instant::now();
        loop {
            let log = self.log_text();
            if let Some(line) = log.lines().find(|l| l.contains(message)) {
                let mut numbers = [0.0; N];
                for (number, field) in numbers.iter_mut().zip(fields) {
                    *number = number_after(line, &format!(" {field}="))
                        .ok_or_else(|| format!("no {field} in: {line}"))?;
                }
                return Ok(numbers);
            }
            if started.elapsed() > RENDER_TIMEOUT {
                return Err(format!("the daemon never said {message:?}:\n{log}"));
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

impl Drop for Serve {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A folder of hard links to `tiles`.
fn day(folder: &Path, tiles: &[&PathBuf]) -> Result<PathBuf, String> {
    std::fs::create_dir_all(folder).map_err(|e| e.to_string())?;
    for tile in tiles {
        let name = tile.file_name().ok_or("a tile without a name")?;
        std::fs::hard_link(tile, folder.join(name)).map_err(|e| e.to_string())?;
    }
    Ok(folder.to_owned())
}

fn load() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}

fn measure(args: &Args) -> Result<(), String> {
    let pointfarm = args.pointfarm.as_deref().ok_or(USAGE)?;
    let ScratchCampaign {
        scratch, written, ..
    } = args.campaign.write("lod-store-growth")?;
    let (rows, cols) = grid(args.campaign.files);
    let inner = (rows / 2) * cols + cols / 2;
    let all: Vec<&PathBuf> = written.laz.iter().collect();
    let before: Vec<&PathBuf> = (0..all.len())
        .filter(|&i| i != inner)
        .map(|i| all[i])
        .collect();
    let dir = scratch.path();
    let (day1, day2) = (
        day(&dir.join("day1"), &before)?,
        day(&dir.join("day2"), &all)?,
    );
    println!(
        "{} points in {} LAZ tiles ({rows} x {cols}); tile {inner} added; daemon {}",
        written.points,
        all.len(),
        pointfarm.display()
    );
    let budget = args.campaign.budget_mib;
    for round in 1..=args.rounds {
        let data = dir.join(format!("grown-{round}"));
        let serve = Serve::start(pointfarm, &data, budget)?;
        serve.render(pointfarm, &day1, &dir.join("day1.png"))?;
        let [before_whole] = serve.said("levels of detail built", ["seconds"])?;
        let load_before = load();
        serve.render(pointfarm, &day2, &dir.join("day2.png"))?;
        let fields = [
            "seconds",
            "update_seconds",
            "regions_rebuilt",
            "regions_kept",
        ];
        let [grown, update, rebuilt, kept] = serve.said("updated the store of", fields)?;
        let [copy] = serve.said("copied the earlier store to update", ["seconds"])?;
        let load_grown = load();
        drop(serve);
        let _ = std::fs::remove_dir_all(&data);

        let data = dir.join(format!("whole-{round}"));
        let serve = Serve::start(pointfarm, &data, budget)?;
        serve.render(pointfarm, &day2, &dir.join("whole.png"))?;
        let [whole] = serve.said("levels of detail built", ["seconds"])?;
        let load_whole = load();
        drop(serve);
        let _ = std::fs::remove_dir_all(&data);
        println!(
            "round {round}: whole build of {} tiles {before_whole:.2} s; of {} tiles \
             {whole:.2} s (load {load_whole}); store of {} tiles grown {grown:.2} s (copy \
             {copy:.2} s, update alone {update:.2} s, {rebuilt} regions rebuilt, {kept} kept; load {load_before} \
             before, {load_grown} after): {:.1}% of the whole build",
            before.len(),
            all.len(),
            all.len(),
            100.0 * grown / whole
        );
    }
    Ok(())
}

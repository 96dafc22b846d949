//! A real `pointfarm serve` on loopback for the figures taken through a daemon: started with
//! its data in a folder of its own, its log in a file the figures read, stopped when dropped.

use std::net::{TcpListener, TcpStream, ToSocketAddrs};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::daemon_log::number_after;

/// The longest a render (its store built or grown) may take.
const RENDER_TIMEOUT: Duration = Duration::from_secs(3600);

/// How long a daemon may take to listen.
const START_TIMEOUT: Duration = Duration::from_secs(60);

/// `command`, a `pointfarm` binary, made `pointfarm serve` listening on `address` with its data
/// in `data`, logging at info level without colors to the file `log` (made here); the
/// caller adds the options of its own and starts it.
pub(crate) fn serve_command(
    mut command: Command,
    address: &str,
    data: &Path,
    log: &Path,
) -> std::io::Result<Command> {
    let log_file = std::fs::File::create(log)?;
    command
        .args(["serve", "--listen", address, "--data-dir"])
        .arg(data)
        .env("RUST_LOG", "warn,pointfarm=info")
        .env("NO_COLOR", "1")
        .stdout(Stdio::null())
        .stderr(log_file);
    Ok(command)
}

/// Whether something listens on `address` within `timeout`, tried every 50 ms: the start of
/// a daemon, or of the S3 server.
pub(crate) fn listens_within(address: impl ToSocketAddrs + Copy, timeout: Duration) -> bool {
    let started = Instant::now();
    while TcpStream::connect(address).is_err() {
        if started.elapsed() > timeout {
            return false;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    true
}

/// A `pointfarm serve` on loopback, its log in a file, stopped when dropped.
pub struct Serve {
    child: Child,
    address: String,
    log: PathBuf,
}

impl Serve {
    /// Starts `pointfarm serve` with its data in `data` and its stores' memory budget.
    pub fn start(pointfarm: &Path, data: &Path, budget_mib: u64) -> Result<Self, String> {
        Self::start_with(pointfarm, data, budget_mib, &[])
    }

    /// Starts `pointfarm serve` as [`Serve::start`] with the folder `tiles` as its data root,
    /// and registers the tiles there: a render of them through it then finds them as its
    /// dataset and uploads nothing, so a campaign takes its disk once.
    pub fn start_in_place(
        pointfarm: &Path,
        data: &Path,
        budget_mib: u64,
        tiles: &Path,
    ) -> Result<Self, String> {
        let root = format!("--data-root={}", tiles.display());
        let serve = Self::start_with(pointfarm, data, budget_mib, &[&root])?;
        let mut register = Command::new(pointfarm);
        register.args(["dataset", "register"]).arg(tiles);
        serve.run(register, &format!("registering {}", tiles.display()))?;
        Ok(serve)
    }

    fn start_with(
        pointfarm: &Path,
        data: &Path,
        budget_mib: u64,
        options: &[&str],
    ) -> Result<Self, String> {
        std::fs::create_dir_all(data).map_err(|e| e.to_string())?;
        let address = TcpListener::bind("127.0.0.1:0")
            .and_then(|listener| listener.local_addr())
            .map_err(|e| format!("a free loopback port: {e}"))?
            .to_string();
        let log = data.with_extension("log");
        let child = serve_command(Command::new(pointfarm), &address, data, &log)
            .and_then(|mut command| {
                let budget = format!("--store-memory-budget={budget_mib}MiB");
                command.arg(budget).args(options).spawn()
            })
            .map_err(|e| format!("starting {}: {e}", pointfarm.display()))?;
        let serve = Self {
            child,
            address,
            log,
        };
        if !listens_within(serve.address.as_str(), START_TIMEOUT) {
            return Err(format!("the daemon did not listen:\n{}", serve.log_text()));
        }
        Ok(serve)
    }

    /// Everything the daemon logged so far.
    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Renders `tiles` through this daemon into `out`, with the render's further `args`.
    pub fn render(
        &self,
        pointfarm: &Path,
        tiles: &Path,
        out: &Path,
        args: &[&str],
    ) -> Result<(), String> {
        let mut render = Command::new(pointfarm);
        render
            .arg("render")
            .arg(tiles)
            .arg("--out")
            .arg(out)
            .args(args);
        self.run(render, &format!("render of {}", tiles.display()))
    }

    /// Runs the `pointfarm` `command` against this daemon to its end; an error saying `what`
    /// failed, with the command's and the daemon's words, otherwise.
    fn run(&self, mut command: Command, what: &str) -> Result<(), String> {
        let output = command
            .arg(format!("--server=http://{}", self.address))
            .output()
            .map_err(|e| e.to_string())?;
        if !output.status.success() {
            return Err(format!(
                "{what} failed: {}\n--- daemon:\n{}",
                String::from_utf8_lossy(&output.stderr),
                self.log_text()
            ));
        }
        Ok(())
    }

    /// The numbers `fields` of the daemon's first line saying `message`, waited for.
    pub fn said<const N: usize>(
        &self,
        message: &str,
        fields: [&str; N],
    ) -> Result<[f64; N], String> {
        let line = self.waited_for(message, |_| true)?;
        let mut numbers = [0.0; N];
        for (number, field) in numbers.iter_mut().zip(fields) {
            *number = number_after(&line, &format!(" {field}="))
                .ok_or_else(|| format!("no {field} in: {line}"))?;
        }
        Ok(numbers)
    }

    /// Seconds from the daemon's first line saying `from` to its first after it saying `to`,
    /// by their timestamps, waited for.
    pub fn seconds_between(&self, from: &str, to: &str) -> Result<f64, String> {
        let start = clock_seconds(&self.waited_for(from, |_| true)?)?;
        let mut after = false;
        let end = self.waited_for(to, |line| {
            after |= line.contains(from);
            after
        })?;
        Ok(clock_seconds(&end)? - start)
    }

    /// The daemon's first line saying `message` among those `considered`, waited for.
    fn waited_for(
        &self,
        message: &str,
        mut considered: impl FnMut(&str) -> bool,
    ) -> Result<String, String> {
        let started = Instant::now();
        loop {
            let log = self.log_text();
            if let Some(line) = log
                .lines()
                .filter(|l| considered(l))
                .find(|l| l.contains(message))
            {
                return Ok(line.to_owned());
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

/// The seconds into its day of a log line's timestamp (`2026-01-02T03:04:05.678Z`).
fn clock_seconds(line: &str) -> Result<f64, String> {
    let clock = line
        .split_once('T')
        .and_then(|(_, rest)| rest.split_once('Z'))
        .map(|(clock, _)| clock)
        .ok_or_else(|| format!("no timestamp in: {line}"))?;
    let parts: Vec<f64> = clock
        .split(':')
        .map(|p| p.parse::<f64>().map_err(|e| format!("{e} in: {line}")))
        .collect::<Result<_, _>>()?;
    match parts[..] {
        [h, m, s] => Ok(h * 3600.0 + m * 60.0 + s),
        _ => Err(format!("no timestamp in: {line}")),
    }
}

/// The machine's load averages over 1, 5 and 15 minutes.
pub fn load() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::clock_seconds;

    #[test]
    fn a_log_line_timestamp_is_read_as_seconds_into_its_day() {
        let line = "2026-01-02T03:04:05.678Z  INFO job submitted";
        let seconds = clock_seconds(line).expect("a timestamp");
        assert!((seconds - (3.0 * 3600.0 + 4.0 * 60.0 + 5.678)).abs() < 1e-9);
        assert!(clock_seconds("no time here").is_err());
    }
}

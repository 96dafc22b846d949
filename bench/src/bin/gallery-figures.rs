//! Renders files with `pointfarm render`'s default flags and prints, per file, how the frame
//! shows its subject (see `pointfarm_bench::frame_figures`) as a markdown table: the figures of
//! the defaults of an older binary beside the current one's, and what the current defaults cost
//! with `--shading none` and `--shading edl`. `deploy/gallery-figures.sh` runs it; the table in
//! docs/gallery.md is its output.
//!
//! ```text
//! gallery-figures --pointfarm PATH [--before PATH] [--size WxH] [--runs N] [--images DIR] INPUT...
//! ```
//!
//! An INPUT folder stands for its `.las`/`.laz` files (not its subfolders), in name order.

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode};
use std::time::Instant;

use pointfarm_bench::frame_figures::{closing_radius, frame_figures, Figures};
use pointfarm_render::raster::DEFAULT_BACKGROUND;
use serde_json::Value;

struct Args {
    pointfarm: PathBuf,
    before: Option<PathBuf>,
    size: String,
    runs: usize,
    images: Option<PathBuf>,
    inputs: Vec<PathBuf>,
}

const USAGE: &str = "usage: gallery-figures --pointfarm PATH [--before PATH] [--size WxH] \
                     [--runs N] [--images DIR] INPUT...";

fn parse_args() -> Result<Args, String> {
    let mut args = Args {
        pointfarm: PathBuf::new(),
        before: None,
        size: "640x360".into(),
        runs: 3,
        images: None,
        inputs: Vec::new(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        let mut value = || {
            it.next()
                .ok_or_else(|| format!("{a} needs a value\n{USAGE}"))
        };
        match a.as_str() {
            "--pointfarm" => args.pointfarm = value()?.into(),
            "--before" => args.before = Some(value()?.into()),
            "--size" => args.size = value()?,
            "--runs" => {
                args.runs = value()?.parse().map_err(|e| format!("--runs: {e}"))?;
                if args.runs == 0 {
                    return Err("--runs must be at least 1".into());
                }
            }
            "--images" => args.images = Some(value()?.into()),
            "-h" | "--help" => return Err(USAGE.into()),
            _ if a.starts_with("--") => return Err(format!("unknown option {a}\n{USAGE}")),
            _ => args.inputs.push(a.into()),
        }
    }
    if args.pointfarm.as_os_str().is_empty() || args.inputs.is_empty() {
        return Err(USAGE.into());
    }
    Ok(args)
}

/// The files an input stands for.
fn expand(input: &Path) -> Result<Vec<PathBuf>, String> {
    if !input.is_dir() {
        return Ok(vec![input.to_path_buf()]);
    }
    let entries = std::fs::read_dir(input).map_err(|e| format!("{}: {e}", input.display()))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| e.eq_ignore_ascii_case("las") || e.eq_ignore_ascii_case("laz"))
        })
        .collect();
    files.sort();
    Ok(files)
}

/// One `render` run: its JSON object, its wall time and its frame's figures.
struct Render {
    json: Value,
    wall_ms: f64,
    figures: Figures,
}

impl Render {
    fn stage_ms(&self, stage: &str) -> f64 {
        self.json["timingsMs"][stage].as_f64().unwrap_or(0.0)
    }

    /// Every stage of the frame, from upload to encode: not the process's start, the file's
    /// reading or the adapter's creation, which do not depend on the options.
    fn stages_ms(&self) -> f64 {
        self.json["timingsMs"]
            .as_object()
            .map(|t| t.values().filter_map(Value::as_f64).sum())
            .unwrap_or(0.0)
    }
}

fn render(
    binary: &Path,
    file: &Path,
    out: &Path,
    size: &str,
    extra: &[&str],
) -> Result<Render, String> {
    let start = Instant::now();
    let output = Command::new(binary)
        .arg("render")
        .arg(file)
        .arg("--out")
        .arg(out)
        .args(["--size", size, "--json", "--local"])
        .args(extra)
        .output()
        .map_err(|e| format!("{}: {e}", binary.display()))?;
    let wall_ms = start.elapsed().as_secs_f64() * 1000.0;
    if !output.status.success() {
        let stderr = String::from_utf8_lossy(&output.stderr);
        let last = stderr
            .lines()
            .rev()
            .find(|l| !l.trim().is_empty())
            .unwrap_or("no message");
        return Err(format!("failed: {}", last.trim()));
    }
    let stdout = String::from_utf8_lossy(&output.stdout);
    let json = stdout
        .lines()
        .rev()
        .find_map(|l| serde_json::from_str::<Value>(l).ok())
        .ok_or("no JSON object on standard output")?;
    let image = image::open(out)
        .map_err(|e| format!("{}: {e}", out.display()))?
        .to_rgba8();
    let figures = frame_figures(&image, DEFAULT_BACKGROUND);
    Ok(Render {
        json,
        wall_ms,
        figures,
    })
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        (values[n / 2 - 1] + values[n / 2]) / 2.0
    }
}

fn pct(v: f64) -> String {
    format!("{:.0}%", v * 100.0)
}

/// Box, centre, lit share and wall time of a render, or its failure in the first cell.
fn figure_cells(r: &Result<Render, String>) -> [String; 4] {
    match r {
        Ok(r) => {
            let f = &r.figures;
            let span = f
                .span()
                .map_or("empty".into(), |(w, h)| format!("{} × {}", pct(w), pct(h)));
            let centre = f
                .centre()
                .map_or("–".into(), |(x, y)| format!("{}, {}", pct(x), pct(y)));
            // The silhouette's size tells a closed surface from a few isolated points, which
            // are their own silhouette and so fully lit.
            let lit = f.lit_share().map_or("–".into(), |l| {
                let px = match f.silhouette {
                    n if n < 10_000 => format!("{n}"),
                    n => format!("{:.0}k", n as f64 / 1000.0),
                };
                format!("{} of {px} px", pct(l))
            });
            [span, centre, lit, format!("{:.0}", r.wall_ms)]
        }
        Err(e) => [e.replace('|', "\\|"), "–".into(), "–".into(), "–".into()],
    }
}

/// Medians over `runs` renders with `--shading MODE`: all stages, and the shade stage alone.
fn shading_cost(
    binary: &Path,
    file: &Path,
    out: &Path,
    size: &str,
    mode: &str,
    runs: usize,
) -> Result<(f64, f64), String> {
    let mut stages = Vec::new();
    let mut shade = Vec::new();
    for _ in 0..runs {
        let r = render(binary, file, out, size, &["--shading", mode])?;
        stages.push(r.stages_ms());
        shade.push(r.stage_ms("shade"));
    }
    Ok((median(stages), median(shade)))
}

fn run(args: &Args) -> Result<(), String> {
    let mut files = Vec::new();
    for input in &args.inputs {
        files.extend(expand(input)?);
    }
    let scratch;
    let images = match &args.images {
        Some(dir) => dir.clone(),
        None => {
            scratch = tempfile::tempdir().map_err(|e| e.to_string())?;
            scratch.path().to_path_buf()
        }
    };
    std::fs::create_dir_all(&images).map_err(|e| format!("{}: {e}", images.display()))?;
    let height: u32 = args
        .size
        .split_once('x')
        .and_then(|(_, h)| h.parse().ok())
        .ok_or_else(|| format!("--size {}: not WxH", args.size))?;
    let [r, g, b, _] = DEFAULT_BACKGROUND;
    println!(
        "{} files rendered with default flags at {}; drawn = not exactly the default background \
         #{r:02x}{g:02x}{b:02x}; silhouette closed with a disc of radius {} px; box and centre as \
         fractions of the frame's width × height; lit: drawn over silhouette pixels, of a silhouette \
         of so many pixels; ms: wall time of the render command; none/edl: \
         median over {} runs of the frame's stages (upload to encode), and of its shade stage.\n",
        files.len(),
        args.size,
        closing_radius(height),
        args.runs
    );
    let mut header = vec!["file", "points drawn", "size"];
    if args.before.is_some() {
        header.extend(["before: box", "centre", "lit", "ms"]);
    }
    header.extend([
        "after: box",
        "centre",
        "lit",
        "ms",
        "none ms",
        "edl ms",
        "edl shade ms",
    ]);
    println!("| {} |", header.join(" | "));
    println!("|{}", "---|".repeat(header.len()));
    let mut labels: Vec<String> = Vec::new();
    for file in &files {
        let name = file
            .file_name()
            .map_or("?".into(), |n| n.to_string_lossy().into_owned());
        let same = labels
            .iter()
            .filter(|l| l.split(" (").next() == Some(name.as_str()))
            .count();
        let label = if same == 0 {
            name.clone()
        } else {
            format!("{name} ({})", same + 1)
        };
        let stem = label.replace([' ', '(', ')'], "");
        labels.push(label.clone());
        eprintln!("gallery-figures: {}", file.display());
        let after = render(
            &args.pointfarm,
            file,
            &images.join(format!("{stem}.after.png")),
            &args.size,
            &[],
        );
        let mut cells = vec![format!("`{label}`")];
        match &after {
            Ok(r) => {
                cells.push(
                    r.json["pointsRendered"]
                        .as_u64()
                        .map_or("?".into(), |p| p.to_string()),
                );
                cells.push(format!("{}x{}", r.figures.width, r.figures.height));
            }
            Err(_) => cells.extend(["–".into(), "–".into()]),
        }
        if let Some(before) = &args.before {
            let out = images.join(format!("{stem}.before.png"));
            cells.extend(figure_cells(&render(before, file, &out, &args.size, &[])));
        }
        cells.extend(figure_cells(&after));
        let timing_out = images.join(format!("{stem}.timing.png"));
        for mode in ["none", "edl"] {
            match shading_cost(
                &args.pointfarm,
                file,
                &timing_out,
                &args.size,
                mode,
                args.runs,
            ) {
                Ok((stages, shade)) => {
                    cells.push(format!("{stages:.1}"));
                    if mode == "edl" {
                        cells.push(format!("{shade:.1}"));
                    }
                }
                Err(_) => {
                    cells.push("–".into());
                    if mode == "edl" {
                        cells.push("–".into());
                    }
                }
            }
        }
        let _ = std::fs::remove_file(&timing_out);
        println!("| {} |", cells.join(" | "));
    }
    Ok(())
}

fn main() -> ExitCode {
    let result = parse_args().and_then(|args| run(&args));
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("gallery-figures: {e}");
            ExitCode::FAILURE
        }
    }
}

//! `pointfarm info`: what LAS/LAZ files hold, before rendering them, as `lasinfo` would say
//! it: header facts, CRS, attributes, and (unless `--no-points`) the points read once in a
//! stream for their classes, returns, intensity and colour. Every file is reported; one that
//! cannot be read is an error naming it, and the command then fails after the others.
//! Text here, JSON in `info_json.rs`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use pointfarm_render::classification;
use pointfarm_render::cloud::{ColorSource, WorldBounds};
use pointfarm_render::ingest::{
    dataset_files, Crs, FileInfo, IngestError, PointSummary, GEOTIFF_USER_DEFINED,
};

#[derive(Args)]
pub struct InfoArgs {
    /// LAS/LAZ files, or folders whose .las and .laz files (in subfolders too) are each
    /// reported.
    #[arg(required = true, value_name = "INPUT")]
    inputs: Vec<PathBuf>,
    /// Print one JSON document (`files` and `summary`) instead of text.
    #[arg(long)]
    json: bool,
    /// Only what the header and records say: do not read the points (fast on huge files;
    /// no classes, returns, intensity or colour).
    #[arg(long)]
    no_points: bool,
}

/// One file's report: its header facts and, when read, its points; or why it could not be read.
pub(crate) struct Report {
    pub path: PathBuf,
    pub outcome: Result<(FileInfo, Option<PointSummary>), IngestError>,
}

pub fn run(args: InfoArgs) -> Result<()> {
    let mut reports = Vec::new();
    let mut files = Vec::new();
    // Each input on its own, so a folder without point files does not hide the others.
    for input in &args.inputs {
        match dataset_files(std::slice::from_ref(input)) {
            Ok(found) => files.extend(found),
            Err(error) => {
                let report = Report {
                    path: input.clone(),
                    outcome: Err(error),
                };
                tell(&report, args.json);
                reports.push(report);
            }
        }
    }
    // Without repeats across inputs (a file named and inside a named folder): the files are
    // files now, so this only drops repeats.
    let files = if files.is_empty() {
        files
    } else {
        dataset_files(&files)?
    };
    for path in files {
        let report = inspect(path, !args.no_points);
        tell(&report, args.json);
        reports.push(report);
    }
    let summary = Summary::of(&reports);
    if args.json {
        outln!("{}", crate::info_json::document(&reports, &summary)?);
    } else if reports.len() > 1 {
        print_summary(&summary);
    }
    match summary.failed {
        0 => Ok(()),
        failed => anyhow::bail!("{failed} of {} files could not be read", reports.len()),
    }
}

/// A report as soon as it is made: its error on stderr, its text unless JSON comes at the end.
fn tell(report: &Report, json: bool) {
    if let Err(error) = &report.outcome {
        eprintln!("error: {error}");
    }
    if !json {
        print_report(report);
    }
}

fn inspect(path: PathBuf, read_points: bool) -> Report {
    let outcome = FileInfo::read(&path).and_then(|info| {
        if !read_points {
            return Ok((info, None));
        }
        let bar = crate::progress::counter(info.points, "points", file_name(&info.path));
        let summary = info.read_points(|read| bar.set_position(read));
        bar.finish_and_clear();
        Ok((info, Some(summary?)))
    });
    Report { path, outcome }
}

fn file_name(path: &std::path::Path) -> String {
    path.file_name()
        .map(|name| name.to_string_lossy().into_owned())
        .unwrap_or_else(|| path.display().to_string())
}

/// What the files have together.
pub(crate) struct Summary {
    pub files: usize,
    pub failed: usize,
    /// The points the headers declare.
    pub points: u64,
    /// The union of the header bounds (finite, not inverted ones).
    pub bounds: Option<WorldBounds>,
}

impl Summary {
    fn of(reports: &[Report]) -> Self {
        let infos: Vec<&FileInfo> = reports
            .iter()
            .filter_map(|r| r.outcome.as_ref().ok().map(|(info, _)| info))
            .collect();
        let bounds = infos
            .iter()
            .map(|info| info.bounds)
            .filter(|b| b.min.is_finite() && b.max.is_finite() && b.min.cmple(b.max).all())
            .reduce(|a, b| WorldBounds {
                min: a.min.min(b.min),
                max: a.max.max(b.max),
            });
        Self {
            files: reports.len(),
            failed: reports.len() - infos.len(),
            points: infos.iter().map(|info| info.points).sum(),
            bounds,
        }
    }
}

fn print_report(report: &Report) {
    outln!("{}", report.path.display());
    let Ok((info, points)) = &report.outcome else {
        outln!("  unreadable (see the error above)");
        outln!("");
        return;
    };
    let (major, minor) = info.version;
    outln!(
        "  LAS {major}.{minor}, point format {} ({}-byte records), {}, {} bytes",
        info.point_format,
        info.record_len,
        if info.compressed {
            "LAZ"
        } else {
            "uncompressed"
        },
        info.file_bytes
    );
    let by_return = match info.points_by_return.as_slice() {
        [] => String::new(),
        counts => format!("  (by return: {})", numbered(counts.iter().copied(), 1)),
    };
    outln!("  points      {}{by_return}", info.points);
    outln!("  records     {} VLRs, {} EVLRs", info.vlrs, info.evlrs);
    let decimals = decimals(info.scale.max_element());
    let axes = ["x", "y", "z"];
    for (axis, label) in axes.iter().enumerate() {
        let heading = if axis == 0 { "bounds" } else { "" };
        outln!(
            "  {heading:<11} {label} {:.decimals$} .. {:.decimals$}",
            info.bounds.min[axis],
            info.bounds.max[axis]
        );
    }
    outln!(
        "  scale       {} {} {}",
        info.scale.x,
        info.scale.y,
        info.scale.z
    );
    outln!(
        "  offset      {} {} {}",
        info.offset.x,
        info.offset.y,
        info.offset.z
    );
    outln!("  crs         {}", crs_words(&info.crs));
    outln!("  attributes  {}", attribute_words(info));
    if let Some(points) = points {
        print_points(points, decimals);
    }
    outln!("");
}

fn print_points(points: &PointSummary, decimals: usize) {
    outln!("  points read {}", points.points);
    if let Some(bounds) = points.bounds {
        outln!(
            "  data bounds x {:.decimals$} .. {:.decimals$}, y {:.decimals$} .. {:.decimals$}, z {:.decimals$} .. {:.decimals$}",
            bounds.min.x, bounds.max.x, bounds.min.y, bounds.max.y, bounds.min.z, bounds.max.z
        );
    }
    let classes: Vec<String> = points
        .classes
        .iter()
        .enumerate()
        .filter(|(_, &count)| count > 0)
        .map(|(class, count)| match class_name(class) {
            Some(name) => format!("{class} {name}: {count}"),
            None => format!("{class}: {count}"),
        })
        .collect();
    outln!("  classes     {}", classes.join(", "));
    let returns: Vec<String> = points
        .returns
        .iter()
        .enumerate()
        .filter(|(_, &count)| count > 0)
        .map(|(number, count)| format!("{number}: {count}"))
        .collect();
    outln!("  returns     {}", returns.join(", "));
    if let Some([low, high]) = points.intensity {
        outln!("  intensity   {low} .. {high}");
    }
    outln!("  colour      {}", color_words(points));
}

fn print_summary(summary: &Summary) {
    let unreadable = match summary.failed {
        0 => String::new(),
        failed => format!(" ({failed} unreadable)"),
    };
    outln!(
        "{} files{unreadable}, {} points",
        summary.files,
        summary.points
    );
    if let Some(b) = summary.bounds {
        outln!(
            "  bounds x {:.3} .. {:.3}, y {:.3} .. {:.3}, z {:.3} .. {:.3}",
            b.min.x,
            b.max.x,
            b.min.y,
            b.max.y,
            b.min.z,
            b.max.z
        );
    }
}

/// `first: a, first+1: b, …` for counts numbered from `first`.
fn numbered(counts: impl Iterator<Item = u64>, first: usize) -> String {
    counts
        .enumerate()
        .map(|(i, count)| format!("{}: {count}", i + first))
        .collect::<Vec<_>>()
        .join(", ")
}

/// Decimals that show a coordinate at `scale` (0.01: 2), from 0 to 9.
pub(crate) fn decimals(scale: f64) -> usize {
    if !(scale.is_finite() && scale > 0.0) {
        return 3;
    }
    (-scale.log10() - 1e-9).ceil().clamp(0.0, 9.0) as usize
}

pub(crate) fn crs_words(crs: &Crs) -> String {
    let code = |code: u16| match code {
        GEOTIFF_USER_DEFINED => "user-defined".to_owned(),
        code => format!("EPSG:{code}"),
    };
    match crs {
        Crs::Wkt { name, epsg, .. } => {
            let name = name.as_deref().unwrap_or("unnamed");
            match epsg {
                Some(epsg) => format!("{name} (EPSG:{epsg}, from the WKT record)"),
                None => format!("{name} (from the WKT record)"),
            }
        }
        Crs::GeoTiff(keys) => {
            let mut parts = Vec::new();
            if let Some(projected) = keys.projected {
                parts.push(format!("projected {}", code(projected)));
            }
            if let Some(geographic) = keys.geographic {
                parts.push(format!("geographic {}", code(geographic)));
            }
            if let Some(vertical) = keys.vertical {
                parts.push(format!("vertical {}", code(vertical)));
            }
            if parts.is_empty() {
                "GeoTIFF keys without an EPSG code".to_owned()
            } else {
                format!("{} (from the GeoTIFF keys)", parts.join(", "))
            }
        }
        Crs::Unreadable(reason) => format!("unreadable: {reason}"),
        Crs::None => "none".to_owned(),
    }
}

fn attribute_words(info: &FileInfo) -> String {
    let a = &info.attributes;
    let mut words: Vec<String> = [
        (a.gps_time, "GPS time"),
        (a.rgb, "RGB"),
        (a.nir, "NIR"),
        (a.waveform, "waveform"),
    ]
    .into_iter()
    .filter(|(present, _)| *present)
    .map(|(_, word)| word.to_owned())
    .collect();
    if a.extra_bytes > 0 {
        let names = match a.extra_names.as_slice() {
            [] => String::new(),
            names => format!(": {}", names.join(", ")),
        };
        words.push(format!("{} extra bytes{names}", a.extra_bytes));
    }
    if words.is_empty() {
        "none beyond position, intensity, returns and class".to_owned()
    } else {
        words.join(", ")
    }
}

/// What the colour fields hold, in words.
pub(crate) fn color_words(points: &PointSummary) -> String {
    let Some(rgb) = points.rgb else {
        return "no RGB (rendered from intensity)".to_owned();
    };
    if points.points == 0 {
        return "RGB fields, no points".to_owned();
    }
    if !rgb.varies() {
        let [r, g, b] = rgb.min;
        return if rgb.min == [0; 3] {
            "RGB fields, all zero: no colour information (rendered from intensity)".to_owned()
        } else {
            let shown = if points.intensity.is_some_and(|[_, max]| max > 0) {
                "rendered from intensity"
            } else {
                "rendered in that colour"
            };
            format!(
                "RGB fields, one colour ({r}, {g}, {b}) for every point: no colour information ({shown})"
            )
        };
    }
    let [r, g, b] = rgb.max;
    match rgb.source() {
        Some(ColorSource::Rgb8In16Bit) => format!(
            "RGB, 8-bit values in 16-bit fields (highest {r}, {g}, {b}; rendered as they are)"
        ),
        _ => format!("RGB, 16-bit (highest {r}, {g}, {b})"),
    }
}

/// The ASPRS name of a standard class, by a histogram's index.
pub(crate) fn class_name(class: usize) -> Option<&'static str> {
    u8::try_from(class)
        .ok()
        .and_then(classification::class_name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coordinates_show_the_decimals_of_their_scale() {
        assert_eq!(decimals(0.01), 2);
        assert_eq!(decimals(0.001), 3);
        assert_eq!(decimals(0.00025), 4);
        assert_eq!(decimals(1.0), 0);
        assert_eq!(decimals(0.0), 3);
    }
}

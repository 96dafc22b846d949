//! `pointfarm info`: what LAS/LAZ files hold, before rendering them, as `lasinfo` would say
//! it: header facts, CRS, attributes, a COPC file's octree, and (unless `--no-points`) the points read once in a
//! stream for their classes, returns, intensity and color. Every file is reported; one that
//! cannot be read is an error naming it, and the command then fails after the others.
//! Files here are read here; with `--server`, an input that is no path here is a dataset id
//! whose files the server reads (`DescribeDataset`). Either way a file's report is the API's
//! `FileDescription`, built here by the daemon's own conversion, so the text printed here and
//! `--json` (the API's `DatasetDescription` in its proto3 JSON mapping) read the same for
//! local files and for a server's.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;
use pointfarm_daemon::describe::FileReport;
use pointfarm_daemon::grpc::{
    copc_description, dataset_description, file_description, point_attributes_message,
};
use pointfarm_proto::v1 as pb;
use pointfarm_render::copc::CopcSummary;
use pointfarm_render::ingest::{dataset_files, GEOTIFF_USER_DEFINED};
use pointfarm_render::remote::{ObjectUrl, RemoteClient};
use pointfarm_render::source::describe_tile_url;

use crate::credentials::ClientCredentials;
use crate::remote::{answer, Client};
use crate::url_input::{self, Inputs};

#[derive(Args)]
pub struct InfoArgs {
    /// LAS/LAZ files, or folders whose .las and .laz files (in subfolders too) are each
    /// reported; files by URL (s3://, gs://, az://, http(s)://), or the .las and .laz objects
    /// under a prefix: header and records (and a COPC file's octree), read by range; with
    /// --server, also dataset ids (an input that is no path here).
    #[arg(required = true, value_name = "INPUT")]
    inputs: Vec<PathBuf>,
    /// Print one JSON document, the API's `DatasetDescription` in the proto3 JSON mapping
    /// (`files` and `summary`), instead of text.
    #[arg(long)]
    json: bool,
    /// Only what the header and records say: do not read the points (fast on huge files;
    /// no classes, returns, intensity or color).
    #[arg(long)]
    no_points: bool,
    /// Describe datasets on this pointfarm server: an input that is no file or folder here is
    /// a dataset id there.
    #[arg(long, env = "POINTFARM_SERVER")]
    server: Option<String>,
    /// Only files here, whatever --server or POINTFARM_SERVER say.
    #[arg(long)]
    local: bool,
    #[command(flatten)]
    credentials: ClientCredentials,
}

/// What an input names.
enum Input {
    /// Files here: a file, or a folder's files.
    Local(Vec<PathBuf>),
    /// A file by URL, or a prefix of them, whose headers (and a COPC file's hierarchy) are
    /// read by range.
    Url(ObjectUrl),
    /// A dataset on the server.
    Dataset(String),
    /// Nothing that can be read, and why.
    Unreadable(String),
}

pub fn run(args: InfoArgs) -> Result<()> {
    let server = args.server.as_deref().filter(|_| !args.local);
    let mut files: Vec<pb::FileDescription> = Vec::new();
    let mut seen = HashSet::new();
    let mut datasets = Vec::new();
    let mut client = None;
    let mut remote = None;
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    for input in &args.inputs {
        match classify(input, server) {
            Input::Unreadable(error) => {
                let unreadable = pb::FileDescription {
                    path: input.display().to_string(),
                    error,
                    ..pb::FileDescription::default()
                };
                tell(&unreadable, args.json);
                files.push(unreadable);
            }
            Input::Local(found) => {
                // Without repeats across inputs (a file named and inside a named folder).
                for path in found {
                    if !seen.insert(std::fs::canonicalize(&path).unwrap_or_else(|_| path.clone())) {
                        continue;
                    }
                    let file = file_description(&inspect(path, !args.no_points));
                    tell(&file, args.json);
                    files.push(file);
                }
            }
            Input::Url(url) => {
                if remote.is_none() {
                    remote = Some(url_input::client()?);
                }
                for file in describe_url(remote.as_ref().expect("made above"), &url) {
                    tell(&file, args.json);
                    files.push(file);
                }
            }
            Input::Dataset(id) => {
                let server = server.unwrap_or_default();
                let description = runtime.block_on(async {
                    if client.is_none() {
                        client = Some(Client::connect(server, &args.credentials).await?);
                    }
                    let client = client.as_mut().expect("connected above");
                    let request = pb::DescribeDatasetRequest {
                        dataset_id: id.clone(),
                        read_points: !args.no_points,
                    };
                    let spinner = crate::progress::spinner(format!("describing dataset {id}"));
                    let reply = client.datasets.describe_dataset(request).await;
                    spinner.finish_and_clear();
                    answer(reply).with_context(|| format!("dataset {id} on {server}"))
                })?;
                for file in description.files {
                    tell(&file, args.json);
                    files.push(file);
                }
                datasets.push(id);
            }
        }
    }
    // The dataset's id when that is all the document describes.
    let dataset_id = match (datasets.as_slice(), args.inputs.len()) {
        ([id], 1) => id.as_str(),
        _ => "",
    };
    let description = dataset_description(dataset_id, files);
    let summary = description.summary.unwrap_or_default();
    if args.json {
        outln!("{}", crate::admin_json::json_line(&description)?);
    } else if description.files.len() > 1 {
        print_summary(&summary);
    }
    match summary.unreadable {
        0 => Ok(()),
        failed => anyhow::bail!("{failed} of {} files could not be read", summary.files),
    }
}

/// A file or folder here is read here, a URL by range; anything else is a dataset id when
/// there is a server.
fn classify(input: &Path, server: Option<&str>) -> Input {
    if url_input::looks_like_url(input) {
        return match url_input::parse(input) {
            Ok(Inputs::Url(url)) => Input::Url(url),
            Ok(Inputs::Paths(paths)) => match dataset_files(&paths) {
                Ok(files) => Input::Local(files),
                Err(error) => Input::Unreadable(error.to_string()),
            },
            Err(error) => Input::Unreadable(format!("{error:#}")),
        };
    }
    if input.exists() {
        return match dataset_files(&[input.to_path_buf()]) {
            Ok(files) => Input::Local(files),
            Err(error) => Input::Unreadable(error.to_string()),
        };
    }
    match (server, input.to_str()) {
        (Some(_), Some(id)) => Input::Dataset(id.to_owned()),
        (Some(_), None) => Input::Unreadable(format!(
            "{}: no such file or folder, nor a dataset id",
            input.display()
        )),
        (None, _) => Input::Unreadable(format!(
            "{}: no such file or folder (a dataset id needs --server or POINTFARM_SERVER)",
            input.display()
        )),
    }
}

/// What the files at `url` hold, read by range: one object, or each `.las`/`.laz` object
/// under a prefix. Their points are not read by URL, nor a COPC file's CRS.
fn describe_url(client: &RemoteClient, url: &ObjectUrl) -> Vec<pb::FileDescription> {
    if !url.is_prefix() {
        return vec![describe_object(client, url)];
    }
    match url_input::tiles_under(client, url) {
        Ok(tiles) => (tiles.iter())
            .map(|tile| describe_object(client, &tile.url))
            .collect(),
        Err(error) => vec![unreadable(url, error)],
    }
}

/// The report of a URL that could not be read.
fn unreadable(url: &ObjectUrl, error: anyhow::Error) -> pb::FileDescription {
    pb::FileDescription {
        path: url.to_string(),
        error: format!("{error:#}"),
        ..pb::FileDescription::default()
    }
}

/// What the object at `url` holds: a COPC file's header and hierarchy, else a plain LAS/LAZ
/// file's header and records.
fn describe_object(client: &RemoteClient, url: &ObjectUrl) -> pb::FileDescription {
    match url_input::describe_copc(client, url) {
        Ok(Some(summary)) => copc_file_description(url, summary),
        Ok(None) => describe_tile(client, url),
        Err(error) => unreadable(url, error),
    }
}

/// What the plain LAS/LAZ file at `url` holds, as `info` says of a file here without its
/// points.
fn describe_tile(client: &RemoteClient, url: &ObjectUrl) -> pb::FileDescription {
    match describe_tile_url(client, url) {
        Ok(info) => file_description(&FileReport {
            path: url.to_string().into(),
            outcome: Ok((info, None)),
            copc: None,
        }),
        Err(error) => unreadable(url, error.into()),
    }
}

/// What a COPC file by URL holds, as its header and hierarchy say.
fn copc_file_description(url: &ObjectUrl, summary: CopcSummary) -> pb::FileDescription {
    let path = url.to_string();
    let header = &summary.header;
    let vec3 = |v: glam::DVec3| pb::Vec3 {
        x: v.x,
        y: v.y,
        z: v.z,
    };
    let attributes = &header.attributes;
    pb::FileDescription {
        path,
        file_bytes: header.file_bytes,
        version_major: 1,
        version_minor: 4,
        point_format: header.point_format.into(),
        compressed: true,
        record_bytes: header.record_len.into(),
        points: header.points,
        vlrs: header.vlrs,
        evlrs: header.evlrs,
        bounds: Some(pb::Bounds {
            min: Some(vec3(header.bounds.min)),
            max: Some(vec3(header.bounds.max)),
        }),
        scale: Some(vec3(header.scale)),
        offset: Some(vec3(header.offset)),
        crs: Some(pb::Crs {
            source: Some(pb::crs::Source::Unreadable(
                "not read by URL yet".to_owned(),
            )),
        }),
        attributes: Some(point_attributes_message(attributes)),
        copc: Some(copc_description(&Ok(summary))),
        ..pb::FileDescription::default()
    }
}

/// A file's report as soon as it is made: its error on stderr, its text unless JSON comes at
/// the end.
fn tell(file: &pb::FileDescription, json: bool) {
    if !file.error.is_empty() {
        eprintln!("error: {}", file.error);
    }
    if !json {
        print_report(file);
    }
}

fn inspect(path: PathBuf, read_points: bool) -> FileReport {
    let mut bar = None;
    let report = FileReport::read(path, read_points, |info| {
        let counter = crate::progress::counter(info.points, "points", file_name(&info.path));
        bar = Some(counter.clone());
        Box::new(move |read: u64| counter.set_position(read))
    });
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    report
}

fn file_name(path: &Path) -> String {
    path.file_name()
        .map(|name| name.to_string_lossy().into_owned())
        .unwrap_or_else(|| path.display().to_string())
}

/// The three components of a vector.
fn xyz(v: Option<&pb::Vec3>) -> [f64; 3] {
    v.map_or([f64::NAN; 3], |v| [v.x, v.y, v.z])
}

/// The three channels of an RGB range's end.
fn rgb(channels: &[u32]) -> [u32; 3] {
    let at = |i: usize| channels.get(i).copied().unwrap_or(0);
    [at(0), at(1), at(2)]
}

fn print_report(file: &pb::FileDescription) {
    outln!("{}", file.path);
    if !file.error.is_empty() {
        outln!("  unreadable (see the error above)");
        outln!("");
        return;
    }
    outln!(
        "  LAS {}.{}, point format {} ({}-byte records), {}, {} bytes",
        file.version_major,
        file.version_minor,
        file.point_format,
        file.record_bytes,
        if file.compressed {
            "LAZ"
        } else {
            "uncompressed"
        },
        file.file_bytes
    );
    let by_return = match file.points_by_return.as_slice() {
        [] => String::new(),
        counts => format!("  (by return: {})", numbered(counts.iter().copied(), 1)),
    };
    outln!("  points      {}{by_return}", file.points);
    outln!("  records     {} VLRs, {} EVLRs", file.vlrs, file.evlrs);
    let scale = xyz(file.scale.as_ref());
    let decimals = decimals(scale.into_iter().fold(f64::NAN, f64::max));
    let bounds = file.bounds.unwrap_or_default();
    let (min, max) = (xyz(bounds.min.as_ref()), xyz(bounds.max.as_ref()));
    let axes = ["x", "y", "z"];
    for (axis, label) in axes.iter().enumerate() {
        let heading = if axis == 0 { "bounds" } else { "" };
        outln!(
            "  {heading:<11} {label} {:.decimals$} .. {:.decimals$}",
            min[axis],
            max[axis]
        );
    }
    outln!("  scale       {} {} {}", scale[0], scale[1], scale[2]);
    let offset = xyz(file.offset.as_ref());
    outln!("  offset      {} {} {}", offset[0], offset[1], offset[2]);
    outln!("  crs         {}", crs_words(file.crs.as_ref()));
    outln!(
        "  attributes  {}",
        attribute_words(&file.attributes.clone().unwrap_or_default())
    );
    if let Some(copc) = &file.copc {
        outln!("  copc        {}", copc_words(copc, decimals));
    }
    if let Some(points) = &file.points_read {
        print_points(points, decimals);
    }
    outln!("");
}

/// A COPC file's octree in a line, or why its hierarchy cannot be read.
fn copc_words(copc: &pb::CopcDescription, decimals: usize) -> String {
    if !copc.error.is_empty() {
        return format!("hierarchy unreadable, read as plain LAZ: {}", copc.error);
    }
    let center = xyz(copc.center.as_ref());
    format!(
        "{} nodes in {} levels, {} hierarchy pages ({} bytes); cube centre {:.decimals$} \
         {:.decimals$} {:.decimals$}, half side {:.decimals$}, root spacing {:.decimals$}",
        copc.nodes,
        copc.depth + 1,
        copc.hierarchy_pages,
        copc.hierarchy_bytes,
        center[0],
        center[1],
        center[2],
        copc.halfsize,
        copc.spacing
    )
}

fn print_points(points: &pb::PointStatistics, decimals: usize) {
    outln!("  points read {}", points.points);
    if points.points == 0 {
        // An empty file (a tile with nothing in it) has no classes, returns or colors.
        return;
    }
    if let Some(bounds) = &points.bounds {
        let (min, max) = (xyz(bounds.min.as_ref()), xyz(bounds.max.as_ref()));
        outln!(
            "  data bounds x {:.decimals$} .. {:.decimals$}, y {:.decimals$} .. {:.decimals$}, z {:.decimals$} .. {:.decimals$}",
            min[0], max[0], min[1], max[1], min[2], max[2]
        );
    }
    let classes: Vec<String> = points
        .classes
        .iter()
        .map(|class| match class.name.as_str() {
            "" => format!("{}: {}", class.code, class.points),
            name => format!("{} {name}: {}", class.code, class.points),
        })
        .collect();
    outln!("  classes     {}", classes.join(", "));
    let returns: Vec<String> = points
        .returns
        .iter()
        .map(|r| format!("{}: {}", r.return_number, r.points))
        .collect();
    outln!("  returns     {}", returns.join(", "));
    if let Some(intensity) = &points.intensity {
        outln!("  intensity   {} .. {}", intensity.min, intensity.max);
    }
    outln!("  color      {}", color_words(points));
}

fn print_summary(summary: &pb::DescriptionSummary) {
    let unreadable = match summary.unreadable {
        0 => String::new(),
        failed => format!(" ({failed} unreadable)"),
    };
    outln!(
        "{} files{unreadable}, {} points",
        summary.files,
        summary.points
    );
    if let Some(bounds) = &summary.bounds {
        let (min, max) = (xyz(bounds.min.as_ref()), xyz(bounds.max.as_ref()));
        outln!(
            "  bounds x {:.3} .. {:.3}, y {:.3} .. {:.3}, z {:.3} .. {:.3}",
            min[0],
            max[0],
            min[1],
            max[1],
            min[2],
            max[2]
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
fn decimals(scale: f64) -> usize {
    if !(scale.is_finite() && scale > 0.0) {
        return 3;
    }
    (-scale.log10() - 1e-9).ceil().clamp(0.0, 9.0) as usize
}

fn crs_words(crs: Option<&pb::Crs>) -> String {
    use pb::crs::Source;
    let code = |code: u32| match code {
        code if code == u32::from(GEOTIFF_USER_DEFINED) => "user-defined".to_owned(),
        code => format!("EPSG:{code}"),
    };
    match crs.and_then(|crs| crs.source.as_ref()) {
        Some(Source::Wkt(wkt)) => {
            let name = wkt.name.as_deref().unwrap_or("unnamed");
            match wkt.epsg {
                Some(epsg) => format!("{name} (EPSG:{epsg}, from the WKT record)"),
                None => format!("{name} (from the WKT record)"),
            }
        }
        Some(Source::Geotiff(keys)) => {
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
        Some(Source::Unreadable(reason)) => format!("unreadable: {reason}"),
        None => "none".to_owned(),
    }
}

fn attribute_words(a: &pb::PointAttributes) -> String {
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

/// What the color fields hold, in words.
fn color_words(points: &pb::PointStatistics) -> String {
    let Some(range) = &points.rgb else {
        return "no RGB (rendered from intensity)".to_owned();
    };
    if points.points == 0 {
        return "RGB fields, no points".to_owned();
    }
    if !range.varies {
        let [r, g, b] = rgb(&range.min);
        return if [r, g, b] == [0; 3] {
            "RGB fields, all zero: no color information (rendered from intensity)".to_owned()
        } else {
            let shown = if points.intensity.as_ref().is_some_and(|i| i.max > 0) {
                "rendered from intensity"
            } else {
                "rendered in that color"
            };
            format!(
                "RGB fields, one color ({r}, {g}, {b}) for every point: no color information ({shown})"
            )
        };
    }
    let [r, g, b] = rgb(&range.max);
    if range.eight_bit_values {
        format!("RGB, 8-bit values in 16-bit fields (highest {r}, {g}, {b}; rendered as they are)")
    } else {
        format!("RGB, 16-bit (highest {r}, {g}, {b})")
    }
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

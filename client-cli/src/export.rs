//! `pointfarm export FILES... --copc OUT`: a dataset written as one COPC 1.0 file, from its
//! level-of-detail store (built once and kept in `--cache-dir`, as `render` keeps it), so
//! PDAL, QGIS, Potree and laspy open what pointfarm built. `pointfarm dataset export` asks a
//! server for the same file made from the store it keeps. Either writes to a file here or
//! uploads to an `s3://` URL.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use pointfarm_daemon::grpc::export_summary;
use pointfarm_proto::v1 as pb;
use pointfarm_render::cut::CutOptions;
use pointfarm_render::ingest::dataset_files;
use pointfarm_render::lod::copc_export::{export_copc, CopcExportReport, ExportSettings};
use pointfarm_render::remote::{ObjectUrl, RemoteClient};
use serde::Serialize;

use pointfarm_render::source::{LocalStore, SourceEvent};

use crate::paths::store_cache;
use crate::source_words::SourceWords;
use crate::url_input::{self, Inputs};

#[derive(Args)]
pub struct ExportArgs {
    /// LAS/LAZ files or folders of them, exported as one dataset.
    #[arg(required = true, value_name = "INPUT")]
    inputs: Vec<PathBuf>,
    #[command(flatten)]
    output: OutputArgs,
    /// Host memory for the store's build when there is none yet, e.g. 512MiB or 4GiB.
    #[arg(long, value_name = "SIZE", value_parser = crate::parse::bytes)]
    memory_budget: Option<u64>,
    /// Where level-of-detail stores are kept between commands (default
    /// $XDG_CACHE_HOME/pointfarm or ~/.cache/pointfarm).
    #[arg(long, env = "POINTFARM_CACHE_DIR", value_name = "DIR")]
    cache_dir: Option<PathBuf>,
    /// The most disk the stores in --cache-dir may take together, e.g. 200GiB.
    #[arg(long, env = "POINTFARM_CACHE_SIZE", value_name = "SIZE", value_parser = crate::parse::bytes)]
    cache_size: Option<u64>,
    /// Print one JSON object (lowerCamelCase keys) instead of a line of text.
    #[arg(long)]
    json: bool,
}

/// Where an export goes; shared by the local and the server command.
#[derive(Args, Clone)]
pub struct OutputArgs {
    /// The COPC file to write (by convention NAME.copc.laz); its folder must exist. An
    /// `s3://bucket/key` (or gs://, az://) URL is written there by a multipart upload (credentials from the
    /// environment, as for reads); the object appears only once the whole file is sent.
    #[arg(long, value_name = "FILE|URL", required = true)]
    pub copc: PathBuf,
    /// Replace the file or object if it exists.
    #[arg(long)]
    pub force: bool,
}

/// Where an export is written: a file here, or an object uploaded by URL.
pub enum ExportTarget {
    File(PathBuf),
    Url {
        client: RemoteClient,
        url: ObjectUrl,
    },
}

impl ExportTarget {
    /// How reports name it.
    pub fn name(&self) -> String {
        match self {
            ExportTarget::File(path) => path.display().to_string(),
            ExportTarget::Url { url, .. } => url.to_string(),
        }
    }
}

impl OutputArgs {
    /// Where to write, checked before any work starts: an existing file or object is refused
    /// without --force (an object is looked for once, here; one written by someone else
    /// meanwhile is replaced), and so is a folder that does not exist.
    pub fn target(&self) -> Result<ExportTarget> {
        // A file:// URL is its path.
        let out = if url_input::looks_like_url(&self.copc) {
            match url_input::parse(&self.copc)? {
                Inputs::Url(url) => return self.url_target(url),
                Inputs::Paths(mut paths) => paths.remove(0),
            }
        } else {
            self.copc.clone()
        };
        if out.is_dir() {
            bail!("{} is a folder: name the COPC file to write", out.display());
        }
        if out.exists() && !self.force {
            bail!("{} exists: pass --force to replace it", out.display());
        }
        let parent = out.parent().filter(|p| !p.as_os_str().is_empty());
        if let Some(parent) = parent.filter(|p| !p.is_dir()) {
            bail!(
                "cannot write {}: the folder {} does not exist",
                out.display(),
                parent.display()
            );
        }
        Ok(ExportTarget::File(out))
    }

    fn url_target(&self, url: ObjectUrl) -> Result<ExportTarget> {
        if !url.is_object_storage() {
            bail!("{url}: exports are uploaded to object storage (s3://, gs:// or az://); a web server's URL is read-only here");
        }
        if url.is_prefix() {
            bail!("{url} names a prefix: name the COPC object to write");
        }
        let client = url_input::client()?;
        client.check_bucket(&url)?;
        if !self.force && client.exists(&url)? {
            bail!("{url} exists: pass --force to replace it");
        }
        Ok(ExportTarget::Url { client, url })
    }
}

/// What `export --json` prints.
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
pub struct ExportJson {
    pub file: String,
    pub points: u64,
    pub nodes: usize,
    pub bytes: u64,
    pub point_format: u8,
    pub scale: [f64; 3],
    pub offset: [f64; 3],
    pub min: [f64; 3],
    pub max: [f64; 3],
    pub seconds: f64,
}

impl ExportJson {
    fn new(file: String, report: &CopcExportReport, seconds: f64) -> Self {
        Self {
            file,
            points: report.points,
            nodes: report.nodes,
            bytes: report.bytes,
            point_format: report.point_format,
            scale: report.transform.scale.to_array(),
            offset: report.transform.offset.to_array(),
            min: report.min.to_array(),
            max: report.max.to_array(),
            seconds,
        }
    }
}

pub fn run(args: ExportArgs) -> Result<()> {
    let target = args.output.target()?;
    let files = dataset_files(&args.inputs)?;
    let stores = store_cache(args.cache_dir.as_ref(), args.cache_size);
    let budget = args
        .memory_budget
        .unwrap_or(CutOptions::default().memory_budget_bytes);
    let folder = stores.folder_of_files(&files)?;
    let words = SourceWords::new(args.json, "export".into());
    let events = |event: SourceEvent<'_>| words.tell(event);
    let stored =
        LocalStore::open_or_build(&files, &folder, budget, stores.disk_budget, &events)?.stored;
    let hierarchy = stored.dataset.hierarchy();
    let settings = ExportSettings::of_files(&files, &hierarchy.cube)?;
    // COPC is written with seeks (its header and hierarchy last), so an upload is made from a
    // file written here first, then sent a part at a time.
    let out = match &target {
        ExportTarget::File(path) => path.clone(),
        ExportTarget::Url { .. } => std::env::temp_dir().join(format!(
            "pointfarm-export-{}-{}.copc.laz",
            std::process::id(),
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap_or_default()
                .as_nanos()
        )),
    };
    let bar = crate::progress::counter(hierarchy.point_count, "points", "exporting".into());
    let started = Instant::now();
    let report = export_copc(
        hierarchy,
        &**stored.dataset.records(),
        &settings,
        &out,
        &mut |points| bar.set_position(points),
    )
    .with_context(|| format!("exporting to {}", out.display()));
    bar.finish_and_clear();
    let report = report?;
    if let ExportTarget::Url { client, url } = &target {
        let spinner = crate::progress::spinner(format!("uploading to {url}"));
        let uploaded = client.upload_file(&out, url);
        spinner.finish_and_clear();
        let _ = std::fs::remove_file(&out);
        uploaded?;
    }
    let seconds = started.elapsed().as_secs_f64();
    print_report(&target.name(), &report, seconds, args.json)
}

/// The line, or the JSON object, that says what an export wrote.
pub fn print_report(out: &str, report: &CopcExportReport, seconds: f64, json: bool) -> Result<()> {
    if json {
        outln!(
            "{}",
            serde_json::to_string(&ExportJson::new(out.to_owned(), report, seconds))?
        );
    } else {
        outln!(
            "{}",
            exported_line(out, &export_summary(report, seconds), "")
        );
    }
    Ok(())
}

/// The line that says what an export wrote to `file`; `made` says where it took its time
/// ("" here, " on the server").
pub fn exported_line(file: &str, summary: &pb::ExportSummary, made: &str) -> String {
    format!(
        "{file}: {} points in {} nodes, {:.1} MB, COPC 1.0 (point format {}, scale {}), in {:.1} s{made}",
        summary.points,
        summary.nodes,
        summary.size_bytes as f64 / 1e6,
        summary.point_format,
        summary.scale.first().copied().unwrap_or_default(),
        summary.seconds,
    )
}

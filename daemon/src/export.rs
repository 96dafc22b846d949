//! A dataset exported as one COPC 1.0 file from the level-of-detail store the daemon keeps of
//! it (built first when there is none, on the stores' own thread; for tiles by URL, by
//! streaming them), into a temporary file that the service streams to the client and then
//! removes. Its name ends in `.part`, as an unfinished upload's does, so a daemon stopped
//! mid-export removes it at its next start.
//!
//! A COPC object by URL already is a COPC file, and the daemon keeps no store of it: its
//! export is the object itself, its hierarchy checked first, then copied by ranged reads of
//! bounded blocks, every one pinned to the version its registration recorded, so an object
//! replaced since fails the export naming it and nothing of it is sent.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use pointfarm_render::copc::{self, CopcSummary};
use pointfarm_render::ingest::{deciding, Crs, FileInfo};
use pointfarm_render::lod::copc_export::{
    export_copc, CopcExportError, CopcExportReport, ExportSettings, ExportTransform,
};
use pointfarm_render::lod::RootCube;
use pointfarm_render::remote::{ObjectReader, RemoteError, RemoteObject};

use crate::error::DaemonError;
use crate::model::Dataset;
use crate::service::{unique_suffix, Daemon};
use crate::stores::StoreAnswer;

/// How often an export waiting for its store's build asks again.
const BUILD_POLL: Duration = Duration::from_millis(200);

/// A written export: its temporary file (the caller removes it), what it holds, and the
/// seconds it took.
pub struct ExportedFile {
    pub path: PathBuf,
    pub report: CopcExportReport,
    pub seconds: f64,
}

impl Daemon {
    /// Writes dataset `id` as a COPC file in the daemon's temporary folder. Blocks while the
    /// dataset's store is built.
    pub fn export_dataset(&self, id: &str) -> Result<ExportedFile, DaemonError> {
        let dataset = self.dataset(id)?;
        if dataset.remote.is_some() {
            return self.export_copc_object(&dataset);
        }
        // Tiles by URL are held to their recorded versions by the build and the reads below.
        if dataset.tiles.is_empty() {
            self.check_dataset_files(&dataset)?;
        }
        let started = Instant::now();
        let store = loop {
            match self.stores.open_store(&dataset, true)? {
                StoreAnswer::Ready(store) => break store,
                StoreAnswer::Building { .. } => std::thread::sleep(BUILD_POLL),
                StoreAnswer::NotNeeded { .. } => {
                    return Err(DaemonError::Internal(
                        "a store was asked for and not opened".into(),
                    ))
                }
            }
        };
        let hierarchy = store.hierarchy();
        let settings = self.export_settings(&dataset, &hierarchy.cube)?;
        let path = self.export_path();
        let report = export_copc(
            hierarchy,
            &**store.node_records(),
            &settings,
            &path,
            &mut |_| {},
        )
        .map_err(export_error)?;
        let seconds = started.elapsed().as_secs_f64();
        tracing::info!(dataset = %id, points = report.points, bytes = report.bytes,
            seconds = format!("{seconds:.1}"), "dataset exported as COPC");
        Ok(ExportedFile {
            path,
            report,
            seconds,
        })
    }
}

impl Daemon {
    /// A temporary file for an export, in the uploads folder (removed at start-up if left).
    fn export_path(&self) -> PathBuf {
        self.config
            .uploads_dir()
            .join(format!("export-{}.copc.part", unique_suffix()))
    }

    /// Exports `dataset`, a COPC object by URL, as the object itself at its recorded version.
    fn export_copc_object(&self, dataset: &Dataset) -> Result<ExportedFile, DaemonError> {
        let started = Instant::now();
        let object = self.open_registered_copc(dataset)?;
        let failed = |error: String| {
            DaemonError::FailedPrecondition(format!("dataset {}: {error}", dataset.id))
        };
        // Its header and hierarchy are checked as a render of it checks them.
        let summary = copc::describe_object(object.clone()).map_err(|e| failed(e.to_string()))?;
        let path = self.export_path();
        let copied = copy_object(object, &path).inspect_err(|_| {
            let _ = std::fs::remove_file(&path);
        });
        let bytes = copied.map_err(|error| match error {
            CopyError::Remote(error) => failed(error.to_string()),
            CopyError::Write(error) => DaemonError::from(error),
        })?;
        let report = pass_through_report(&summary, bytes);
        let seconds = started.elapsed().as_secs_f64();
        tracing::info!(dataset = %dataset.id, points = report.points, bytes,
            seconds = format!("{seconds:.1}"), "COPC object exported as it is");
        Ok(ExportedFile {
            path,
            report,
            seconds,
        })
    }

    /// The settings `dataset`'s store is exported with: from its files' headers, or its
    /// tiles' read by range at their recorded versions.
    fn export_settings(
        &self,
        dataset: &Dataset,
        cube: &RootCube,
    ) -> Result<ExportSettings, DaemonError> {
        if dataset.tiles.is_empty() {
            let files: Vec<PathBuf> = dataset.files().into_iter().map(|f| f.path).collect();
            return ExportSettings::of_files(&files, cube).map_err(export_error);
        }
        let headers = (self.describe_tiles(dataset)?.into_iter())
            .map(|report| match report.outcome {
                Ok((info, _)) => Ok(info),
                Err(error) => Err(DaemonError::FailedPrecondition(format!(
                    "dataset {}: {error}",
                    dataset.id
                ))),
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(tiles_export_settings(&headers, cube))
    }
}

/// What `ExportSettings::of_files` takes from files, taken from tiles' headers read by range:
/// the finest scale per axis and the first tile's offset, and the WKT record when every tile
/// declares the same one (as its text, NUL-terminated, as LAS writes it).
fn tiles_export_settings(headers: &[FileInfo], cube: &RootCube) -> ExportSettings {
    // Only tiles with points decide, as in a load: an empty tile changes nothing.
    let headers = deciding(headers, |info| info.points);
    let Some(&first) = headers.first() else {
        return ExportSettings::fixed(cube);
    };
    let scale = (headers.iter()).fold(first.scale, |scale, info| scale.min(info.scale));
    let wkt_of = |info: &FileInfo| match &info.crs {
        Crs::Wkt { wkt, .. } => Some(wkt.clone()),
        _ => None,
    };
    let common =
        wkt_of(first).filter(|wkt| headers.iter().all(|h| wkt_of(h).as_ref() == Some(wkt)));
    ExportSettings {
        transform: ExportTransform {
            scale,
            offset: first.offset,
        },
        wkt: common
            .map(|wkt| [wkt.as_bytes(), b"\0"].concat())
            .filter(|record| record.len() <= usize::from(u16::MAX)),
    }
}

/// Why a copy of an object stopped.
enum CopyError {
    Remote(RemoteError),
    Write(std::io::Error),
}

/// Copies `object` to a new file at `path` in ranged blocks of bounded size, each pinned to
/// the object's version; the bytes copied, which are the object's size.
fn copy_object(object: RemoteObject, path: &Path) -> Result<u64, CopyError> {
    use std::io::{Read, Write};
    let (size, url) = (object.size(), object.url().to_string());
    let mut reader = ObjectReader::new(Arc::new(object));
    let mut file = std::io::BufWriter::new(std::fs::File::create(path).map_err(CopyError::Write)?);
    let mut block = vec![0u8; 1 << 20];
    let mut copied = 0u64;
    loop {
        let read = reader.read(&mut block).map_err(remote_error)?;
        if read == 0 {
            break;
        }
        file.write_all(&block[..read]).map_err(CopyError::Write)?;
        copied += read as u64;
    }
    file.flush().map_err(CopyError::Write)?;
    if copied != size {
        return Err(CopyError::Remote(RemoteError::ShortRead {
            url,
            range: 0..size,
            got: copied,
        }));
    }
    Ok(copied)
}

/// The remote layer's error an [`ObjectReader`] carries through `io::Error`.
fn remote_error(error: std::io::Error) -> CopyError {
    if !error
        .get_ref()
        .is_some_and(|inner| inner.is::<RemoteError>())
    {
        return CopyError::Write(error);
    }
    match error
        .into_inner()
        .map(|inner| inner.downcast::<RemoteError>())
    {
        Some(Ok(remote)) => CopyError::Remote(*remote),
        _ => CopyError::Write(std::io::Error::other("reading the object")),
    }
}

/// What an export of a COPC object as it is holds, from its header and hierarchy.
fn pass_through_report(summary: &CopcSummary, bytes: u64) -> CopcExportReport {
    let header = &summary.header;
    CopcExportReport {
        points: header.points,
        nodes: summary.nodes,
        bytes,
        transform: ExportTransform {
            scale: header.scale,
            offset: header.offset,
        },
        min: header.bounds.min,
        max: header.bounds.max,
        point_format: header.point_format,
    }
}

fn export_error(error: CopcExportError) -> DaemonError {
    match error {
        CopcExportError::Write { source, .. } => DaemonError::from(source),
        CopcExportError::Store(e) => {
            DaemonError::FailedPrecondition(format!("the dataset's store: {e}"))
        }
        other => DaemonError::FailedPrecondition(other.to_string()),
    }
}

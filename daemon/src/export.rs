//! A dataset exported as one COPC 1.0 file from the level-of-detail store the daemon keeps of
//! it (built first when there is none, on the stores' own thread; for tiles by URL, by
//! streaming them), into a temporary file that the service streams to the client and then
//! removes. Its name ends in `.part`, as an unfinished upload's does, so a daemon stopped
//! mid-export removes it at its next start.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use pointfarm_render::ingest::{Crs, FileInfo};
use pointfarm_render::lod::copc_export::{
    export_copc, CopcExportError, CopcExportReport, ExportSettings, ExportTransform,
};
use pointfarm_render::lod::RootCube;

use crate::describe::FileReport;
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
        let path = self
            .config
            .uploads_dir()
            .join(format!("export-{}.copc.part", unique_suffix()));
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
        let (client, tiles) = self.stores.tiles_of(dataset)?;
        let headers = (tiles.iter())
            .map(|tile| match FileReport::read_tile(&client, tile).outcome {
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
    let Some(first) = headers.first() else {
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

fn export_error(error: CopcExportError) -> DaemonError {
    match error {
        CopcExportError::Write { source, .. } => DaemonError::from(source),
        CopcExportError::Store(e) => {
            DaemonError::FailedPrecondition(format!("the dataset's store: {e}"))
        }
        other => DaemonError::FailedPrecondition(other.to_string()),
    }
}

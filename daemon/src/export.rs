//! A dataset exported as one COPC 1.0 file from the level-of-detail store the daemon keeps of
//! it (built first when there is none, on the stores' own thread), into a temporary file that
//! the service streams to the client and then removes. Its name ends in `.part`, as an
//! unfinished upload's does, so a daemon stopped mid-export removes it at its next start.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use pointfarm_render::lod::copc_export::{
    export_copc, CopcExportError, CopcExportReport, ExportSettings,
};

use crate::error::DaemonError;
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
        self.check_dataset_files(&dataset)?;
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
        let files: Vec<PathBuf> = dataset.files().into_iter().map(|f| f.path).collect();
        let hierarchy = store.hierarchy();
        let settings = ExportSettings::of_files(&files, &hierarchy.cube).map_err(export_error)?;
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

fn export_error(error: CopcExportError) -> DaemonError {
    match error {
        CopcExportError::Write { source, .. } => DaemonError::from(source),
        CopcExportError::Store(e) => {
            DaemonError::FailedPrecondition(format!("the dataset's store: {e}"))
        }
        other => DaemonError::FailedPrecondition(other.to_string()),
    }
}

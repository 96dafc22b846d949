//! Helpers for the crate's tests: one GPU for the process, and the real scans' location.

use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

use pointfarm_render::gpu::{AdapterChoice, GpuContext};

/// One GPU context for all tests of the process; fails loudly without an adapter, so that the
/// measuring tests cannot pass by skipping.
pub fn gpu() -> Arc<GpuContext> {
    static GPU: OnceLock<Arc<GpuContext>> = OnceLock::new();
    let init = || {
        let choice = AdapterChoice::from_env().expect("valid POINTFARM_ADAPTER");
        let gpu = GpuContext::new(choice).expect("an adapter (deploy/setup.sh installs lavapipe)");
        Arc::new(gpu)
    };
    GPU.get_or_init(init).clone()
}

/// `../shared/data/<file>` next to the repository, or None (saying so) when it is absent.
pub fn shared_data(file: &str) -> Option<PathBuf> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data")
        .join(file);
    if !path.is_file() {
        eprintln!("skipped: {} not found", path.display());
        return None;
    }
    Some(path)
}

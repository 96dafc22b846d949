//! Where pointfarm keeps its files when no flag, variable or configuration file says: folders
//! that fit a service (systemd's `StateDirectory=`/`CacheDirectory=`, `/var/lib` and
//! `/var/cache` for root) or a user (the XDG base directories), never the current directory.

use std::path::PathBuf;

use pointfarm_render::source::StoreCache;

/// The daemon's state database, uploaded datasets and rendered frames.
pub fn daemon_data_dir() -> PathBuf {
    service_dir("STATE_DIRECTORY", "/var/lib/pointfarm")
        .unwrap_or_else(|| xdg_dir("XDG_DATA_HOME", ".local/share").join("pointfarm"))
}

/// A worker process's dataset cache.
pub fn worker_cache_dir() -> PathBuf {
    service_dir("CACHE_DIRECTORY", "/var/cache/pointfarm")
        .unwrap_or_else(user_cache_dir)
        .join("worker")
}

/// The levels-of-detail stores of local `render` and `export`.
pub fn user_cache_dir() -> PathBuf {
    xdg_dir("XDG_CACHE_HOME", ".cache").join("pointfarm")
}

/// The levels-of-detail stores of local `render` and `export`: in `cache_dir` (default
/// [`user_cache_dir`]), at most `disk_budget` bytes together.
pub fn store_cache(cache_dir: Option<&PathBuf>, disk_budget: Option<u64>) -> StoreCache {
    StoreCache {
        dir: cache_dir
            .cloned()
            .unwrap_or_else(user_cache_dir)
            .join("lod"),
        disk_budget,
    }
}

/// The folder systemd made for the unit (`variable`, the first of a colon-separated list),
/// else `root_default` when running as root, else none.
fn service_dir(variable: &str, root_default: &str) -> Option<PathBuf> {
    if let Some(dirs) = std::env::var_os(variable) {
        if let Some(first) = dirs
            .to_string_lossy()
            .split(':')
            .find(|dir| !dir.is_empty())
        {
            return Some(PathBuf::from(first));
        }
    }
    rustix::process::geteuid()
        .is_root()
        .then(|| PathBuf::from(root_default))
}

/// `$variable`, or `$HOME/home_relative`, or the temporary folder where neither is set.
fn xdg_dir(variable: &str, home_relative: &str) -> PathBuf {
    std::env::var_os(variable)
        .map(PathBuf::from)
        .filter(|dir| dir.is_absolute())
        .or_else(|| std::env::var_os("HOME").map(|home| PathBuf::from(home).join(home_relative)))
        .unwrap_or_else(std::env::temp_dir)
}

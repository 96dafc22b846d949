//! The datasets page: each dataset with its files, points, size, where its level-of-detail
//! store stands (a build's stage and the share of the points it has stored) and its bytes
//! on the daemon's disk, its files' and its store's: the bytes removing the store frees, and
//! apart from them the payload layers it shares with other stores (`lod::disk_usage`). While a store builds the page reloads
//! itself, as the workers page does.

use std::fmt::Write;
use std::path::Path;

use axum::extract::State;
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::Router;

use super::api::{failure_page, run};
use super::html::{self, escape};
use super::Dashboard;
use crate::model::Dataset;
use crate::service::Daemon;
use pointfarm_render::lod::disk_usage::DiskUsage;

pub(super) fn routes() -> Router<Dashboard> {
    Router::new().route("/datasets", get(page))
}

/// How often the page reloads while a store builds, in seconds.
const REFRESH_WHILE_BUILDING_S: u32 = 2;

/// A dataset's points from its files' headers; `None` for an object by URL or a file that
/// cannot be read now.
fn dataset_points(daemon: &Daemon, dataset: &Dataset) -> Option<u64> {
    if dataset.remote.is_some() {
        return None;
    }
    let reports = daemon.describe_dataset(&dataset.id, false).ok()?;
    reports
        .iter()
        .map(|report| report.outcome.as_ref().ok().map(|(info, _)| info.points))
        .sum()
}

/// Where a dataset's level-of-detail store stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Store {
    /// Not built: a frame that needs it starts its build.
    None,
    /// Being built: the points stored so far of `total` (0 of 0 while it counts them).
    Building {
        stored: u64,
        total: u64,
    },
    Built,
}

impl Store {
    fn of(daemon: &Daemon, dataset: &Dataset, folder: &Path) -> Self {
        if let Some((stored, total)) = daemon.stores.building_points(&dataset.sha256) {
            Store::Building { stored, total }
        } else if pointfarm_render::cut::StoredLod::is_built(folder) {
            Store::Built
        } else {
            Store::None
        }
    }

    /// The store's cell: its stage, with a progress bar while it stores nodes.
    fn cell(self) -> String {
        match self {
            Store::None => "none (built when a frame needs it)".to_string(),
            Store::Built => "built".to_string(),
            Store::Building { total: 0, .. } => {
                "<span class=\"store-stage\" data-stage=\"counting\">building: counting the \
                 points</span>"
                    .to_string()
            }
            Store::Building { stored, total } => {
                let percent = (stored.min(total) as f64 / total as f64 * 100.0).floor();
                format!(
                    "<span class=\"store-stage\" data-stage=\"storing\">building: storing the \
                     nodes</span> <progress max=\"{total}\" value=\"{stored}\"></progress> \
                     <span class=\"store-progress\">{percent:.0}%</span>"
                )
            }
        }
    }
}

/// A dataset's bytes on the daemon's disk: its files (none for an object by URL) and its
/// store.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct DiskBytes {
    files: u64,
    /// What removing the store frees.
    store: u64,
    /// The store's files that other stores link too.
    shared: u64,
}

impl DiskBytes {
    fn of(dataset: &Dataset, store_folder: &Path) -> Self {
        let files = if dataset.remote.is_some() {
            0
        } else {
            dataset
                .files()
                .iter()
                .filter_map(|file| std::fs::metadata(&file.path).ok())
                .map(|meta| meta.len())
                .sum()
        };
        let store = DiskUsage::of(store_folder);
        let freed = store.freed_bytes();
        Self {
            files,
            store: freed,
            shared: store.bytes().saturating_sub(freed),
        }
    }

    fn cell(self) -> String {
        let shared = match self.shared {
            0 => String::new(),
            bytes => format!(
                ", <span class=\"disk-shared\" data-bytes=\"{bytes}\">{} shared with other \
                 stores</span>",
                html::bytes(bytes)
            ),
        };
        format!(
            "<span class=\"disk-total\" data-bytes=\"{total}\">{shown}</span> \
             <span class=\"disk-parts\">(files {files}, store {store}{shared})</span>",
            total = self.files.saturating_add(self.store),
            shown = html::bytes(self.files.saturating_add(self.store)),
            files = html::bytes(self.files),
            store = html::bytes(self.store),
        )
    }
}

pub async fn page(State(dashboard): State<Dashboard>) -> Response {
    let read = run(&dashboard.daemon, |daemon| {
        let mut datasets = daemon.state.datasets()?;
        datasets.sort_by(|a, b| (b.created_unix_ms, &b.id).cmp(&(a.created_unix_ms, &a.id)));
        Ok(datasets
            .into_iter()
            .map(|dataset| {
                let folder = daemon.config.data_dir.join("lod").join(&dataset.sha256);
                let points = dataset_points(daemon, &dataset);
                let store = Store::of(daemon, &dataset, &folder);
                let disk = DiskBytes::of(&dataset, &folder);
                (dataset, points, store, disk)
            })
            .collect::<Vec<_>>())
    });
    let datasets = match read.await {
        Ok(datasets) => datasets,
        Err(failure) => return failure_page("Datasets", failure),
    };
    let mut body = String::from(
        "<h1>Datasets</h1><div class=\"table\"><table id=\"datasets\"><thead><tr>\
         <th>Dataset</th><th>Name</th><th>Files</th><th>Points</th><th>Size</th>\
         <th>Store</th><th>On disk</th></tr></thead><tbody>",
    );
    for (dataset, points, store, disk) in &datasets {
        let files = dataset.files();
        let file_names: Vec<String> = files.iter().map(|file| escape(&file.name)).collect();
        let _ = write!(
            body,
            "<tr data-dataset=\"{id}\"><td><code>{id}</code></td><td>{name}</td>\
             <td><details><summary>{count}</summary>{names}</details></td>\
             <td class=\"number\">{points}</td><td class=\"number\">{size}</td>\
             <td class=\"store\">{store}</td><td class=\"disk\">{disk}</td></tr>",
            id = escape(&dataset.id),
            name = escape(&dataset.name),
            count = files.len(),
            names = file_names.join("<br>"),
            points = points.map_or("—".to_string(), |p| p.to_string()),
            size = html::bytes(dataset.size_bytes),
            store = store.cell(),
            disk = disk.cell(),
        );
    }
    body.push_str("</tbody></table></div>");
    if datasets.is_empty() {
        body.push_str(
            "<p>No datasets yet: <code>pointfarm render --server</code> uploads one.</p>",
        );
    }
    let building = datasets
        .iter()
        .any(|(_, _, store, _)| matches!(store, Store::Building { .. }));
    let data = if building {
        format!(" data-refresh=\"{REFRESH_WHILE_BUILDING_S}\"")
    } else {
        String::new()
    };
    Html(html::layout(
        "Datasets", "Datasets", "datasets", &data, &body,
    ))
    .into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_building_store_shows_its_stage_and_share_stored() {
        assert!(Store::Building {
            stored: 0,
            total: 0
        }
        .cell()
        .contains("counting the points"));
        let storing = Store::Building {
            stored: 420,
            total: 1000,
        }
        .cell();
        assert!(storing.contains("storing the nodes"), "{storing}");
        assert!(storing.contains("max=\"1000\" value=\"420\""), "{storing}");
        assert!(storing.contains(">42%<"), "{storing}");
        assert_eq!(Store::Built.cell(), "built");
    }

    #[test]
    fn bytes_on_disk_add_the_files_and_the_store() {
        let dir = tempfile::tempdir().expect("tempdir");
        let file = dir.path().join("scene.las");
        std::fs::write(&file, [0u8; 1000]).expect("a file");
        let store = dir.path().join("lod");
        std::fs::create_dir_all(store.join("index")).expect("a store");
        std::fs::write(store.join("payload"), [0u8; 300]).expect("payload");
        std::fs::write(store.join("index").join("db"), [0u8; 24]).expect("index");
        let dataset = Dataset {
            id: "ds-1".into(),
            name: "scene.las".into(),
            size_bytes: 1000,
            sha256: "00".into(),
            path: file,
            files: Vec::new(),
            created_unix_ms: 0,
            remote: None,
            tiles: Vec::new(),
        };
        let disk = DiskBytes::of(&dataset, &store);
        assert_eq!(
            disk,
            DiskBytes {
                files: 1000,
                store: 324,
                shared: 0
            }
        );
        assert!(
            disk.cell().contains("data-bytes=\"1324\""),
            "{}",
            disk.cell()
        );
        // A store grown from this one links its payload: removing this one frees its index.
        let grown = dir.path().join("grown");
        std::fs::create_dir_all(&grown).expect("a grown store");
        std::fs::hard_link(store.join("payload"), grown.join("payload.0")).expect("a layer");
        let disk = DiskBytes::of(&dataset, &store);
        assert_eq!((disk.store, disk.shared), (24, 300));
        assert!(
            disk.cell().contains("data-bytes=\"1024\"") && disk.cell().contains("300 B shared"),
            "{}",
            disk.cell()
        );
        let gone = DiskBytes::of(&dataset, &dir.path().join("none"));
        assert_eq!(gone.store, 0);
    }
}

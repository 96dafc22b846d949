//! Camera first through the daemon: a job whose keyframed path sees part of a dataset without
//! a store gets the store of the files its frames see built first, so its first final frame
//! does not wait for the rest; the dataset's whole store is grown from it after (or, when the
//! job asks, never).
//!
//! Which files the frames see is the render crate's decision (`source::FileOrder`, from the
//! files' header boxes and the keyframes' clip planes), and so is which jobs qualify: a path
//! whose cameras or colors depend on the points themselves (an automatic camera, a stretch
//! over percentiles) waits for the whole store, as does a dataset of tiles or an object by
//! URL, one with a COPC file, one rendered resident, and a job that finds the whole store
//! already building.
//!
//! The design is two stores, each a content of its own in `DATA/lod/`:
//! - the **part**: the files any frame of the path sees, built within the box of all the
//!   dataset's files (`source::WithinBounds`), so its cube, and the camera fitted to its
//!   bounds, are the whole store's. Its content hash is that of its files and that box, never
//!   a dataset's, and it is known to workers as a dataset of its own (id and hash), so their
//!   caches never mix its nodes with the whole store's. Every frame of the job is leased
//!   against it: the frames of files that are all in it are the frames of every file
//!   (`camera_first.rs` of the render crate), up to the cut's node choice, which
//!   `tests/daemon_camera_first.rs` holds to the local fidelity rule.
//! - the **whole** store of the dataset, grown from a copy of the part, whatever share of
//!   files it lacks (`growth::grow`), for a job that leaves the unseen files to after (its
//!   `build_unseen`, the default), once the part is ready and the job's first frame is in
//!   (`whole_growth_due`): the first frame, drawn from the part, has the daemon's cores to
//!   itself. A job asking never to build them leaves it unbuilt, though a job that needs the
//!   whole store still gets it grown. Once the whole store is ready, frames are leased
//!   against it.
//!
//! Both are built through the daemon's one build path (`DatasetStores::start_build`): one at
//! a time, finished before they are served, the part resumed by its journal after a restart
//! (its fingerprint holds the box) and the whole one's copy made again from its start. The
//! decision per job is kept in memory and made again after a restart from the same headers,
//! giving the same part.
//!
//! Each part is recorded in the state database when it is made, with whether its whole store
//! is wanted (`PartLedger`, `model::CameraFirstPart`), so a restart knows the parts without a
//! job asking (`restart`): it grows a wanted whole store from its finished part, and removes
//! the parts nobody needs any more. A part's folder is removed with its dataset's store
//! (`DatasetStores::remove`).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use glam::DVec3;

use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::copc::is_copc;
use pointfarm_render::cut::{CutError, StoredLod};
use pointfarm_render::ingest::{dataset_point_count, DatasetSource};
use pointfarm_render::lod::{BuildProgress, PointSource};
use pointfarm_render::request::RenderRequest;
use pointfarm_render::source::{
    file_boxes, frame_points, BuildUnseen, FileOrder, FramePoints, PointSourceFacts, WithinBounds,
};

use super::growth::{grow, list_contents, Grown};
use super::input::{ready_of, with_build};
use super::{DatasetStores, Entry, ReadyStore};
use crate::model::{content_sha256_of, dataset_id, CameraFirstPart, Dataset, DatasetFile, Job};

/// The longest the whole store's growth waits for the first frame of a job reading a ready
/// part, so that a stuck worker cannot hold it back.
const WHOLE_GROWTH_HOLD: Duration = Duration::from_secs(30);

/// Whether the whole store is grown now from the ready part `job` reads, which has waited
/// `held` since it was first found ready: once the job's first frame is handed in or the job
/// ends, so that frame has the daemon's cores, or once the hold runs out.
fn whole_growth_due(job: &Job, held: Duration) -> bool {
    job.frames_done > 0 || job.state.is_terminal() || held >= WHOLE_GROWTH_HOLD
}

mod restart;

/// The part of a dataset a job's frames see, and what becomes of the rest.
pub(super) struct Part {
    /// The files the frames see, as a dataset of its own content.
    dataset: Dataset,
    /// The content of the whole dataset.
    whole_sha256: String,
    /// The box of all the dataset's files, which the part's store is built within.
    bounds: WorldBounds,
    /// Whether the whole store is grown from it: a job that read it left the unseen files to
    /// after. Recorded, for a restart.
    whole_wanted: AtomicBool,
    /// Removed once the whole store is grown from it: no job reads it any more (`restart`).
    retired: AtomicBool,
    /// When a job wanting the whole store first found it ready: the whole store's growth
    /// waits from then (`whole_growth_due`).
    ready_since: OnceLock<Instant>,
}

impl Part {
    /// The part as the state records it.
    fn record(&self) -> CameraFirstPart {
        CameraFirstPart {
            part: self.dataset.clone(),
            whole_sha256: self.whole_sha256.clone(),
            bounds: [self.bounds.min.to_array(), self.bounds.max.to_array()],
            whole_wanted: self.whole_wanted.load(Ordering::SeqCst),
        }
    }

    /// The part a record tells.
    fn recorded(record: CameraFirstPart) -> Self {
        let [min, max] = record.bounds;
        Self {
            dataset: record.part,
            whole_sha256: record.whole_sha256,
            bounds: WorldBounds {
                min: DVec3::from_array(min),
                max: DVec3::from_array(max),
            },
            whole_wanted: AtomicBool::new(record.whole_wanted),
            retired: AtomicBool::new(false),
            ready_since: OnceLock::new(),
        }
    }
}

/// Where the parts are recorded so that a restart knows them: the state database.
pub trait PartLedger: Send + Sync {
    /// Records `part`, anew or as it changed.
    fn keep(&self, part: &CameraFirstPart);
    /// Forgets the part whose dataset id is `id`.
    fn forget(&self, id: &str);
}

/// The parts the daemon built or builds first, by the jobs that asked for them.
#[derive(Default)]
pub(super) struct CameraFirstParts {
    /// Each job's decision once made: `None` reads the whole store.
    jobs: Mutex<HashMap<String, Option<Arc<Part>>>>,
    /// The parts by their dataset ids; shared with the builds that retire them.
    parts: Arc<Mutex<HashMap<String, Arc<Part>>>>,
    /// Where they are recorded; unset in tests of the stores alone.
    ledger: OnceLock<Arc<dyn PartLedger>>,
}

/// How a store is made beyond the plain build of its files.
pub(super) enum Making {
    /// Built (or grown by `growth::grow`) from its files.
    Plain,
    /// A part: built within the box of all the dataset's files.
    Within(WorldBounds),
    /// A whole store grown from the finished part in folder `from`, which is then removed
    /// when `retire` says so.
    GrownFrom {
        from: PathBuf,
        retire: Option<Retirement>,
    },
}

/// A part no job reads any more, removed once the whole store is grown from it.
pub(super) struct Retirement {
    id: String,
    parts: Arc<Mutex<HashMap<String, Arc<Part>>>>,
    ledger: Option<Arc<dyn PartLedger>>,
}

impl Retirement {
    /// Removes the part's folder `from`, its record, and forgets it.
    fn run(&self, from: &Path) {
        self.parts
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(&self.id);
        if let Some(ledger) = &self.ledger {
            ledger.forget(&self.id);
        }
        remove_part_folder(
            from,
            &self.id,
            "the whole store is grown from it and no job reads it",
        );
    }
}

/// Removes the folder of part `id`, saying `why`.
fn remove_part_folder(folder: &Path, id: &str, why: &str) {
    match std::fs::remove_dir_all(folder) {
        Ok(()) => tracing::info!(part = %id, folder = %folder.display(),
            "camera first: the part's store is removed: {why}"),
        Err(error) if error.kind() == std::io::ErrorKind::NotFound => {}
        Err(error) => tracing::warn!(part = %id, folder = %folder.display(), %error,
            "camera first: removing the part's store"),
    }
}

impl DatasetStores {
    /// The dataset whose store a frame of `job` (on `dataset`) reads: the part its frames
    /// see while the whole store is not ready (module doc), else `dataset`. Starts growing
    /// the whole store once the part is ready and the growth is due.
    pub fn leased(&self, job: &Job, dataset: &Dataset) -> Dataset {
        let (job_id, request) = (job.id.as_str(), &job.spec.request);
        if dataset.is_by_url() || self.whole_ready(dataset) {
            return dataset.clone();
        }
        let decided = self.lock_jobs().get(job_id).cloned();
        let part = match decided {
            Some(part) => part,
            None => {
                let building = self
                    .entry(&dataset.sha256, |e| {
                        Ok::<_, ()>(matches!(e, Entry::Building { .. }))
                    })
                    .ok()
                    .flatten()
                    .unwrap_or(false);
                let part = match building {
                    true => None,
                    false => self.part_of(request, dataset, wants_whole(job)),
                };
                self.lock_jobs().insert(job_id.to_owned(), part.clone());
                part
            }
        };
        let Some(part) = part else {
            return dataset.clone();
        };
        self.grow_whole_when_due(job, dataset, &part);
        part.dataset.clone()
    }

    /// A final frame of `job` (on `dataset`) was handed in, or the job ended: the whole store
    /// is grown from the part it read, when the job wants it.
    pub fn job_moved(&self, job: &Job, dataset: &Dataset) {
        if dataset.is_by_url() || self.whole_ready(dataset) {
            return;
        }
        let decided = self.lock_jobs().get(job.id.as_str()).cloned().flatten();
        if let Some(part) = decided {
            self.grow_whole_when_due(job, dataset, &part);
        }
    }

    /// Starts growing the whole store of `dataset` from `part` when it is ready, `job` wants
    /// the whole store, and the growth is due (`whole_growth_due`).
    fn grow_whole_when_due(&self, job: &Job, dataset: &Dataset, part: &Part) {
        if !wants_whole(job) || !StoredLod::is_built(&self.folder(&part.dataset.sha256)) {
            return;
        }
        let held = part.ready_since.get_or_init(Instant::now).elapsed();
        if !whole_growth_due(job, held) {
            return;
        }
        // Started once: later calls find it building or ready.
        if let Err(error) = self.open_store(dataset, true) {
            tracing::warn!(dataset = %dataset.id, %error, "growing the whole store");
        }
    }

    /// The part of a dataset a job reads first, by its dataset id (for workers' requests).
    pub fn part_dataset(&self, id: &str) -> Option<Dataset> {
        let parts = self.lock_parts();
        parts.get(id).map(|part| part.dataset.clone())
    }

    /// Whether content `sha256` is a part, which is always cut, never rendered resident.
    pub(super) fn is_part(&self, sha256: &str) -> bool {
        let parts = self.lock_parts();
        parts.values().any(|part| part.dataset.sha256 == sha256)
    }

    /// How the store of content `sha256` is made.
    pub(super) fn making(&self, sha256: &str) -> Making {
        let parts = self.lock_parts();
        for part in parts.values() {
            if part.dataset.sha256 == sha256 {
                return Making::Within(part.bounds);
            }
            let from = self.folder(&part.dataset.sha256);
            if part.whole_sha256 == sha256 && StoredLod::is_built(&from) {
                let retire = part.retired.load(Ordering::SeqCst).then(|| Retirement {
                    id: part.dataset.id.clone(),
                    parts: Arc::clone(&self.camera_first.parts),
                    ledger: self.camera_first.ledger.get().cloned(),
                });
                return Making::GrownFrom { from, retire };
            }
        }
        Making::Plain
    }

    /// Forgets the parts of the whole content `sha256` and the jobs' decisions about it; the
    /// parts' contents, whose stores go with the whole one's.
    pub(super) fn forget_parts_of(&self, sha256: &str) -> Vec<String> {
        let mut parts = self.lock_parts();
        let gone: Vec<Arc<Part>> = parts
            .values()
            .filter(|part| part.whole_sha256 == sha256)
            .cloned()
            .collect();
        parts.retain(|_, part| part.whole_sha256 != sha256);
        drop(parts);
        self.lock_jobs()
            .retain(|_, part| part.as_ref().is_none_or(|part| part.whole_sha256 != sha256));
        if let Some(ledger) = self.camera_first.ledger.get() {
            for part in &gone {
                ledger.forget(&part.dataset.id);
            }
        }
        gone.iter()
            .map(|part| part.dataset.sha256.clone())
            .collect()
    }

    /// Parts are recorded in `ledger` from now on.
    pub fn record_parts_in(&self, ledger: Arc<dyn PartLedger>) {
        if self.camera_first.ledger.set(ledger).is_err() {
            tracing::warn!("the parts built first are recorded in one place already");
        }
    }

    /// Records `part` as it is now.
    fn record(&self, part: &Part) {
        if let Some(ledger) = self.camera_first.ledger.get() {
            ledger.keep(&part.record());
        }
    }

    fn lock_parts(&self) -> std::sync::MutexGuard<'_, HashMap<String, Arc<Part>>> {
        self.camera_first
            .parts
            .lock()
            .unwrap_or_else(|e| e.into_inner())
    }

    fn lock_jobs(&self) -> std::sync::MutexGuard<'_, HashMap<String, Option<Arc<Part>>>> {
        self.camera_first
            .jobs
            .lock()
            .unwrap_or_else(|e| e.into_inner())
    }

    /// Whether the whole store of `dataset` is ready or built; the jobs' decisions about it
    /// are forgotten then.
    fn whole_ready(&self, dataset: &Dataset) -> bool {
        let ready = matches!(
            self.entries_now().get(&dataset.sha256),
            Some(Entry::Ready(_))
        ) || StoredLod::is_built(&self.folder(&dataset.sha256));
        if ready {
            self.lock_jobs().retain(|_, part| {
                part.as_ref()
                    .is_none_or(|part| part.whole_sha256 != dataset.sha256)
            });
        }
        ready
    }

    /// The part of `dataset` the frames of `request` see, when they qualify (module doc), for
    /// a job that wants the whole store grown from it or not (`wants_whole`); recorded when it
    /// is new or first wanted whole.
    fn part_of(
        &self,
        request: &RenderRequest,
        dataset: &Dataset,
        wants_whole: bool,
    ) -> Option<Arc<Part>> {
        if !FileOrder::applies(request) || self.check_files(dataset).is_err() {
            return None;
        }
        let files = dataset.files();
        let paths: Vec<PathBuf> = files.iter().map(|f| f.path.clone()).collect();
        if paths.len() < 2 || paths.iter().any(|p| is_copc(p).unwrap_or(true)) {
            return None;
        }
        let facts = PointSourceFacts {
            points: Some(dataset_point_count(&paths).ok()?),
            one_copc_file: false,
            store_built: false,
            levels_of_detail_asked: request.render.lod_error.is_some(),
        };
        if frame_points(&facts) == FramePoints::Resident {
            return None;
        }
        let order = FileOrder::of(request, &file_boxes(&paths).ok()?)?;
        let mut places: Vec<usize> = order.first.iter().chain(&order.path).copied().collect();
        places.sort_unstable();
        let bounds = DatasetSource::open(&paths).ok()?.bounds();
        let seen: Vec<DatasetFile> = places.iter().map(|&i| files[i].clone()).collect();
        let part = Arc::new(Part {
            dataset: part_dataset(dataset, seen, &bounds),
            whole_sha256: dataset.sha256.clone(),
            bounds,
            whole_wanted: AtomicBool::new(false),
            retired: AtomicBool::new(false),
            ready_since: OnceLock::new(),
        });
        tracing::info!(dataset = %dataset.id, part = %part.dataset.id,
            files_seen = places.len(), files = files.len(),
            "camera first: the store of the {} of {} files the job's frames see is built first",
            places.len(), files.len());
        let known = Arc::clone(
            self.lock_parts()
                .entry(part.dataset.id.clone())
                .or_insert_with(|| Arc::clone(&part)),
        );
        let newly_wanted = wants_whole && !known.whole_wanted.swap(true, Ordering::SeqCst);
        if Arc::ptr_eq(&known, &part) || newly_wanted {
            self.record(&known);
        }
        Some(known)
    }
}

/// Whether `job` wants the whole store grown from its part: it leaves the unseen files to
/// after.
fn wants_whole(job: &Job) -> bool {
    job.spec.build_unseen == BuildUnseen::After
}

/// The part of `whole` holding the files `seen`, within `bounds`: its content hash is its
/// files' and the box's, so no dataset of the same files shares its store.
fn part_dataset(whole: &Dataset, seen: Vec<DatasetFile>, bounds: &WorldBounds) -> Dataset {
    let within = format!(
        "camera first within {:?} {:?}",
        bounds.min.to_array(),
        bounds.max.to_array()
    );
    let mut hashes: Vec<&str> = seen.iter().map(|f| f.sha256.as_str()).collect();
    hashes.push(&within);
    let sha256 = content_sha256_of(&hashes);
    Dataset {
        id: dataset_id(&sha256),
        name: format!("{} (camera first)", whole.name),
        size_bytes: seen.iter().map(|f| f.size_bytes).sum(),
        sha256,
        path: seen[0].path.clone(),
        files: seen,
        created_unix_ms: whole.created_unix_ms,
        remote: None,
        tiles: Vec::new(),
    }
}

/// What [`make`] made before the plain opening.
pub(super) enum Made {
    /// Nothing: the store is opened (built or grown) from its files.
    Nothing,
    /// The store was grown from a part, and is opened from its folder.
    Grown(Grown),
    /// A part, built and opened.
    Ready(Box<ReadyStore>),
}

impl Made {
    /// The store made, opened by `open` unless it is open already.
    pub(super) fn or_open(
        self,
        open: impl FnOnce() -> Result<ReadyStore, CutError>,
    ) -> Result<ReadyStore, CutError> {
        match self {
            Made::Nothing => open(),
            Made::Grown(grown) => open().map(|ready| ready.grown_by(grown)),
            Made::Ready(ready) => Ok(*ready),
        }
    }
}

/// Makes the store of `files` in `folder` as `making` says: a part within its box, or a
/// whole store grown from its part (when growing fails, it is built whole by the opening).
pub(super) fn make(
    making: &Making,
    folder: &std::path::Path,
    budget: u64,
    progress: &BuildProgress,
    files: &[DatasetFile],
    points: u64,
    dataset_id: &str,
) -> Result<Made, CutError> {
    match making {
        Making::Plain => Ok(Made::Nothing),
        Making::GrownFrom { from, retire } => {
            let grown = grow(folder, files, points, budget, dataset_id, Some(from));
            if let (Some(_), Some(retire)) = (&grown, retire) {
                retire.run(from);
            }
            Ok(grown.map_or(Made::Nothing, Made::Grown))
        }
        Making::Within(bounds) => {
            let paths: Vec<PathBuf> = files.iter().map(|f| f.path.clone()).collect();
            let source = DatasetSource::open(&paths)?;
            let within = WithinBounds {
                source: &source,
                bounds: *bounds,
            };
            let lod = with_build(folder, budget, progress, |build| {
                StoredLod::open_or_build_source(&within, build)
            })?;
            list_contents(folder, files);
            Ok(Made::Ready(Box::new(ready_of(lod, folder))))
        }
    }
}

impl super::ReadyStore {
    /// The store, made by growing another content's store as `grown` says.
    fn grown_by(mut self, grown: Grown) -> Self {
        self.build_ms = grown.seconds * 1e3;
        self.grown = Some(grown);
        self
    }
}

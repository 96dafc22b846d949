//! What a frame source says as it opens and renders: the caller decides how to tell it (the
//! command line says it in words with spinners for the long steps, a worker logs it).

use std::path::{Path, PathBuf};

use crate::cache::CacheOutcome;
use crate::cut::CutError;

/// One step of a frame source's opening or rendering.
#[derive(Debug)]
pub enum SourceEvent<'a> {
    /// Reading a dataset's files whole starts; [`SourceEvent::Read`] ends it.
    Reading { files: &'a [PathBuf] },
    /// A dataset's points are read, from its files or a dataset cache.
    Read {
        points: usize,
        files: usize,
        /// Where the points' colors come from, in words.
        colors: &'static str,
        ms: f64,
        /// Whether a dataset cache held them; `None` without a cache.
        cache: Option<CacheOutcome>,
    },
    /// A preview's points are resident: a few of the dataset's, and of the nodes a build has
    /// stored so far.
    Preview {
        points: usize,
        points_in_files: u64,
        stored_nodes: usize,
        stored_points: usize,
        colors: &'static str,
    },
    /// The request's filter kept `kept` of `points` points (none: the frames show only the
    /// background).
    Filtered { kept: usize, points: usize },
    /// A store is built camera first: this stage adds `files` (`camera_first.rs`).
    BuildingFirst {
        stage: BuildStage,
        files: &'a [PathBuf],
    },
    /// A store's build starts; [`SourceEvent::Built`] ends it.
    Building { points: u64, folder: &'a Path },
    /// A store is built.
    Built {
        nodes: usize,
        points: u64,
        seconds: f64,
    },
    /// The store of an earlier set of the dataset's files took the added ones in and the
    /// removed ones out (a changed file counts once, as changed): only the regions they reach
    /// were built again.
    Updated {
        files_added: usize,
        files_removed: usize,
        files_changed: usize,
        regions_rebuilt: usize,
        points_added: u64,
        points_removed: u64,
        seconds: f64,
    },
    /// A store's bytes failed their checks: it is removed and built again.
    Rebuilding {
        folder: &'a Path,
        damage: &'a CutError,
    },
    /// The frames are cuts through levels of detail, through node caches of these sizes.
    Levels {
        points: u64,
        from: LevelsFrom<'a>,
        host_cache_bytes: u64,
        gpu_cache_bytes: u64,
        lod_error: f64,
    },
}

/// The stage of a store built camera first, by the files it adds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BuildStage {
    /// The files the first frame sees.
    FirstFrame,
    /// The files the rest of the camera path sees.
    Path,
    /// The files no frame sees.
    Unseen,
}

impl BuildStage {
    /// Which files the stage adds, in words.
    pub fn describe(self) -> &'static str {
        match self {
            BuildStage::FirstFrame => "the files the first frame sees",
            BuildStage::Path => "the files the rest of the camera path sees",
            BuildStage::Unseen => "the files no frame sees",
        }
    }
}

/// Where a cut's levels of detail come from, as a [`SourceEvent::Levels`] tells it.
#[derive(Debug, Clone, Copy)]
pub enum LevelsFrom<'a> {
    /// A store in a folder of this machine, of a dataset of `files` files.
    Store { folder: &'a Path, files: usize },
    /// A COPC file's own hierarchy: the nodes of the pages read so far, the pages not read
    /// yet, and the nodes read for the color ranges.
    Copc {
        nodes: usize,
        pages: usize,
        unread_pages: usize,
        sample_nodes: usize,
    },
    /// Node records another machine serves.
    Served,
}

/// A caller that has nothing to say of a source's steps.
pub fn quiet(_: SourceEvent<'_>) {}

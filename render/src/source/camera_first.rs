//! Camera first: the store of a dataset whose camera path sees part of it is built from the
//! files its frames see first, so the first final frame does not wait for the rest; the rest
//! is added after (`update_store`), or never.
//!
//! Which files a frame sees is decided from their headers alone. A point draws a pixel only
//! when its linear depth lies within the camera's `near..=far` and its centre projects within
//! the image widened by its side (at most the frame's point size, or
//! [`MAX_ADAPTIVE_POINT_SIZE`] for adaptive sizes) on every edge. A file whose header box
//! (every point lies in it) has all eight corners beyond one of those six planes (before the
//! near plane, past the far plane, or beyond one widened image edge) cannot draw a pixel of
//! that frame: each plane is linear in the point, so a convex box wholly beyond it has no
//! point on the near side. The frames of such files alone are the frames of every file.
//!
//! This holds where the path's cameras follow from the files' headers: keyframes (their
//! positions are given; the clip planes fit the files' box, which a store built first from
//! some files keeps, being built within the box of all of them). An automatic camera, a
//! turntable or a still one, frames the robust box of the points themselves, which only the
//! whole store knows; so does a color stretch over percentiles (intensity or elevation without
//! a fixed range). Those build the whole store first.
//!
//! The store is built in stages, each opened and cut in turn: the files the first frame sees,
//! then with the rest of the path's, then, unless asked never to, with the rest. A stage after
//! the first updates the store in its folder (its file list names what it holds), so a render
//! stopped between stages goes on from the stage it reached. Every stage's store is built
//! within the cube of all files, which `update_store` keeps: the finished store holds every
//! point in exactly one node, as a build of all files at once does.

use std::path::{Path, PathBuf};

use glam::{DVec3, DVec4};

use super::events::{BuildStage, SourceEvent};
use super::local_store::{list_files, update_earlier_store, LocalStore};
use super::SourceError;
use crate::camera::box_corners;
use crate::cloud::WorldBounds;
use crate::color::ColorMode;
use crate::cut::{StoreBuild, StoredLod};
use crate::extent::Extent;
use crate::ingest::DatasetSource;
use crate::lod::{
    AttributeSchema, BatchVisitor, BuildProgress, LodError, PointSource, PositionGrid,
};
use crate::raster::{FrameSettings, MAX_ADAPTIVE_POINT_SIZE};
use crate::request::{CameraPath, RenderRequest};

/// What happens to the files no frame of the path sees once its frames are drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BuildUnseen {
    /// They are added to the store after the frames, so it ends as a store of every file.
    #[default]
    After,
    /// They are never built: the store holds the files the path sees.
    Never,
}

impl BuildUnseen {
    pub const NAMES: [&'static str; 2] = ["after", "never"];

    /// The option as the command line names it.
    pub fn name(self) -> &'static str {
        match self {
            BuildUnseen::After => "after",
            BuildUnseen::Never => "never",
        }
    }

    /// The option a name spells.
    pub fn parse(name: &str) -> Result<Self, String> {
        match name {
            "after" => Ok(BuildUnseen::After),
            "never" => Ok(BuildUnseen::Never),
            other => Err(format!(
                "{other:?} is not when to build the unseen files: after or never"
            )),
        }
    }
}

/// A dataset's files by the order the camera path needs them in, as their places among the
/// files: those the first frame sees (and those without points), the rest of the path's, and
/// those no frame sees.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FileOrder {
    pub first: Vec<usize>,
    pub path: Vec<usize>,
    pub unseen: Vec<usize>,
}

impl FileOrder {
    /// The order of `files` (each one's header box) for the frames of `request`; `None` where
    /// the frames' cameras or colors depend on points no header tells (module doc), or
    /// every file is seen: the whole store is then built first.
    pub fn of(request: &RenderRequest, boxes: &[WorldBounds]) -> Option<Self> {
        if !Self::applies(request) {
            return None;
        }
        let all = union(boxes)?;
        let extent = Extent::whole(all).clipped(&request.render.filter).ok()?;
        let mut seen = vec![false; boxes.len()];
        let mut first = Vec::new();
        let mut path = Vec::new();
        for index in 0..request.frames() {
            let settings = request.frame_settings(index, &extent, None);
            for (place, bounds) in boxes.iter().enumerate() {
                if !seen[place] && frame_sees(&settings, bounds) {
                    seen[place] = true;
                    match index {
                        0 => first.push(place),
                        _ => path.push(place),
                    }
                }
            }
        }
        // Files without points lie nowhere: no frame sees them, and the first stage takes
        // them, for nothing.
        let nowhere: Vec<usize> = (0..boxes.len())
            .filter(|&i| !boxes[i].is_somewhere())
            .collect();
        let unseen: Vec<usize> = (0..boxes.len())
            .filter(|&i| !seen[i] && boxes[i].is_somewhere())
            .collect();
        // A path that sees nothing draws the background from any store; one that sees every
        // file needs the whole store.
        let sees_some = !first.is_empty();
        first.extend(nowhere);
        first.sort_unstable();
        (sees_some && !unseen.is_empty()).then_some(Self {
            first,
            path,
            unseen,
        })
    }

    /// The stages of the build in order, each with the places of the files its store holds
    /// (every earlier stage's too); the unseen files' stage only `after`.
    pub fn stages(&self, unseen: BuildUnseen) -> Vec<(BuildStage, Vec<usize>)> {
        let mut stages = Vec::new();
        let mut held = self.first.clone();
        stages.push((BuildStage::FirstFrame, held.clone()));
        if !self.path.is_empty() {
            held.extend(&self.path);
            stages.push((BuildStage::Path, held.clone()));
        }
        if unseen == BuildUnseen::After {
            held.extend(&self.unseen);
            stages.push((BuildStage::Unseen, held));
        }
        stages
    }
}

impl FileOrder {
    /// Whether the frames of `request` are fixed by the files' headers: keyframes, colored
    /// without a stretch over the points' percentiles. Only then are the headers read for it.
    pub fn applies(request: &RenderRequest) -> bool {
        let keyframes = matches!(request.camera_path, CameraPath::Keyframes { .. });
        let options = &request.render;
        let stretched = matches!(
            options.color_mode,
            ColorMode::Intensity | ColorMode::Elevation
        ) && options.color_range.is_none();
        keyframes && !stretched
    }
}

fn union(boxes: &[WorldBounds]) -> Option<WorldBounds> {
    // An empty file's box lies nowhere and widens nothing.
    let mut somewhere = boxes.iter().filter(|b| b.is_somewhere());
    let head = *somewhere.next()?;
    Some(somewhere.fold(head, |all, b| WorldBounds {
        min: all.min.min(b.min),
        max: all.max.max(b.max),
    }))
}

/// Whether a point inside `bounds` may draw a pixel of the frame of `settings` (module doc):
/// false only when every corner of the box lies beyond one of the frame's six planes.
pub fn frame_sees(settings: &FrameSettings, bounds: &WorldBounds) -> bool {
    if !bounds.is_somewhere() {
        return false;
    }
    // Room for the f32 rounding of positions relative to the rendering origin.
    let slack = DVec3::splat(bounds.size().max_element() * 1e-6 + 1e-6);
    let grown = WorldBounds {
        min: bounds.min - slack,
        max: bounds.max + slack,
    };
    let origin = grown.center();
    let transform = settings
        .camera
        .transform(origin, settings.width, settings.height);
    let side = match settings.adaptive_size {
        Some(_) => settings.point_size.max(MAX_ADAPTIVE_POINT_SIZE),
        None => settings.point_size,
    };
    // A whole side (twice the half side that matters) and two pixels more, in NDC.
    let reach_x = 2.0 * f64::from(side + 2) / f64::from(settings.width.max(1));
    let reach_y = 2.0 * f64::from(side + 2) / f64::from(settings.height.max(1));
    let corners: Vec<(DVec4, f64)> = box_corners(&grown)
        .iter()
        .map(|corner| {
            let p = (*corner - origin).extend(1.0);
            (transform.view_proj * p, transform.depth_row.dot(p))
        })
        .collect();
    let beyond = |outside: &dyn Fn(DVec4, f64) -> bool| {
        corners.iter().all(|&(clip, depth)| outside(clip, depth))
    };
    let planes: [&dyn Fn(DVec4, f64) -> bool; 6] = [
        &|_, depth| depth < transform.near,
        &|_, depth| depth > transform.far,
        &|clip, _| clip.x > (1.0 + reach_x) * clip.w,
        &|clip, _| -clip.x > (1.0 + reach_x) * clip.w,
        &|clip, _| clip.y > (1.0 + reach_y) * clip.w,
        &|clip, _| -clip.y > (1.0 + reach_y) * clip.w,
    ];
    !planes.iter().any(|outside| beyond(*outside))
}

/// The header box of each of `files` (widened by its rounding, as a build takes it).
pub fn file_boxes(files: &[PathBuf]) -> Result<Vec<WorldBounds>, SourceError> {
    files
        .iter()
        .map(|file| Ok(DatasetSource::open(std::slice::from_ref(file))?.bounds()))
        .collect()
}

/// A dataset's store built in stages in its folder (module doc).
pub struct StagedStore<'a> {
    pub files: &'a [PathBuf],
    /// The box of every file: each stage's store is built within its cube.
    pub bounds: WorldBounds,
    pub folder: &'a Path,
    pub memory_budget: u64,
    pub disk_budget: Option<u64>,
}

impl<'a> StagedStore<'a> {
    /// The staged store of `files` in `folder`, within the box a build of all of them takes
    /// (their headers' union, widened by its rounding), so that each stage's cube is theirs.
    pub fn new(
        files: &'a [PathBuf],
        folder: &'a Path,
        memory_budget: u64,
        disk_budget: Option<u64>,
    ) -> Result<Self, SourceError> {
        Ok(Self {
            files,
            bounds: DatasetSource::open(files)?.bounds(),
            folder,
            memory_budget,
            disk_budget,
        })
    }

    /// The store of the files at `places` (the earlier stage's, updated with the others, or
    /// built), opened for frames; `events` hears which files this stage adds.
    pub fn open_stage(
        &self,
        stage: BuildStage,
        places: &[usize],
        added: &[usize],
        events: &dyn Fn(SourceEvent<'_>),
    ) -> Result<LocalStore, SourceError> {
        let files: Vec<PathBuf> = places.iter().map(|&i| self.files[i].clone()).collect();
        let added: Vec<PathBuf> = added.iter().map(|&i| self.files[i].clone()).collect();
        events(SourceEvent::BuildingFirst {
            stage,
            files: &added,
        });
        update_earlier_store(&files, self.folder, self.memory_budget, events);
        let source = DatasetSource::open(&files)?;
        let within = WithinBounds {
            source: &source,
            bounds: self.bounds,
        };
        let progress = BuildProgress::new();
        let build = StoreBuild {
            folder: self.folder,
            memory_budget: self.memory_budget,
            disk_budget: self.disk_budget,
            on_build: &mut |points| {
                events(SourceEvent::Building {
                    points,
                    folder: self.folder,
                })
            },
            progress: &progress,
        };
        let stored = StoredLod::open_or_build_source(&within, build).map_err(SourceError::from)?;
        list_files(&files, self.folder);
        let budgets = (self.memory_budget, self.disk_budget);
        Ok(LocalStore::of_built(
            stored, &files, budgets.0, budgets.1, events,
        ))
    }
}

/// A source whose points are read as they are, in a larger box: a store of some of a
/// dataset's files built within the cube of all of them.
pub struct WithinBounds<'a> {
    pub source: &'a DatasetSource,
    pub bounds: WorldBounds,
}

impl PointSource for WithinBounds<'_> {
    fn bounds(&self) -> WorldBounds {
        let own = self.source.bounds();
        WorldBounds {
            min: self.bounds.min.min(own.min),
            max: self.bounds.max.max(own.max),
        }
    }

    fn point_count(&self) -> u64 {
        self.source.point_count()
    }

    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError> {
        self.source.for_each_batch(visit)
    }

    fn position_grid(&self) -> Option<PositionGrid> {
        self.source.position_grid()
    }

    /// The files' and the box's: a build stopped part way resumes only within the same cube.
    fn fingerprint(&self) -> Option<String> {
        let bounds = self.bounds();
        let files = self.source.fingerprint()?;
        Some(format!(
            "{files}within {:?} {:?}",
            bounds.min.to_array(),
            bounds.max.to_array()
        ))
    }

    fn part_starts(&self) -> Vec<u64> {
        self.source.part_starts()
    }

    fn for_each_batch_from(
        &self,
        first: u64,
        visit: &mut BatchVisitor<'_>,
    ) -> Result<(), LodError> {
        self.source.for_each_batch_from(first, visit)
    }

    fn attributes(&self) -> Option<AttributeSchema> {
        self.source.attributes()
    }
}

#[cfg(test)]
mod tests;

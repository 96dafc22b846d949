//! A dataset's files as a level-of-detail [`PointSource`]: read batch by batch, file after
//! file, in world coordinates with their raw attributes, never held whole.

use std::path::PathBuf;

use glam::DVec3;

use super::contain::contain_panics;
use super::read::{usable, DatasetFile};
use super::IngestError;
use crate::cloud::WorldBounds;
use crate::lod::{BatchColumns, LodError, PointBatch, PointSource};

/// The files of a dataset, checked, as a source the level-of-detail builder reads twice.
pub struct DatasetSource {
    files: Vec<DatasetFile>,
    bounds: WorldBounds,
    points: u64,
    has_rgb: bool,
}

impl DatasetSource {
    /// Checks every file (the same pre-parse as a load); the bounds are the union of their
    /// headers', widened by their rounding. A file whose header bounds are unusable is an
    /// error naming it: the builder needs bounds before it reads a point.
    pub fn open(paths: &[PathBuf]) -> Result<Self, IngestError> {
        let files = DatasetFile::check_all(paths)?;
        if let Some(file) = files.iter().find(|file| !usable(&file.header_bounds)) {
            return Err(IngestError::Corrupt {
                path: file.path.clone(),
                what: "its header bounds are not finite or inverted".into(),
            });
        }
        let union = files
            .iter()
            .map(|file| file.header_bounds)
            .reduce(|a, b| WorldBounds {
                min: a.min.min(b.min),
                max: a.max.max(b.max),
            })
            .unwrap_or(files[0].header_bounds);
        // Header bounds are rounded to the files' scales; allow for that and a little more.
        let slack = DVec3::splat(1e-3) + union.size().abs() * 1e-9;
        Ok(Self {
            points: files.iter().map(|file| file.facts.declared_points).sum(),
            has_rgb: files.iter().all(|file| file.has_color),
            bounds: WorldBounds {
                min: union.min - slack,
                max: union.max + slack,
            },
            files,
        })
    }
}

/// Fills `columns` with a decoded batch (its RGB only `with_rgb`).
fn fill(columns: &mut BatchColumns, batch: &las::PointData, with_rgb: bool) {
    columns.clear();
    columns.positions.extend(
        batch
            .x()
            .zip(batch.y())
            .zip(batch.z())
            .map(|((x, y), z)| DVec3::new(x, y, z)),
    );
    if let (true, Some(rgb)) = (with_rgb, batch.rgb()) {
        columns.rgb.extend(rgb.map(|(r, g, b)| [r, g, b]));
    }
    columns.intensity.extend(batch.intensity());
    columns.classification.extend(batch.classification());
    columns.return_number.extend(batch.return_number());
}

impl PointSource for DatasetSource {
    fn bounds(&self) -> WorldBounds {
        self.bounds
    }

    fn point_count(&self) -> u64 {
        self.points
    }

    fn for_each_batch(
        &self,
        visit: &mut dyn FnMut(PointBatch<'_>) -> Result<(), LodError>,
    ) -> Result<(), LodError> {
        let mut columns = BatchColumns::default();
        for file in &self.files {
            // The visitor's error stops the read; it is kept apart from the file's errors.
            let mut stopped = None;
            let read = contain_panics(&file.path, || {
                file.for_each_batch(|batch| {
                    fill(&mut columns, batch, self.has_rgb);
                    match visit(columns.batch(self.has_rgb)) {
                        Ok(()) => Ok(()),
                        Err(error) => {
                            stopped = Some(error);
                            Err(IngestError::Corrupt {
                                path: file.path.clone(),
                                what: "reading stopped".into(),
                            })
                        }
                    }
                })
            });
            if let Some(error) = stopped {
                return Err(error);
            }
            read.map_err(|error| LodError::Source(error.to_string()))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ingest::{load_dataset, write_las, LasWriteOptions};
    use crate::lod::{build_lod, LodBuildOptions, LodStore};
    use crate::sample::sample_scene;

    #[test]
    fn the_files_of_a_dataset_build_a_hierarchy_holding_every_point_once() {
        let dir = tempfile::tempdir().expect("tempdir");
        let scene = sample_scene(30_000, 4);
        let half = scene.len() / 2;
        let (a, b) = (dir.path().join("a.laz"), dir.path().join("b.las"));
        let first: Vec<usize> = (0..half).collect();
        let second: Vec<usize> = (half..scene.len()).collect();
        write_las(&a, &scene.select(&first), &LasWriteOptions::default()).expect("a");
        write_las(&b, &scene.select(&second), &LasWriteOptions::default()).expect("b");
        let files = [a, b];

        let source = DatasetSource::open(&files).expect("open");
        assert_eq!(source.point_count(), scene.len() as u64);
        let loaded = load_dataset(&files).expect("load");
        assert!(source.bounds().min.cmple(loaded.bounds.min).all());
        assert!(loaded.bounds.max.cmple(source.bounds().max).all());

        let db = sled::Config::new().temporary(true).open().expect("sled");
        let store = LodStore::open(
            db.open_tree("lod").expect("tree"),
            dir.path().join("lod.bin"),
        )
        .expect("store");
        let mut options = LodBuildOptions::new(dir.path().join("spill"));
        options.max_leaf_points = 4_000;
        let report = build_lod(&source, &store, &options).expect("build");
        let hierarchy = store.read_hierarchy().expect("hierarchy");
        assert_eq!(hierarchy.point_count, scene.len() as u64);
        let stored: u64 = hierarchy
            .nodes()
            .iter()
            .map(|node| store.read_node(&hierarchy, node.key).expect("node").len() as u64)
            .sum();
        assert_eq!(
            stored,
            scene.len() as u64,
            "every point in exactly one node"
        );
        assert!(hierarchy.stats.has_rgb);
        assert!(report.hierarchy.nodes().len() > 1);
    }

    #[test]
    fn a_bad_file_fails_the_source_naming_it() {
        let dir = tempfile::tempdir().expect("tempdir");
        let bad = dir.path().join("bad.las");
        std::fs::write(&bad, b"LASF and nothing else").expect("write");
        let error = DatasetSource::open(&[bad]).err().expect("a bad file");
        assert!(error.to_string().contains("bad.las"), "{error}");
    }
}

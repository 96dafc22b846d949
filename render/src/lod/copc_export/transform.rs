//! `ExportTransform`: how exported positions become LAS's 32-bit integers (scale and offset
//! per axis).
//!
//! The store keeps positions far finer than any source file (30 bits within each node's
//! cube) but not the files' scales, so the export takes them from the dataset's files when
//! it has them: the finest scale per axis among the files and the first file's offset. A
//! point of a file with that scale and offset is then written with exactly the integers it
//! was read from (the store's step is orders of magnitude below half a scale step). Without
//! the files the scale is a fixed millimetre ([`DEFAULT_SCALE`]) and the offset the cube's
//! corner on that grid.

use std::fs::File;
use std::io::BufReader;
use std::path::PathBuf;

use glam::DVec3;

use super::error::CopcExportError;
use crate::lod::RootCube;

/// The files among `paths` that decide an export ([`crate::ingest::deciding`]); a file whose
/// header cannot be read stays among them, for the export to say why.
pub(super) fn deciding_paths(paths: &[PathBuf]) -> Vec<PathBuf> {
    let points =
        |path: &PathBuf| crate::ingest::FileInfo::read(path).map_or(u64::MAX, |i| i.points);
    crate::ingest::deciding(paths, points)
        .into_iter()
        .cloned()
        .collect()
}

/// The scale when the dataset's files are not at hand: one millimetre.
pub const DEFAULT_SCALE: f64 = 0.001;

/// The smallest scale accepted from a file: below it a real scan's coordinates overflow.
const MIN_SCALE: f64 = 1e-9;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExportTransform {
    pub scale: DVec3,
    pub offset: DVec3,
}

impl ExportTransform {
    /// Millimetre steps from the cube's corner (rounded down to whole steps).
    pub fn fixed(cube: &RootCube) -> Self {
        let scale = DVec3::splat(DEFAULT_SCALE);
        Self {
            scale,
            offset: (cube.min / scale).floor() * scale,
        }
    }

    /// The finest scale per axis among `paths`' headers and the first file's offset; `None`
    /// for no files.
    pub fn of_files(paths: &[PathBuf]) -> Result<Option<Self>, CopcExportError> {
        let mut found: Option<Self> = None;
        for path in paths {
            let fail = |reason: String| CopcExportError::SourceHeader {
                path: path.clone(),
                reason,
            };
            let file = File::open(path).map_err(|e| fail(e.to_string()))?;
            let header = las::raw::Header::read_from(BufReader::new(file))
                .map_err(|e| fail(e.to_string()))?;
            let scale = DVec3::new(
                header.x_scale_factor,
                header.y_scale_factor,
                header.z_scale_factor,
            );
            let offset = DVec3::new(header.x_offset, header.y_offset, header.z_offset);
            if !scale.is_finite() || scale.min_element() < MIN_SCALE || !offset.is_finite() {
                return Err(fail(format!(
                    "scale {scale:?} or offset {offset:?} is not usable"
                )));
            }
            found = Some(match found {
                None => Self { scale, offset },
                Some(t) => Self {
                    scale: t.scale.min(scale),
                    offset: t.offset,
                },
            });
        }
        Ok(found)
    }

    /// This transform when `cube` fits 32-bit integers under it; else the same scale with the
    /// offset at the cube's centre; else an error.
    pub fn fitted(self, cube: &RootCube) -> Result<Self, CopcExportError> {
        if self.fits(cube) {
            return Ok(self);
        }
        let centre = cube.min + DVec3::splat(cube.side / 2.0);
        let centred = Self {
            scale: self.scale,
            offset: (centre / self.scale).round() * self.scale,
        };
        if centred.fits(cube) {
            return Ok(centred);
        }
        Err(CopcExportError::ScaleTooFine {
            min: cube.min.to_array(),
            max: (cube.min + DVec3::splat(cube.side)).to_array(),
            scale: self.scale.to_array(),
        })
    }

    fn fits(&self, cube: &RootCube) -> bool {
        let limit = f64::from(i32::MAX) - 1.0;
        let low = (cube.min - self.offset) / self.scale;
        let high = (cube.min + DVec3::splat(cube.side) - self.offset) / self.scale;
        low.abs().max_element() < limit && high.abs().max_element() < limit
    }

    /// The integers of world position `v`, each rounded to the nearest step. Callers
    /// use only positions inside a fitted cube.
    pub(crate) fn to_integer(self, v: DVec3) -> [i32; 3] {
        let q = ((v - self.offset) / self.scale).round();
        [q.x as i32, q.y as i32, q.z as i32]
    }

    /// The world position an integer triple stands for.
    pub(crate) fn to_world(self, q: [i32; 3]) -> DVec3 {
        DVec3::new(f64::from(q[0]), f64::from(q[1]), f64::from(q[2])) * self.scale + self.offset
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_offset_too_far_moves_to_the_centre_and_a_scale_too_fine_is_refused() {
        let cube = RootCube {
            min: DVec3::new(600_000.0, 4_000_000.0, 10.0),
            side: 2_000.0,
        };
        let far = ExportTransform {
            scale: DVec3::splat(0.001),
            offset: DVec3::ZERO,
        };
        let fitted = far.fitted(&cube).expect("fits at the centre");
        assert_eq!(fitted.offset, DVec3::new(601_000.0, 4_001_000.0, 1_010.0));
        let q = fitted.to_integer(cube.min);
        assert!((fitted.to_world(q) - cube.min).abs().max_element() < 1e-9);
        let fine = ExportTransform {
            scale: DVec3::splat(1e-7),
            offset: DVec3::ZERO,
        };
        assert!(matches!(
            fine.fitted(&cube),
            Err(CopcExportError::ScaleTooFine { .. })
        ));
        assert!(ExportTransform::fixed(&cube).fits(&cube));
    }
}

//! Which points a render draws: by classification, return number, intensity range and a clip
//! box in world coordinates.
//!
//! A filter is applied to the points before they reach the GPU (the resident cloud once, each
//! node of a cut as it is prepared), so the point passes never see what it drops. Colors are
//! chosen before filtering, with the ranges of the whole dataset, so a filtered view keeps the
//! colors of the unfiltered one. The attribute filters keep the camera the whole dataset
//! would get, so layers rendered apart (ground, buildings, vegetation) line up; a clip box
//! frames what lies inside it.

use std::fmt;

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::cloud::{PointCloud, WorldBounds};
use crate::lod::NodePoints;

/// The highest return number a LAS file can hold (four bits in point formats 6 to 10).
pub const MAX_RETURN_NUMBER: u8 = 15;

/// A set of one-byte codes (classes, return numbers). Stored as the list of its codes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(from = "Vec<u8>", into = "Vec<u8>")]
pub struct CodeSet {
    bits: [u64; 4],
}

impl CodeSet {
    pub fn of(codes: impl IntoIterator<Item = u8>) -> Self {
        let mut set = Self::default();
        for code in codes {
            set.bits[usize::from(code >> 6)] |= 1 << (code & 63);
        }
        set
    }

    pub fn contains(&self, code: u8) -> bool {
        self.bits[usize::from(code >> 6)] & (1 << (code & 63)) != 0
    }

    pub fn is_empty(&self) -> bool {
        self.bits == [0; 4]
    }

    /// Every code not in the set.
    pub fn complement(&self) -> Self {
        Self {
            bits: self.bits.map(|word| !word),
        }
    }

    /// The codes in the set, lowest first.
    pub fn codes(&self) -> Vec<u8> {
        (0..=u8::MAX).filter(|&code| self.contains(code)).collect()
    }

    /// The highest code in the set.
    pub fn max(&self) -> Option<u8> {
        (0..=u8::MAX).rev().find(|&code| self.contains(code))
    }
}

impl From<Vec<u8>> for CodeSet {
    fn from(codes: Vec<u8>) -> Self {
        Self::of(codes)
    }
}

impl From<CodeSet> for Vec<u8> {
    fn from(set: CodeSet) -> Self {
        set.codes()
    }
}

/// Raw intensities from `min` to `max`, both kept.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct IntensityRange {
    pub min: u16,
    pub max: u16,
}

/// A box in world coordinates (the file's, before recentring): points on its faces are kept.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ClipBox {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl ClipBox {
    fn contains(&self, p: DVec3) -> bool {
        p.cmpge(DVec3::from(self.min)).all() && p.cmple(DVec3::from(self.max)).all()
    }

    /// Whether the box shares any point with the cube at `min` with side `side`.
    pub fn meets_cube(&self, min: DVec3, side: f64) -> bool {
        let max = min + DVec3::splat(side);
        max.cmpge(DVec3::from(self.min)).all() && min.cmple(DVec3::from(self.max)).all()
    }
}

impl fmt::Display for ClipBox {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [x0, y0, z0] = self.min;
        let [x1, y1, z1] = self.max;
        write!(f, "x {x0} .. {x1}, y {y0} .. {y1}, z {z0} .. {z1}")
    }
}

/// Which points are drawn; the default keeps every point. Each part that is present must be
/// passed (classes and returns: the point's code is in the set).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct PointFilter {
    #[serde(default)]
    pub classes: Option<CodeSet>,
    #[serde(default)]
    pub return_numbers: Option<CodeSet>,
    #[serde(default)]
    pub intensity: Option<IntensityRange>,
    #[serde(default)]
    pub clip: Option<ClipBox>,
}

/// A filter that cannot apply to a dataset.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FilterError {
    #[error("the clip box ({clip}) lies outside the dataset's bounds ({bounds})")]
    ClipOutside { clip: ClipBox, bounds: ClipBox },
}

impl PointFilter {
    /// Whether every point passes.
    pub fn keeps_everything(&self) -> bool {
        *self == Self::default()
    }

    /// Whether it reads a point's classification, return number or intensity (a clip box
    /// reads only its position).
    pub fn reads_attributes(&self) -> bool {
        self.classes.is_some() || self.return_numbers.is_some() || self.intensity.is_some()
    }

    /// Whether a point with these attributes passes the classification, return and intensity
    /// filters.
    fn keeps_attributes(&self, classification: u8, return_number: u8, intensity: u16) -> bool {
        self.classes.is_none_or(|set| set.contains(classification))
            && self
                .return_numbers
                .is_none_or(|set| set.contains(return_number))
            && self
                .intensity
                .is_none_or(|range| (range.min..=range.max).contains(&intensity))
    }

    /// Whether a point at world position `position` with these attributes is drawn.
    pub fn keeps(
        &self,
        position: DVec3,
        classification: u8,
        return_number: u8,
        intensity: u16,
    ) -> bool {
        self.keeps_attributes(classification, return_number, intensity)
            && self.clip.is_none_or(|clip| clip.contains(position))
    }

    /// What the automatic camera frames for a dataset with `bounds`: the bounds, within the
    /// clip box when there is one. A box that misses the bounds is refused: nothing would be
    /// drawn.
    pub fn framing_bounds(&self, bounds: &WorldBounds) -> Result<WorldBounds, FilterError> {
        let Some(clip) = self.clip else {
            return Ok(*bounds);
        };
        let min = bounds.min.max(DVec3::from(clip.min));
        let max = bounds.max.min(DVec3::from(clip.max));
        if min.cmpgt(max).any() {
            return Err(FilterError::ClipOutside {
                clip,
                bounds: ClipBox {
                    min: bounds.min.to_array(),
                    max: bounds.max.to_array(),
                },
            });
        }
        Ok(WorldBounds { min, max })
    }

    /// Keeps only the points of `cloud` that pass, in place and in their order; the cloud's
    /// bounds become [`framing_bounds`](Self::framing_bounds). Returns how many were kept.
    pub fn apply(&self, cloud: &mut PointCloud) -> Result<usize, FilterError> {
        let framing = self.framing_bounds(&cloud.bounds)?;
        if self.keeps_everything() {
            return Ok(cloud.len());
        }
        let mut kept = 0;
        for i in 0..cloud.len() {
            let position = cloud.origin + cloud.positions[i].as_dvec3();
            if !self.keeps(
                position,
                cloud.classification[i],
                cloud.return_number[i],
                cloud.intensity[i],
            ) {
                continue;
            }
            cloud.positions[kept] = cloud.positions[i];
            cloud.colors[kept] = cloud.colors[i];
            cloud.intensity[kept] = cloud.intensity[i];
            cloud.classification[kept] = cloud.classification[i];
            cloud.return_number[kept] = cloud.return_number[i];
            kept += 1;
        }
        cloud.positions.truncate(kept);
        cloud.colors.truncate(kept);
        cloud.intensity.truncate(kept);
        cloud.classification.truncate(kept);
        cloud.return_number.truncate(kept);
        cloud.bounds = framing;
        Ok(kept)
    }

    /// The indices of the points of `node` that pass, in order; `None` when all of them do
    /// (nothing is filtered, or the node lies inside the clip box and no attribute drops any).
    pub fn node_points(&self, node: &NodePoints) -> Option<Vec<u32>> {
        if self.keeps_everything() {
            return None;
        }
        let inside = |q: &[u32; 3]| match self.clip {
            None => true,
            Some(clip) => {
                clip.contains(node.cube_min + (DVec3::from(q.map(f64::from)) + 0.5) * node.step)
            }
        };
        let kept: Vec<u32> = (0..node.len())
            .filter(|&i| {
                self.keeps_attributes(
                    node.classification[i],
                    node.return_number[i],
                    node.intensity[i],
                ) && inside(&node.quantised[i])
            })
            .map(|i| i as u32)
            .collect();
        (kept.len() < node.len()).then_some(kept)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloud::pack_rgba8;

    #[test]
    fn code_sets_hold_every_byte() {
        let set = CodeSet::of([0, 2, 63, 64, 255]);
        assert_eq!(set.codes(), vec![0, 2, 63, 64, 255]);
        assert!(!set.contains(1) && !set.contains(254));
        assert_eq!(set.max(), Some(255));
        assert_eq!(set.complement().codes().len(), 251);
        assert!(set.complement().contains(1) && !set.complement().contains(64));
        let json = serde_json::to_string(&set).expect("valid");
        assert_eq!(json, "[0,2,63,64,255]");
        assert_eq!(serde_json::from_str::<CodeSet>(&json).expect("valid"), set);
    }

    fn cloud() -> PointCloud {
        let points: Vec<DVec3> = (0..10)
            .map(|i| DVec3::new(500_000.0 + f64::from(i), 4_000_000.0, 100.0 + f64::from(i)))
            .collect();
        let colors = (0..10).map(|i| pack_rgba8(i, 0, 0)).collect();
        let mut cloud = PointCloud::from_world_points(&points, colors);
        cloud.classification = (0..10).map(|i| if i % 2 == 0 { 2 } else { 6 }).collect();
        cloud.return_number = (0..10).map(|i| 1 + (i % 3)).collect();
        cloud.intensity = (0..10).map(|i| i as u16 * 100).collect();
        cloud
    }

    /// The red channel of the kept points names which they are.
    fn kept(cloud: &PointCloud) -> Vec<u32> {
        cloud.colors.iter().map(|c| c & 0xff).collect()
    }

    #[test]
    fn attributes_and_the_box_each_drop_points() {
        let cases: [(PointFilter, Vec<u32>); 5] = [
            (PointFilter::default(), (0..10).collect()),
            (
                PointFilter {
                    classes: Some(CodeSet::of([6])),
                    ..Default::default()
                },
                vec![1, 3, 5, 7, 9],
            ),
            (
                PointFilter {
                    return_numbers: Some(CodeSet::of([1])),
                    ..Default::default()
                },
                vec![0, 3, 6, 9],
            ),
            (
                PointFilter {
                    intensity: Some(IntensityRange { min: 250, max: 500 }),
                    ..Default::default()
                },
                vec![3, 4, 5],
            ),
            (
                PointFilter {
                    classes: Some(CodeSet::of([2])),
                    clip: Some(ClipBox {
                        min: [500_002.0, 3_999_999.0, 0.0],
                        max: [500_006.0, 4_000_001.0, 1e4],
                    }),
                    ..Default::default()
                },
                vec![2, 4, 6],
            ),
        ];
        for (filter, expected) in cases {
            let mut c = cloud();
            let all = c.bounds;
            let count = filter.apply(&mut c).expect("inside");
            assert_eq!(kept(&c), expected, "{filter:?}");
            assert_eq!(count, expected.len());
            assert_eq!(c.intensity.len(), count);
            if filter.clip.is_none() {
                assert_eq!(c.bounds, all, "attribute filters keep the framing");
            }
        }
    }

    #[test]
    fn a_clip_box_frames_its_part_and_one_outside_is_refused() {
        let c = cloud();
        let inside = PointFilter {
            clip: Some(ClipBox {
                min: [0.0, 0.0, 103.0],
                max: [1e7, 1e7, 1e7],
            }),
            ..Default::default()
        };
        let framed = inside.framing_bounds(&c.bounds).expect("valid");
        assert_eq!(framed.min, DVec3::new(500_000.0, 4_000_000.0, 103.0));
        assert_eq!(framed.max, c.bounds.max);
        let outside = PointFilter {
            clip: Some(ClipBox {
                min: [0.0, 0.0, 0.0],
                max: [10.0, 10.0, 10.0],
            }),
            ..Default::default()
        };
        let error = outside
            .framing_bounds(&c.bounds)
            .expect_err("refused")
            .to_string();
        assert!(
            error.contains("lies outside the dataset's bounds"),
            "{error}"
        );
    }
}

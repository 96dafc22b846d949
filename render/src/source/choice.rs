//! Where a frame's points come from: read whole and resident, or a cut through levels of
//! detail (a store's, or a COPC file's own hierarchy). One decision, which a local render, the
//! daemon and a worker that keeps its own stores all make, so a dataset renders the same way
//! here and through a server.

use crate::cut::RESIDENT_MAX_POINTS;

/// The ways a frame's points come.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FramePoints {
    /// The dataset read whole and uploaded once, every frame drawing all of it.
    Resident,
    /// A cut per frame through the dataset's level-of-detail store (built when missing).
    StoreCut,
    /// A cut per frame through the COPC file's own hierarchy: nothing is built.
    CopcCut,
}

impl FramePoints {
    /// Whether frames are cuts through levels of detail, not the resident dataset.
    pub fn is_cut(self) -> bool {
        self != Self::Resident
    }
}

/// The facts of a dataset and of a request that decide how its frames' points come.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PointSourceFacts {
    /// The dataset's points; `None` when not counted (the decision then rests on the rest).
    pub points: Option<u64>,
    /// Whether the dataset is one COPC file.
    pub one_copc_file: bool,
    /// Whether the dataset's level-of-detail store is built already.
    pub store_built: bool,
    /// Whether the request asks for levels of detail: a pixel error, or node-cache budgets.
    pub levels_of_detail_asked: bool,
}

impl PointSourceFacts {
    /// How the frames' points come: [`frame_points`].
    pub fn frame_points(&self) -> FramePoints {
        frame_points(self)
    }
}

/// How the frames of a dataset with `facts` get their points.
///
/// A COPC file is always cut from its own hierarchy: it is levels of detail already, and a
/// cut reads only the chunks a frame needs. Any other dataset is cut from its store when the
/// request asks for levels of detail, when it has more than [`RESIDENT_MAX_POINTS`] points
/// (too many to read whole, and a build is worth its time), or when its store is built already
/// (nothing to build, and a cut reads only what the frame needs); otherwise it is rendered
/// resident, which for a small dataset is faster than building a store first.
pub fn frame_points(facts: &PointSourceFacts) -> FramePoints {
    if facts.one_copc_file {
        return FramePoints::CopcCut;
    }
    let large = facts.points.is_some_and(|p| p > RESIDENT_MAX_POINTS);
    if facts.levels_of_detail_asked || large || facts.store_built {
        FramePoints::StoreCut
    } else {
        FramePoints::Resident
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_point_source_follows_the_one_rule() {
        use FramePoints::{CopcCut, Resident, StoreCut};
        let small = Some(RESIDENT_MAX_POINTS);
        let large = Some(RESIDENT_MAX_POINTS + 1);
        // (points, one COPC file, store built, levels of detail asked) -> the source.
        let table = [
            (small, false, false, false, Resident),
            (None, false, false, false, Resident),
            (Some(0), false, false, false, Resident),
            (small, false, false, true, StoreCut),
            (small, false, true, false, StoreCut),
            (None, false, true, false, StoreCut),
            (None, false, false, true, StoreCut),
            (large, false, false, false, StoreCut),
            (large, false, true, true, StoreCut),
            (Some(u64::MAX), false, false, false, StoreCut),
            (small, true, false, false, CopcCut),
            (large, true, false, false, CopcCut),
            (None, true, true, true, CopcCut),
            (Some(0), true, false, false, CopcCut),
        ];
        for (points, one_copc_file, store_built, levels_of_detail_asked, expected) in table {
            let facts = PointSourceFacts {
                points,
                one_copc_file,
                store_built,
                levels_of_detail_asked,
            };
            assert_eq!(frame_points(&facts), expected, "{facts:?}");
            assert_eq!(facts.frame_points(), expected, "{facts:?}");
            assert_eq!(expected.is_cut(), expected != Resident);
        }
    }
}

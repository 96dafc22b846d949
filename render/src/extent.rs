//! Where a dataset's points lie, as its frames are fitted to them: the box of every point, and
//! the robust box the automatic camera frames, which a few stray points do not stretch.
//!
//! A scan's header box, or even the box of its points, is decided by its most extreme points:
//! a few returns from birds or a misplaced batch of points put the subject in a corner or shrink
//! it to a dot. The robust box takes per axis the 0.5th to 99.5th percentile of an even sample of
//! the points and widens it to the points that continue from there without a gap wider than
//! [`GAP`] of its longest side, so that a subject's sparse edges stay in it and points set apart
//! from it do not. Its outline, the sampled points inside it that lie outermost in each of
//! [`OUTLINE_DIRECTIONS`] directions, is what the automatic camera fits to: a cloud seldom
//! fills its box's corners, so a camera fitted to them leaves the cloud small and off centre.

use glam::{DVec3, Vec3};

use crate::camera::box_corners;
use crate::cloud::WorldBounds;
use crate::filter::{FilterError, PointFilter};

/// The share of the sample each side of the percentile box, per axis.
const TAIL: f64 = 0.005;
/// The widest gap between sorted coordinates, as a share of the percentile box's longest side,
/// across which the robust box still grows.
const GAP: f64 = 0.05;
/// Directions, spread evenly over the sphere, in which the outline takes the outermost point.
const OUTLINE_DIRECTIONS: usize = 96;
/// Sampled points the outline is chosen from, at most.
const OUTLINE_SAMPLE: usize = 1 << 16;

/// A dataset's extent: what explicit cameras' clip planes enclose and what the automatic camera
/// frames.
#[derive(Debug, Clone, PartialEq)]
pub struct Extent {
    /// The box of every point (the header's, or the points' own).
    pub all: WorldBounds,
    /// The box most points lie in, stray points left out; inside `all`.
    pub robust: WorldBounds,
    /// Points of the robust box, world coordinates, that a camera sees all of when it sees
    /// these: the sample's outermost (module doc), or the box's corners.
    pub outline: Vec<DVec3>,
}

impl Extent {
    /// An extent nothing is known of but its box: the automatic camera frames all of it.
    pub fn whole(all: WorldBounds) -> Self {
        Self {
            all,
            robust: all,
            outline: box_corners(&all).to_vec(),
        }
    }

    /// The extent of a dataset whose points lie in `all`, its robust box from `sample` (an even
    /// sample of its points, relative to `origin`); `all` itself when the sample is empty.
    pub fn of_sample(all: WorldBounds, origin: DVec3, sample: &[Vec3]) -> Self {
        let Some((lo, hi, _)) = robust_box(sample) else {
            return Self::whole(all);
        };
        Self::within(all, origin, lo, hi, sample)
    }

    /// [`Extent::of_sample`], the robust box then widened to the points of `positions` (every
    /// point of the dataset, relative to `origin`) that lie within a gap of it.
    pub fn of_points(all: WorldBounds, origin: DVec3, sample: &[Vec3], positions: &[Vec3]) -> Self {
        let Some((mut lo, mut hi, gap)) = robust_box(sample) else {
            return Self::whole(all);
        };
        let gap32 = gap as f32;
        for p in positions.iter().filter(|p| p.is_finite()) {
            let below = p.cmplt(lo) & p.cmpge(lo - gap32);
            let above = p.cmpgt(hi) & p.cmple(hi + gap32);
            lo = Vec3::select(below, *p, lo);
            hi = Vec3::select(above, *p, hi);
        }
        Self::within(all, origin, lo, hi, sample)
    }

    /// The robust box `lo..hi` (relative to `origin`) in world coordinates, inside `all`, and
    /// its outline from `sample`.
    fn within(all: WorldBounds, origin: DVec3, lo: Vec3, hi: Vec3, sample: &[Vec3]) -> Self {
        let min = (origin + lo.as_dvec3()).clamp(all.min, all.max);
        let max = (origin + hi.as_dvec3()).clamp(all.min, all.max);
        let robust = WorldBounds { min, max };
        // Positions are f32 offsets from the origin: the points that decide the box round to
        // either side of the header's box, which the robust box is clamped to, and the outline
        // must not lose them for it.
        let rounding = f64::from(lo.abs().max(hi.abs()).max_element() * f32::EPSILON) * 2.0;
        let slack = DVec3::splat(rounding + (max - min).max_element() * 1e-6);
        let kept = WorldBounds {
            min: min - slack,
            max: max + slack,
        };
        let inside = sample.iter().map(|p| origin + p.as_dvec3());
        Self {
            all,
            robust,
            outline: outline(&robust, &kept, inside),
        }
    }

    /// This extent as `filter`'s clip box leaves it. The robust box is the clipped one unless
    /// the clip box lies wholly among the stray points, where the clipped box of every point is
    /// framed instead.
    pub fn clipped(&self, filter: &PointFilter) -> Result<Self, FilterError> {
        let all = filter.framing_bounds(&self.all)?;
        let robust = filter.framing_bounds(&self.robust).unwrap_or(all);
        if robust == self.robust {
            return Ok(Self {
                all,
                ..self.clone()
            });
        }
        Ok(Self {
            all,
            robust,
            outline: outline(&robust, &robust, self.outline.iter().copied()),
        })
    }
}

/// An extent reads as the box of every point, so that code that prints or checks a dataset's
/// bounds keeps doing so while [`crate::request::RenderRequest`] takes the whole extent.
impl std::ops::Deref for Extent {
    type Target = WorldBounds;

    fn deref(&self) -> &WorldBounds {
        &self.all
    }
}

/// What a request's frames are fitted to: an [`Extent`], or a box that is framed whole.
pub trait Framed {
    fn extent(&self) -> Extent;
}

impl Framed for Extent {
    fn extent(&self) -> Extent {
        self.clone()
    }
}

impl Framed for WorldBounds {
    fn extent(&self) -> Extent {
        Extent::whole(*self)
    }
}

/// The outermost of `points` inside `kept` (the robust box, or a hair wider) in each of
/// [`OUTLINE_DIRECTIONS`] directions (a Fibonacci sphere's), at most [`OUTLINE_SAMPLE`] of
/// them taken evenly; the robust box's corners when none lies inside.
fn outline(
    robust: &WorldBounds,
    kept: &WorldBounds,
    points: impl Iterator<Item = DVec3>,
) -> Vec<DVec3> {
    let center = robust.center();
    let inside: Vec<DVec3> = points
        .filter(|p| p.cmpge(kept.min).all() && p.cmple(kept.max).all())
        .map(|p| p - center)
        .collect();
    if inside.is_empty() {
        return box_corners(robust).to_vec();
    }
    let step = inside.len().div_ceil(OUTLINE_SAMPLE);
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let mut chosen: Vec<DVec3> = (0..OUTLINE_DIRECTIONS)
        .map(|k| {
            let z = 1.0 - 2.0 * (k as f64 + 0.5) / OUTLINE_DIRECTIONS as f64;
            let (sin, cos) = (golden * k as f64).sin_cos();
            let r = (1.0 - z * z).sqrt();
            DVec3::new(r * cos, r * sin, z)
        })
        .map(|direction| {
            inside
                .iter()
                .step_by(step)
                .copied()
                .max_by(|a, b| a.dot(direction).total_cmp(&b.dot(direction)))
                .unwrap_or(DVec3::ZERO)
        })
        .collect();
    chosen.sort_by(|a, b| a.to_array().partial_cmp(&b.to_array()).expect("finite"));
    chosen.dedup();
    chosen.into_iter().map(|p| p + center).collect()
}

/// The robust box of `sample` (module doc) and the gap it grows across; `None` without a finite
/// point.
fn robust_box(sample: &[Vec3]) -> Option<(Vec3, Vec3, f64)> {
    let finite: Vec<Vec3> = sample.iter().copied().filter(|p| p.is_finite()).collect();
    if finite.is_empty() {
        return None;
    }
    let mut axes: [Vec<f32>; 3] =
        std::array::from_fn(|axis| finite.iter().map(|p| p[axis]).collect());
    let n = finite.len();
    let skipped = (TAIL * (n - 1) as f64).floor() as usize;
    let mut percentiles = [(0.0f32, 0.0f32); 3];
    for (axis, values) in axes.iter_mut().enumerate() {
        values.sort_unstable_by(f32::total_cmp);
        percentiles[axis] = (values[skipped], values[n - 1 - skipped]);
    }
    let longest = percentiles
        .iter()
        .map(|&(lo, hi)| f64::from(hi - lo))
        .fold(0.0, f64::max);
    let gap = longest * GAP;
    let (mut lo, mut hi) = (Vec3::ZERO, Vec3::ZERO);
    for (axis, values) in axes.iter().enumerate() {
        // From the percentiles outwards while the next coordinate is within the gap.
        let mut first = skipped;
        while first > 0 && f64::from(values[first] - values[first - 1]) <= gap {
            first -= 1;
        }
        let mut last = n - 1 - skipped;
        while last + 1 < n && f64::from(values[last + 1] - values[last]) <= gap {
            last += 1;
        }
        lo[axis] = values[first];
        hi[axis] = values[last];
    }
    Some((lo, hi, gap))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn everything() -> WorldBounds {
        WorldBounds {
            min: DVec3::splat(-1e8),
            max: DVec3::splat(1e8),
        }
    }

    /// A 100 x 50 grid of points 1 apart on a gentle slope, from the origin.
    fn terrain() -> Vec<Vec3> {
        (0..5000)
            .map(|i| {
                let (x, y) = ((i % 100) as f32, (i / 100) as f32);
                Vec3::new(x, y, 0.1 * x)
            })
            .collect()
    }

    fn assert_near(actual: DVec3, expected: DVec3) {
        assert!(actual.abs_diff_eq(expected, 1e-4), "{actual} != {expected}");
    }

    #[test]
    fn stray_points_are_left_out() {
        let mut points = terrain();
        points.extend([
            Vec3::new(5000.0, 20.0, 3.0),
            Vec3::new(-800.0, -900.0, 1000.0),
            Vec3::new(40.0, 20.0, -3000.0),
        ]);
        let origin = DVec3::new(500_000.0, 4_000_000.0, 100.0);
        let extent = Extent::of_sample(everything(), origin, &points);
        assert_near(extent.robust.min, origin + DVec3::new(0.0, 0.0, 0.0));
        assert_near(extent.robust.max, origin + DVec3::new(99.0, 49.0, 9.9));
        // Every point widens it back to the subject's edge, not to the strays.
        let sample: Vec<Vec3> = points.iter().copied().step_by(7).collect();
        let extent = Extent::of_points(everything(), origin, &sample, &points);
        assert_near(extent.robust.min, origin);
        assert_near(extent.robust.max, origin + DVec3::new(99.0, 49.0, 9.9));
    }

    #[test]
    fn the_outline_keeps_the_points_that_rounded_past_the_header_box() {
        // The header's box a rounding error inside the points that decide it, as f32 offsets
        // from a far origin leave them.
        let origin = DVec3::new(500_000.0, 4_000_000.0, 100.0);
        let points = terrain();
        let hair = DVec3::splat(1e-5);
        let all = WorldBounds {
            min: origin + hair,
            max: origin + DVec3::new(99.0, 49.0, 9.9) - hair,
        };
        let extent = Extent::of_points(all, origin, &points, &points);
        let lo = extent.outline.iter().fold(DVec3::MAX, |lo, p| lo.min(*p));
        let hi = extent.outline.iter().fold(DVec3::MIN, |hi, p| hi.max(*p));
        // The grid's corners are its outermost points in every direction off the axes.
        assert_near(lo.truncate().extend(0.0), origin.truncate().extend(0.0));
        assert_near(
            hi.truncate().extend(0.0),
            (origin + DVec3::new(99.0, 49.0, 0.0))
                .truncate()
                .extend(0.0),
        );
    }

    #[test]
    fn a_subject_without_strays_keeps_its_whole_box() {
        let points = terrain();
        let extent = Extent::of_sample(everything(), DVec3::ZERO, &points);
        assert_near(extent.robust.min, DVec3::ZERO);
        assert_near(extent.robust.max, DVec3::new(99.0, 49.0, 9.9));
    }

    #[test]
    fn the_robust_box_lies_inside_every_points_box() {
        let all = WorldBounds {
            min: DVec3::new(10.0, 10.0, 0.0),
            max: DVec3::new(50.0, 40.0, 5.0),
        };
        let extent = Extent::of_sample(all, DVec3::ZERO, &terrain());
        assert_eq!(extent.all, all);
        assert_near(extent.robust.min, DVec3::new(10.0, 10.0, 0.0));
        assert_near(extent.robust.max, DVec3::new(50.0, 40.0, 5.0));
    }

    #[test]
    fn equal_points_and_tiny_clouds_give_a_box() {
        let p = Vec3::new(1.0, 2.0, 3.0);
        for sample in [
            vec![p; 1000],
            vec![p],
            vec![p, Vec3::ZERO],
            vec![p, -p, Vec3::X],
        ] {
            let extent = Extent::of_points(everything(), DVec3::ZERO, &sample, &sample);
            let (lo, hi) = sample
                .iter()
                .fold((p, p), |(lo, hi), q| (lo.min(*q), hi.max(*q)));
            assert_near(extent.robust.min, lo.as_dvec3());
            assert_near(extent.robust.max, hi.as_dvec3());
        }
        let all = everything();
        assert_eq!(Extent::of_sample(all, DVec3::ZERO, &[]), Extent::whole(all));
        let nan = [Vec3::NAN];
        assert_eq!(
            Extent::of_points(all, DVec3::ZERO, &nan, &nan),
            Extent::whole(all)
        );
    }
}

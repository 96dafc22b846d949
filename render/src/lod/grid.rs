//! `PositionGrid`: the grid of LAS integer coordinates a source's points lie on, which spill
//! records hold positions on where every file of a dataset shares it (`point.rs`).

use glam::DVec3;

/// The grid of LAS integer coordinates every point of a source lies on: world =
/// scale * i + offset per axis, i an i32, computed in f64 exactly as the LAS reader does, so
/// a position and its integers convert both ways without loss.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionGrid {
    scale: DVec3,
    offset: DVec3,
}

impl PositionGrid {
    /// The grid of files sharing this scale and offset, if every i32 on it converts back
    /// exactly: positive normal scales and coordinates (|offset| + 2^31 scale) below
    /// 2^50 scale, where f64 spacing is under a quarter of the scale, so rounding never
    /// reaches the next integer.
    pub fn new(scale: DVec3, offset: DVec3) -> Option<Self> {
        let usable = (0..3).all(|a| {
            let (s, o) = (scale[a], offset[a]);
            s.is_normal()
                && s > 0.0
                && o.is_finite()
                && o.abs() + s * 2f64.powi(31) < s * 2f64.powi(50)
        });
        usable.then_some(Self { scale, offset })
    }

    pub fn scale(&self) -> DVec3 {
        self.scale
    }

    pub fn offset(&self) -> DVec3 {
        self.offset
    }

    /// The position of the integers `i`, as the LAS reader computes it (`scale * i + offset`;
    /// wider than i32 for integers shifted onto this grid from another file's offset, which
    /// convert to f64 exactly below 2^53).
    pub fn position(&self, i: [i64; 3]) -> DVec3 {
        DVec3::new(
            self.scale.x * i[0] as f64 + self.offset.x,
            self.scale.y * i[1] as f64 + self.offset.y,
            self.scale.z * i[2] as f64 + self.offset.z,
        )
    }

    /// The integers of `p`, if `p` lies exactly on the grid.
    pub fn index(&self, p: DVec3) -> Option<[i32; 3]> {
        let q = ((p - self.offset) / self.scale).round();
        let fits = |v: f64| v >= f64::from(i32::MIN) && v <= f64::from(i32::MAX);
        if !(fits(q.x) && fits(q.y) && fits(q.z)) {
            return None;
        }
        let i = [q.x as i32, q.y as i32, q.z as i32];
        let back = self.position(i.map(i64::from));
        let same = |a: f64, b: f64| a.to_bits() == b.to_bits();
        (same(back.x, p.x) && same(back.y, p.y) && same(back.z, p.z)).then_some(i)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grids_whose_integers_could_round_to_a_neighbour_are_refused() {
        let ok = DVec3::splat(0.001);
        assert!(PositionGrid::new(ok, DVec3::new(500_000.0, 4_500_000.0, 0.0)).is_some());
        // At 5e6, f64 steps are about 1e-9: a scale of 1e-9 cannot be resolved there.
        assert!(PositionGrid::new(DVec3::splat(1e-9), DVec3::splat(5e6)).is_none());
        assert!(PositionGrid::new(DVec3::new(-0.001, 0.001, 0.001), DVec3::ZERO).is_none());
        assert!(PositionGrid::new(ok, DVec3::new(f64::NAN, 0.0, 0.0)).is_none());
        assert!(PositionGrid::new(DVec3::new(0.0, 0.001, 0.001), DVec3::ZERO).is_none());
    }
}

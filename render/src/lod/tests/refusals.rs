//! Sources that break their promises, and options that cannot work: refused with clear errors.

use glam::DVec3;

use super::{options, temp_store};
use crate::cloud::WorldBounds;
use crate::lod::*;

/// A source that breaks its promises in one chosen way.
struct Broken {
    points: Vec<DVec3>,
    bounds: WorldBounds,
    declared: u64,
    short_intensity: bool,
}

impl Broken {
    fn new(points: Vec<DVec3>) -> Self {
        Self {
            bounds: crate::cloud::bounds_of(points.iter().copied()),
            declared: points.len() as u64,
            points,
            short_intensity: false,
        }
    }
}

impl PointSource for Broken {
    fn bounds(&self) -> WorldBounds {
        self.bounds
    }

    fn point_count(&self) -> u64 {
        self.declared
    }

    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError> {
        let n = self.points.len();
        let intensity = vec![0; if self.short_intensity { n - 1 } else { n }];
        visit(PointBatch {
            positions: &self.points,
            rgb: None,
            intensity: &intensity,
            classification: &vec![0; n],
            return_number: &vec![0; n],
            rows: &[],
        })
    }
}

#[test]
fn bad_sources_are_refused_with_clear_errors() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (_db, store) = temp_store(dir.path());
    let options = options(dir.path(), 500);
    let grid: Vec<DVec3> = (0..1000)
        .map(|i| DVec3::new(f64::from(i), 1.0, 2.0))
        .collect();

    let mut nan = Broken::new(grid.clone());
    nan.points[10].y = f64::NAN;
    let error = build_lod(&nan, &store, &options).expect_err("NaN");
    assert!(
        matches!(error, LodError::NonFinitePoint { index: 10, .. }),
        "{error}"
    );

    let mut lying = Broken::new(grid.clone());
    lying.bounds.max.x = 500.0;
    let error = build_lod(&lying, &store, &options).expect_err("outside");
    assert!(
        matches!(error, LodError::PointOutsideBounds { index: 501, .. }),
        "{error}"
    );

    let mut counted = Broken::new(grid.clone());
    counted.declared = 1001;
    let error = build_lod(&counted, &store, &options).expect_err("count");
    assert!(
        matches!(error, LodError::CountMismatch { read: 1000, .. }),
        "{error}"
    );

    let mut short = Broken::new(grid.clone());
    short.short_intensity = true;
    let error = build_lod(&short, &store, &options).expect_err("lengths");
    assert!(
        error.to_string().contains("intensity has 999 values"),
        "{error}"
    );

    let mut infinite = Broken::new(grid);
    infinite.bounds.max.z = f64::INFINITY;
    assert!(matches!(
        build_lod(&infinite, &store, &options),
        Err(LodError::InvalidBounds { .. })
    ));

    let mut tiny = options.clone();
    tiny.memory_budget_bytes = 1 << 20;
    assert!(matches!(
        build_lod(&GeneratedSource::cube(10, 1), &store, &tiny),
        Err(LodError::InvalidOptions(_))
    ));
    assert!(matches!(
        store.read_hierarchy(),
        Err(LodError::MissingHierarchy)
    ));
}

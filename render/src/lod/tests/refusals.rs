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

/// A source whose second reading moves one point into space the first reading left empty.
struct Moving {
    points: Vec<DVec3>,
    moved: usize,
    to: DVec3,
    readings: std::sync::atomic::AtomicU32,
}

impl PointSource for Moving {
    fn bounds(&self) -> WorldBounds {
        crate::cloud::bounds_of(self.points.iter().copied())
    }

    fn point_count(&self) -> u64 {
        self.points.len() as u64
    }

    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError> {
        let reading = self
            .readings
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let mut points = self.points.clone();
        if reading > 0 {
            points[self.moved] = self.to;
        }
        let n = points.len();
        // In two batches, so that the moved point's index counts the batch before it.
        let zeros = vec![0u16; n];
        let bytes = vec![0u8; n];
        let half = n / 2;
        for range in [0..half, half..n] {
            visit(PointBatch {
                positions: &points[range.clone()],
                rgb: None,
                intensity: &zeros[range.clone()],
                classification: &bytes[range.clone()],
                return_number: &bytes[range],
            })?;
        }
        Ok(())
    }
}

#[test]
fn a_source_that_changes_between_its_readings_is_refused_naming_the_point() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (_db, store) = temp_store(dir.path());
    let mut points: Vec<DVec3> = (0..3000)
        .map(|i| DVec3::new(f64::from(i % 1000), 1.0, 2.0))
        .collect();
    points.push(DVec3::splat(999.0));
    let moving = Moving {
        points,
        moved: 2100,
        to: DVec3::new(200.0, 700.0, 200.0),
        readings: Default::default(),
    };
    let error = build_lod(&moving, &store, &options(dir.path(), 500)).expect_err("moved");
    assert!(
        matches!(&error, LodError::SourceChanged(what) if what.contains("point 2100 ")),
        "{error}"
    );
    let left = std::fs::read_dir(dir.path().join("spill"))
        .map(|entries| entries.count())
        .unwrap_or(0);
    assert_eq!(left, 0, "no spill left behind");
}

//! `GeneratedSource`: seeded clouds of any size generated batch by batch, never whole, for
//! tests and benchmarks of the builder.

use glam::DVec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::error::LodError;
use super::source::{BatchColumns, BatchVisitor, PointSource, SOURCE_BATCH_POINTS};
use crate::cloud::WorldBounds;

/// The corner of the generated clouds, at survey-like coordinates.
const GENERATED_ORIGIN: DVec3 = DVec3::new(515_000.0, 4_918_000.0, 200.0);
/// Ground points per square metre of the terrain.
const TERRAIN_DENSITY: f64 = 10.0;
/// Share of terrain points that are vegetation above the ground.
const VEGETATION_SHARE: f64 = 0.2;
const VEGETATION_HEIGHT: f64 = 20.0;
/// Side of the generated cube, in metres.
const CUBE_SIDE: f64 = 100.0;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GeneratedShape {
    /// Rolling ground with vegetation above it: the 2.5D shape of airborne scans.
    Terrain,
    /// Uniform points filling a cube: the volumetric worst case for node sizes.
    Cube,
}

/// `points` points of `shape`; each batch is generated from the seed and its index alone, so
/// every pass yields the same points in the same order.
#[derive(Debug, Clone)]
pub struct GeneratedSource {
    pub shape: GeneratedShape,
    pub points: u64,
    pub seed: u64,
}

impl GeneratedSource {
    pub fn terrain(points: u64, seed: u64) -> Self {
        Self {
            shape: GeneratedShape::Terrain,
            points,
            seed,
        }
    }

    pub fn cube(points: u64, seed: u64) -> Self {
        Self {
            shape: GeneratedShape::Cube,
            points,
            seed,
        }
    }

    fn terrain_extent(&self) -> f64 {
        (self.points as f64 / TERRAIN_DENSITY).sqrt().max(1.0)
    }
}

/// Ground height: gentle waves and a slight tilt; within ±13 m plus the tilt.
fn ground(x: f64, y: f64) -> f64 {
    8.0 * (x / 97.0).sin() + 5.0 * (y / 61.0).cos() + 0.002 * x
}

/// Appends one generated point.
trait PushPoint {
    fn push(&mut self, p: DVec3, rgb: [u16; 3], intensity: u16, class: u8, ret: u8);
}

impl PushPoint for BatchColumns {
    fn push(&mut self, p: DVec3, rgb: [u16; 3], intensity: u16, class: u8, ret: u8) {
        self.positions.push(p);
        self.rgb.push(rgb);
        self.intensity.push(intensity);
        self.classification.push(class);
        self.return_number.push(ret);
    }
}

impl PointSource for GeneratedSource {
    /// Its points are its parameters' alone.
    fn fingerprint(&self) -> Option<String> {
        Some(format!(
            "generated {:?}, {} points, seed {}",
            self.shape, self.points, self.seed
        ))
    }

    fn bounds(&self) -> WorldBounds {
        let size = match self.shape {
            GeneratedShape::Terrain => {
                let extent = self.terrain_extent();
                DVec3::new(extent, extent, 0.0)
            }
            GeneratedShape::Cube => DVec3::splat(CUBE_SIDE),
        };
        match self.shape {
            GeneratedShape::Terrain => WorldBounds {
                min: GENERATED_ORIGIN + DVec3::new(0.0, 0.0, -13.0),
                max: GENERATED_ORIGIN
                    + DVec3::new(size.x, size.y, 13.0 + 0.002 * size.x + VEGETATION_HEIGHT),
            },
            GeneratedShape::Cube => WorldBounds {
                min: GENERATED_ORIGIN,
                max: GENERATED_ORIGIN + size,
            },
        }
    }

    fn point_count(&self) -> u64 {
        self.points
    }

    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError> {
        let mut columns = BatchColumns::default();
        let extent = self.terrain_extent();
        let batches = self.points.div_ceil(SOURCE_BATCH_POINTS as u64);
        for batch in 0..batches {
            let mut rng =
                ChaCha8Rng::seed_from_u64(self.seed ^ batch.wrapping_mul(0x9E37_79B9_7F4A_7C15));
            let count =
                (self.points - batch * SOURCE_BATCH_POINTS as u64).min(SOURCE_BATCH_POINTS as u64);
            columns.clear();
            for _ in 0..count {
                match self.shape {
                    GeneratedShape::Terrain => {
                        let x = rng.random::<f64>() * extent;
                        let y = rng.random::<f64>() * extent;
                        let z = ground(x, y);
                        let vegetation = rng.random::<f64>() < VEGETATION_SHARE;
                        let (z, class, ret) = if vegetation {
                            (z + rng.random::<f64>() * VEGETATION_HEIGHT, 5, 1)
                        } else {
                            (z + rng.random::<f64>() * 0.05, 2, 2)
                        };
                        let shade = ((z + 13.0) * 1500.0).clamp(0.0, 65_535.0) as u16;
                        let rgb = if vegetation {
                            [shade / 4, shade, shade / 3]
                        } else {
                            [shade, shade / 2, shade / 5]
                        };
                        columns.push(
                            GENERATED_ORIGIN + DVec3::new(x, y, z),
                            rgb,
                            rng.random(),
                            class,
                            ret,
                        );
                    }
                    GeneratedShape::Cube => {
                        let unit = DVec3::new(rng.random(), rng.random(), rng.random());
                        let rgb = (unit * 65_535.0).as_uvec3().to_array().map(|c| c as u16);
                        columns.push(GENERATED_ORIGIN + unit * CUBE_SIDE, rgb, rng.random(), 1, 1);
                    }
                }
            }
            visit(columns.batch(true))?;
        }
        Ok(())
    }
}

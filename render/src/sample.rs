//! A generated demo scene: rolling terrain with a road, a gabled house and a few trees, sampled
//! as a colored point cloud in survey-like world coordinates.
//!
//! The scene sits at UTM-like coordinates (x ≈ 500,000 m, y ≈ 4,500,000 m) on purpose, so that
//! rendering it exercises the same recentring path as a real scan. The layout is fixed; the seed
//! only changes where on the surfaces the points fall.

use std::f64::consts::TAU;

use glam::DVec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::cloud::{pack_rgba8, PointCloud};

/// World position of the scene's local origin (metres, UTM-like easting/northing/elevation).
pub const SAMPLE_ORIGIN: DVec3 = DVec3::new(500_000.0, 4_500_000.0, 100.0);
/// Half the side of the square patch of terrain, in metres.
const HALF_EXTENT: f64 = 60.0;
/// A reasonable default size for demos and benchmarks.
pub const DEFAULT_SAMPLE_POINTS: usize = 200_000;

/// ASPRS classification codes used by the scene.
const CLASS_GROUND: u8 = 2;
const CLASS_HIGH_VEGETATION: u8 = 5;
const CLASS_BUILDING: u8 = 6;
const CLASS_ROAD: u8 = 11;

/// Objects get this many times the terrain's point density, so they stay crisp next to the
/// much larger ground area.
const OBJECT_DENSITY_BOOST: f64 = 2.5;

/// The house: footprint centre, half sizes of the footprint, wall height and ridge height above
/// the eaves; the ridge runs along x.
const HOUSE_CENTER: (f64, f64) = (12.0, 16.0);
const HOUSE_HALF_SIZE: (f64, f64) = (11.0, 6.5);
const HOUSE_WALL_HEIGHT: f64 = 6.5;
const HOUSE_RIDGE_RISE: f64 = 4.5;
const ROOF_OVERHANG: f64 = 0.7;

/// Trees as (x, y, trunk height, crown radius), placed clear of the house and the road.
const TREES: [(f64, f64, f64, f64); 11] = [
    (-35.0, 30.0, 3.5, 3.4),
    (-27.0, 40.0, 3.0, 2.8),
    (-42.0, 45.0, 4.0, 3.8),
    (-18.0, 28.0, 3.2, 3.0),
    (34.0, 35.0, 3.6, 3.5),
    (42.0, 24.0, 3.0, 2.7),
    (-38.0, -42.0, 3.8, 3.6),
    (-22.0, -48.0, 3.0, 2.9),
    (15.0, -45.0, 3.4, 3.3),
    (30.0, -40.0, 3.0, 2.6),
    (45.0, -50.0, 4.0, 3.9),
];

/// Generates the demo scene with exactly `points` points; the same seed gives the same cloud.
pub fn sample_scene(points: usize, seed: u64) -> PointCloud {
    SampleScene::new(points, seed).next_block(points)
}

/// What one generated point is sampled from.
#[derive(Debug, Clone, Copy)]
enum Part {
    House,
    Tree(usize),
    Terrain,
}

/// The demo scene generated block by block, so a scene of any size is written within a
/// block's memory: the points of [`sample_scene`], in its order (the house's, each tree's, then
/// the terrain's, from one random stream).
pub struct SampleScene {
    rng: ChaCha8Rng,
    house: Vec<Facet>,
    house_area: f64,
    /// Each part and the points it gets, in order.
    parts: Vec<(Part, usize)>,
    /// The part being sampled and the points it has left.
    part: usize,
    left_in_part: usize,
    remaining: usize,
}

impl SampleScene {
    pub fn new(points: usize, seed: u64) -> Self {
        let house = house_facets();
        let house_area: f64 = house.iter().map(Facet::area).sum();
        let tree_areas: Vec<f64> = TREES
            .iter()
            .map(|&(_, _, trunk_height, crown_radius)| {
                TAU * TRUNK_RADIUS * trunk_height + 2.0 * TAU * crown_radius * crown_radius
            })
            .collect();
        let terrain_area = (2.0 * HALF_EXTENT).powi(2);
        let object_area = (house_area + tree_areas.iter().sum::<f64>()) * OBJECT_DENSITY_BOOST;
        let points_per_area = points as f64 / (terrain_area + object_area);
        let share = |area: f64| (area * OBJECT_DENSITY_BOOST * points_per_area) as usize;
        let mut parts = vec![(Part::House, share(house_area))];
        parts.extend(
            tree_areas
                .iter()
                .enumerate()
                .map(|(i, &area)| (Part::Tree(i), share(area))),
        );
        // Terrain takes the remainder, so the count is exact whatever the rounding above.
        let objects: usize = parts.iter().map(|&(_, n)| n).sum();
        parts.push((Part::Terrain, points.saturating_sub(objects)));
        let left_in_part = parts[0].1;
        Self {
            rng: ChaCha8Rng::seed_from_u64(seed),
            house,
            house_area,
            parts,
            part: 0,
            left_in_part,
            remaining: points,
        }
    }

    /// Points not generated yet.
    pub fn remaining(&self) -> usize {
        self.remaining
    }

    /// The next `max` points (fewer at the end; none once every point was generated).
    pub fn next_block(&mut self, max: usize) -> PointCloud {
        let count = max.min(self.remaining);
        let mut scene = SceneBuilder::with_capacity(count);
        while scene.len() < count {
            while self.left_in_part == 0 {
                self.part += 1;
                self.left_in_part = self.parts[self.part].1;
            }
            let rng = &mut self.rng;
            match self.parts[self.part].0 {
                Part::House => {
                    let facet = pick_by_area(&self.house, self.house_area, rng);
                    facet.sample(rng, &mut scene);
                }
                Part::Tree(i) => sample_tree(TREES[i], rng, &mut scene),
                Part::Terrain => sample_terrain(rng, &mut scene),
            }
            self.left_in_part -= 1;
        }
        self.remaining -= count;
        scene.into_cloud()
    }
}

/// Accumulates world points and their attributes.
struct SceneBuilder {
    world: Vec<DVec3>,
    colors: Vec<u32>,
    intensity: Vec<u16>,
    classification: Vec<u8>,
}

impl SceneBuilder {
    fn with_capacity(points: usize) -> Self {
        Self {
            world: Vec::with_capacity(points),
            colors: Vec::with_capacity(points),
            intensity: Vec::with_capacity(points),
            classification: Vec::with_capacity(points),
        }
    }

    fn len(&self) -> usize {
        self.world.len()
    }

    fn push(&mut self, local: DVec3, rgb: [u8; 3], intensity: u16, classification: u8) {
        self.world.push(SAMPLE_ORIGIN + local);
        self.colors.push(pack_rgba8(rgb[0], rgb[1], rgb[2]));
        self.intensity.push(intensity);
        self.classification.push(classification);
    }

    fn into_cloud(self) -> PointCloud {
        let points = self.world.len();
        let mut cloud = PointCloud::from_world_points(&self.world, self.colors);
        cloud.intensity = self.intensity;
        cloud.classification = self.classification;
        cloud.return_number = vec![1; points];
        cloud
    }
}

/// Ground height: two long gentle waves and a slight tilt, flattened to a pad around the house.
fn terrain_height(x: f64, y: f64) -> f64 {
    let rolling = |x: f64, y: f64| {
        2.2 * (x / 23.0).sin() * (y / 31.0).cos() + 1.3 * ((x + 0.6 * y) / 17.0).sin() + 0.03 * x
    };
    let (cx, cy) = HOUSE_CENTER;
    let (hx, hy) = HOUSE_HALF_SIZE;
    // Distance outside the footprint; the pad blends into the hills over 8 m.
    let outside = ((x - cx).abs() - hx).max((y - cy).abs() - hy).max(0.0);
    let blend = smoothstep(0.0, 8.0, outside);
    let pad = rolling(cx, cy);
    pad + (rolling(x, y) - pad) * blend
}

fn smoothstep(edge0: f64, edge1: f64, x: f64) -> f64 {
    let t = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Centre line of the road, which sweeps across the patch south of the house.
fn road_center_y(x: f64) -> f64 {
    -12.0 + 9.0 * (x / 28.0).sin()
}
const ROAD_HALF_WIDTH: f64 = 3.2;

fn sample_terrain(rng: &mut impl Rng, scene: &mut SceneBuilder) {
    let (cx, cy) = HOUSE_CENTER;
    let (hx, hy) = HOUSE_HALF_SIZE;
    let (x, y) = loop {
        let x = rng.random_range(-HALF_EXTENT..HALF_EXTENT);
        let y = rng.random_range(-HALF_EXTENT..HALF_EXTENT);
        // Nothing under the house: those points would be hidden and only cost time.
        if (x - cx).abs() > hx || (y - cy).abs() > hy {
            break (x, y);
        }
    };
    let z = terrain_height(x, y);
    let from_road_center = y - road_center_y(x);
    if from_road_center.abs() < ROAD_HALF_WIDTH {
        let dashed_center_line = from_road_center.abs() < 0.1 && x.rem_euclid(6.0) < 3.0;
        let rgb = if dashed_center_line {
            [235, 235, 225]
        } else {
            jitter(rng, [78, 78, 84], 6)
        };
        let intensity = if dashed_center_line {
            2_400
        } else {
            rng.random_range(300..500)
        };
        scene.push(DVec3::new(x, y, z + 0.05), rgb, intensity, CLASS_ROAD);
    } else {
        // Green in the hollows, drier brown on the crests.
        let t = smoothstep(-2.5, 3.5, z);
        let grass = [62.0, 128.0, 48.0];
        let dry = [140.0, 118.0, 72.0];
        let rgb = std::array::from_fn(|i| (grass[i] + (dry[i] - grass[i]) * t) as u8);
        scene.push(
            DVec3::new(x, y, z),
            jitter(rng, rgb, 10),
            rng.random_range(700..1_300),
            CLASS_GROUND,
        );
    }
}

const TRUNK_RADIUS: f64 = 0.3;

fn sample_tree(
    (x, y, trunk_height, crown_radius): (f64, f64, f64, f64),
    rng: &mut impl Rng,
    scene: &mut SceneBuilder,
) {
    let base = DVec3::new(x, y, terrain_height(x, y));
    let trunk_area = TAU * TRUNK_RADIUS * trunk_height;
    let crown_area = 2.0 * TAU * crown_radius * crown_radius;
    if rng.random_range(0.0..trunk_area + crown_area) < trunk_area {
        let angle = rng.random_range(0.0..TAU);
        let height = rng.random_range(0.0..trunk_height);
        let offset = DVec3::new(
            TRUNK_RADIUS * angle.cos(),
            TRUNK_RADIUS * angle.sin(),
            height,
        );
        scene.push(
            base + offset,
            jitter(rng, [96, 66, 40], 8),
            rng.random_range(400..600),
            CLASS_HIGH_VEGETATION,
        );
    } else {
        // Uniform on the sphere (Archimedes: uniform in z), with a ragged, foliage-like surface.
        let z = rng.random_range(-1.0..1.0_f64);
        let angle = rng.random_range(0.0..TAU);
        let ring = (1.0 - z * z).sqrt();
        let radius = crown_radius * rng.random_range(0.85..1.0);
        let direction = DVec3::new(ring * angle.cos(), ring * angle.sin(), z);
        let center = base + DVec3::Z * (trunk_height + 0.7 * crown_radius);
        // Lit from above: the upper crown a lighter green.
        let shade = 0.75 + 0.25 * (z + 1.0) * 0.5;
        let rgb = [
            (48.0 * shade) as u8,
            (122.0 * shade) as u8,
            (42.0 * shade) as u8,
        ];
        scene.push(
            center + direction * radius,
            jitter(rng, rgb, 12),
            rng.random_range(500..900),
            CLASS_HIGH_VEGETATION,
        );
    }
}

/// What a house facet is made of.
#[derive(Clone, Copy)]
enum Material {
    /// Rendered walls with a regular pattern of windows.
    Wall,
    /// Gable ends: plain wall, no windows.
    Gable,
    Roof,
}

/// A planar piece of the house: the parallelogram or triangle spanned by `edge_u` and `edge_v`
/// from `corner`.
struct Facet {
    corner: DVec3,
    edge_u: DVec3,
    edge_v: DVec3,
    triangle: bool,
    material: Material,
}

impl Facet {
    fn area(&self) -> f64 {
        let parallelogram = self.edge_u.cross(self.edge_v).length();
        if self.triangle {
            parallelogram * 0.5
        } else {
            parallelogram
        }
    }

    fn sample(&self, rng: &mut impl Rng, scene: &mut SceneBuilder) {
        let (mut s, mut t) = (rng.random::<f64>(), rng.random::<f64>());
        if self.triangle && s + t > 1.0 {
            (s, t) = (1.0 - s, 1.0 - t);
        }
        let position = self.corner + self.edge_u * s + self.edge_v * t;
        let (rgb, intensity) = match self.material {
            Material::Wall => {
                // Windows 1.4 m wide every 3.5 m, between 1.0 and 2.4 m above each storey.
                let along = s * self.edge_u.length();
                let up = t * self.edge_v.length();
                let in_window = along.rem_euclid(3.5) > 1.05
                    && along.rem_euclid(3.5) < 2.45
                    && up.rem_euclid(3.25) > 1.0
                    && up.rem_euclid(3.25) < 2.4;
                if in_window {
                    ([55, 68, 88], 300)
                } else {
                    ([228, 218, 192], 1_800)
                }
            }
            Material::Gable => ([228, 218, 192], 1_800),
            Material::Roof => {
                // Faint stripes of tile courses every 0.35 m down the slope.
                let course = (t * self.edge_v.length() / 0.35) as i64;
                let rgb = if course % 2 == 0 {
                    [176, 52, 40]
                } else {
                    [160, 44, 34]
                };
                (rgb, 1_100)
            }
        };
        scene.push(position, jitter(rng, rgb, 6), intensity, CLASS_BUILDING);
    }
}

/// Walls, gable ends and the two roof planes of the house, in local coordinates.
fn house_facets() -> Vec<Facet> {
    let (cx, cy) = HOUSE_CENTER;
    let (hx, hy) = HOUSE_HALF_SIZE;
    let floor = terrain_height(cx, cy);
    let eaves = floor + HOUSE_WALL_HEIGHT;
    let corner = |sx: f64, sy: f64, z: f64| DVec3::new(cx + sx * hx, cy + sy * hy, z);
    let up = DVec3::Z * HOUSE_WALL_HEIGHT;
    let wall = |from: DVec3, to: DVec3| Facet {
        corner: from,
        edge_u: to - from,
        edge_v: up,
        triangle: false,
        material: Material::Wall,
    };
    let (sw, se) = (corner(-1.0, -1.0, floor), corner(1.0, -1.0, floor));
    let (nw, ne) = (corner(-1.0, 1.0, floor), corner(1.0, 1.0, floor));

    // The roof overhangs the walls and drops a little below the eaves at its edges.
    let overhang_drop = ROOF_OVERHANG * HOUSE_RIDGE_RISE / hy;
    let ridge_west = DVec3::new(cx - hx - ROOF_OVERHANG, cy, eaves + HOUSE_RIDGE_RISE);
    let ridge = DVec3::X * (2.0 * (hx + ROOF_OVERHANG));
    let roof_plane = |side: f64| Facet {
        corner: ridge_west,
        edge_u: ridge,
        edge_v: DVec3::new(
            0.0,
            side * (hy + ROOF_OVERHANG),
            -(HOUSE_RIDGE_RISE + overhang_drop),
        ),
        triangle: false,
        material: Material::Roof,
    };
    let gable = |x_side: f64| Facet {
        corner: corner(x_side, -1.0, eaves),
        edge_u: DVec3::Y * (2.0 * hy),
        edge_v: DVec3::new(0.0, hy, HOUSE_RIDGE_RISE),
        triangle: true,
        material: Material::Gable,
    };
    vec![
        wall(sw, se),
        wall(se, ne),
        wall(ne, nw),
        wall(nw, sw),
        gable(-1.0),
        gable(1.0),
        roof_plane(-1.0),
        roof_plane(1.0),
    ]
}

/// Picks a facet with probability proportional to its area.
fn pick_by_area<'a>(facets: &'a [Facet], total_area: f64, rng: &mut impl Rng) -> &'a Facet {
    let mut remaining = rng.random_range(0.0..total_area);
    for facet in facets {
        remaining -= facet.area();
        if remaining < 0.0 {
            return facet;
        }
    }
    &facets[facets.len() - 1]
}

/// Adds a little per-point color noise, as real scans have.
fn jitter(rng: &mut impl Rng, rgb: [u8; 3], amount: i16) -> [u8; 3] {
    let offset = rng.random_range(-amount..=amount);
    rgb.map(|channel| (i16::from(channel) + offset).clamp(0, 255) as u8)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ingest::{load_point_cloud, write_las, LasWriteOptions};

    #[test]
    fn the_same_seed_gives_the_same_scene() {
        let first = sample_scene(20_000, 7);
        assert!(first == sample_scene(20_000, 7));
        assert!(first != sample_scene(20_000, 8));
    }

    #[test]
    fn blocks_are_the_whole_scene_in_order() {
        let whole = sample_scene(25_000, 5);
        let mut scene = SampleScene::new(25_000, 5);
        let mut blocks = Vec::new();
        while scene.remaining() > 0 {
            blocks.push(scene.next_block(4_096));
        }
        assert_eq!(blocks.len(), 7);
        assert_eq!(scene.next_block(4_096).len(), 0);
        let world: Vec<DVec3> = blocks
            .iter()
            .flat_map(|b| b.positions.iter().map(|p| b.origin + p.as_dvec3()))
            .collect();
        assert_eq!(world.len(), whole.len());
        for (i, (a, p)) in world.iter().zip(&whole.positions).enumerate() {
            let b = whole.origin + p.as_dvec3();
            // Each cloud keeps f32 offsets from its own centre: the same point within 10 µm.
            assert!(
                (*a - b).abs().max_element() < 1e-5,
                "point {i}: {a} against {b}"
            );
        }
        let attributes = |clouds: &[&PointCloud]| -> Vec<(u32, u16, u8)> {
            clouds
                .iter()
                .flat_map(|c| {
                    (0..c.len()).map(|i| (c.colors[i], c.intensity[i], c.classification[i]))
                })
                .collect()
        };
        let blocks: Vec<&PointCloud> = blocks.iter().collect();
        assert_eq!(attributes(&blocks), attributes(&[&whole]));
    }

    #[test]
    fn has_exactly_the_requested_number_of_points() {
        for points in [0, 1, 10, 999, 20_001] {
            let cloud = sample_scene(points, 1);
            assert_eq!(cloud.len(), points);
            assert_eq!(cloud.colors.len(), points);
            assert_eq!(cloud.intensity.len(), points);
            assert_eq!(cloud.classification.len(), points);
            assert_eq!(cloud.return_number.len(), points);
        }
    }

    #[test]
    fn lies_at_survey_coordinates_with_the_expected_classes() {
        let cloud = sample_scene(DEFAULT_SAMPLE_POINTS, 42);
        let (min, max) = (cloud.bounds.min, cloud.bounds.max);
        assert!(min.x >= SAMPLE_ORIGIN.x - HALF_EXTENT && max.x <= SAMPLE_ORIGIN.x + HALF_EXTENT);
        assert!(min.y >= SAMPLE_ORIGIN.y - HALF_EXTENT && max.y <= SAMPLE_ORIGIN.y + HALF_EXTENT);
        assert!(
            min.z > SAMPLE_ORIGIN.z - 10.0 && max.z < SAMPLE_ORIGIN.z + 25.0,
            "z {min} {max}"
        );
        assert!(cloud.bounds.size().x > 100.0 && cloud.bounds.size().y > 100.0);
        // Recentred: the stored offsets are small.
        assert!(cloud
            .positions
            .iter()
            .all(|p| p.abs().max_element() < 100.0));

        let count = |class: u8| cloud.classification.iter().filter(|&&c| c == class).count();
        let (ground, road, building, trees) = (
            count(CLASS_GROUND),
            count(CLASS_ROAD),
            count(CLASS_BUILDING),
            count(CLASS_HIGH_VEGETATION),
        );
        assert_eq!(ground + road + building + trees, cloud.len());
        assert!(ground > cloud.len() / 2, "ground {ground}");
        for (name, n) in [("road", road), ("building", building), ("trees", trees)] {
            assert!(n > cloud.len() / 50, "{name}: only {n} points");
        }
    }

    #[test]
    fn survives_a_laz_round_trip() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("sample.laz");
        let cloud = sample_scene(30_000, 3);
        write_las(&path, &cloud, &LasWriteOptions::default()).expect("write");
        let loaded = load_point_cloud(&path).expect("load");
        assert_eq!(loaded.len(), cloud.len());
        assert_eq!(loaded.colors, cloud.colors);
        assert_eq!(loaded.classification, cloud.classification);
        assert_eq!(loaded.intensity, cloud.intensity);
        let max_error = cloud
            .positions
            .iter()
            .zip(&loaded.positions)
            .map(|(a, b)| {
                ((cloud.origin + a.as_dvec3()) - (loaded.origin + b.as_dvec3()))
                    .abs()
                    .max_element()
            })
            .fold(0.0, f64::max);
        assert!(
            max_error <= 0.0006,
            "max error {max_error} m at scale 0.001"
        );
    }
}

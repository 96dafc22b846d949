//! Where a frame's pixels lie on the ground: the affine map from pixels to the sources'
//! coordinates of an orthographic view from straight above, and the sources' CRS, written
//! into a TIFF frame as GeoTIFF tags, or beside it as a world file and WKT where the CRS has
//! no EPSG code a GeoTIFF key can hold.
//!
//! Pixels are areas: the map's origin is the top-left corner of the top-left pixel, as in a
//! world file's corner form and GDAL's geotransform.

use std::path::{Path, PathBuf};

use glam::{DVec2, DVec3, DVec4};

use crate::camera::{Camera, Projection};
use crate::ingest::{Crs, FileInfo, IngestError, GEOTIFF_USER_DEFINED};

/// GeoTIFF's GeoKeyDirectory header: version 1, revision 1.0.
const KEY_DIRECTORY_VERSION: [u16; 3] = [1, 1, 0];
/// GTModelTypeGeoKey and its values.
const MODEL_TYPE_KEY: u16 = 1024;
const MODEL_PROJECTED: u16 = 1;
const MODEL_GEOGRAPHIC: u16 = 2;
/// GTRasterTypeGeoKey: a pixel's value covers its whole area (RasterPixelIsArea).
const RASTER_TYPE_KEY: u16 = 1025;
const RASTER_PIXEL_IS_AREA: u16 = 1;
/// GeographicTypeGeoKey, ProjectedCSTypeGeoKey, VerticalCSTypeGeoKey.
const GEOGRAPHIC_TYPE_KEY: u16 = 2048;
const PROJECTED_CS_TYPE_KEY: u16 = 3072;
const VERTICAL_CS_TYPE_KEY: u16 = 4096;

/// How far from straight down a view may look and still be a top view: its direction's
/// horizontal part, in radians (about 2e-4 arc seconds; a top view's trigonometry leaves 1e-16).
const STRAIGHT_DOWN_TOLERANCE: f64 = 1e-9;
/// A rotation term this small against the pixel size is the rounding of a north-up view's
/// trigonometry, not a rotation.
const NORTH_UP_TOLERANCE: f64 = 1e-9;

/// The affine map from continuous pixel coordinates (column, row; (0, 0) the top-left corner
/// of the top-left pixel) to the sources' x and y: `origin + column * per_column + row *
/// per_row`. GDAL's geotransform is `[origin.x, per_column.x, per_row.x, origin.y,
/// per_column.y, per_row.y]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeoTransform {
    pub origin: DVec2,
    pub per_column: DVec2,
    pub per_row: DVec2,
}

impl GeoTransform {
    /// The map of a `width` x `height` image `camera` sees, when the camera is orthographic
    /// and looks straight down; `None` for any other view, whose pixels have no one place on
    /// the ground.
    pub fn of_top_view(camera: &Camera, width: u32, height: u32) -> Option<Self> {
        if !matches!(camera.projection, Projection::Orthographic { .. })
            || width == 0
            || height == 0
        {
            return None;
        }
        let forward = (camera.target - camera.position).normalize_or_zero();
        if !(forward.z < 0.0 && forward.truncate().length() <= STRAIGHT_DOWN_TOLERANCE) {
            return None;
        }
        // The renderer's own transform, relative to the target so that survey coordinates
        // keep their precision; an orthographic projection is affine, so three points fix it.
        let transform = camera.transform(camera.target, width, height);
        let pixel_of = |p: DVec3| {
            let clip = transform.view_proj * DVec4::new(p.x, p.y, p.z, 1.0);
            DVec2::new(
                (clip.x / clip.w * 0.5 + 0.5) * f64::from(width),
                (0.5 - clip.y / clip.w * 0.5) * f64::from(height),
            )
        };
        let at_target = pixel_of(DVec3::ZERO);
        let per_x = pixel_of(DVec3::X) - at_target;
        let per_y = pixel_of(DVec3::Y) - at_target;
        let determinant = per_x.x * per_y.y - per_y.x * per_x.y;
        if !(determinant.is_finite() && determinant.abs() > f64::MIN_POSITIVE) {
            return None;
        }
        // The inverse of the 2x2 map from world offsets to pixel offsets.
        let per_column = DVec2::new(per_y.y, -per_x.y) / determinant;
        let per_row = DVec2::new(-per_y.x, per_x.x) / determinant;
        let origin = camera.target.truncate() - per_column * at_target.x - per_row * at_target.y;
        let mut map = Self {
            origin,
            per_column,
            per_row,
        };
        let size = per_column.length();
        if map.per_column.y.abs() <= NORTH_UP_TOLERANCE * size
            && map.per_row.x.abs() <= NORTH_UP_TOLERANCE * size
        {
            map.per_column.y = 0.0;
            map.per_row.x = 0.0;
        }
        map.is_finite().then_some(map)
    }

    fn is_finite(&self) -> bool {
        self.origin.is_finite() && self.per_column.is_finite() && self.per_row.is_finite()
    }

    /// Whether columns run east and rows south without rotation, which GeoTIFF's pixel scale
    /// and tie point can say; any other map needs its transformation matrix.
    pub fn is_north_up(&self) -> bool {
        self.per_column.y == 0.0
            && self.per_row.x == 0.0
            && self.per_column.x > 0.0
            && self.per_row.y < 0.0
    }

    /// GDAL's geotransform of this map.
    pub fn gdal(&self) -> [f64; 6] {
        [
            self.origin.x,
            self.per_column.x,
            self.per_row.x,
            self.origin.y,
            self.per_column.y,
            self.per_row.y,
        ]
    }

    /// The six lines of a world file (`.tfw`): the map's terms, then the centre of the
    /// top-left pixel, which is where a world file places its origin.
    pub fn world_file(&self) -> String {
        let center = self.origin + (self.per_column + self.per_row) * 0.5;
        [
            self.per_column.x,
            self.per_column.y,
            self.per_row.x,
            self.per_row.y,
            center.x,
            center.y,
        ]
        .iter()
        .map(|v| format!("{v:.12}\n"))
        .collect()
    }

    /// ModelTransformationTag's 4x4 matrix (row major), from pixel (column, row, 0, 1) to the
    /// model's (x, y, z, 1).
    pub(crate) fn model_transformation(&self) -> [f64; 16] {
        let (o, c, r) = (self.origin, self.per_column, self.per_row);
        [
            c.x, r.x, 0.0, o.x, //
            c.y, r.y, 0.0, o.y, //
            0.0, 0.0, 0.0, 0.0, //
            0.0, 0.0, 0.0, 1.0,
        ]
    }
}

/// Whether a CRS is projected or geographic, which decides the GeoTIFF keys that hold it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CrsKind {
    Projected,
    Geographic,
}

/// The sources' coordinate reference system, as a georeferenced frame carries it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum GeoCrs {
    /// An EPSG code GeoTIFF's keys hold, with the vertical system's when the files give one.
    Epsg {
        kind: CrsKind,
        code: u16,
        vertical: Option<u16>,
    },
    /// A WKT without an EPSG code a GeoTIFF key can hold (a compound system, an ESRI name,
    /// parameters): written beside the frame.
    Wkt(String),
    /// No CRS, and why: the frame is placed in the sources' coordinates without one.
    Unknown(String),
}

impl GeoCrs {
    /// The CRS every one of `paths` that declares points declares (headers only; an empty
    /// tile decides nothing, as in a load); [`GeoCrs::Unknown`] when one has none or they
    /// differ.
    pub fn of_files(paths: &[PathBuf]) -> Result<Self, IngestError> {
        let infos = (paths.iter())
            .map(|path| Ok((FileInfo::read(path)?, path.as_path())))
            .collect::<Result<Vec<_>, IngestError>>()?;
        let mut common: Option<(Crs, &Path)> = None;
        for (info, path) in crate::ingest::deciding(&infos, |(info, _)| info.points) {
            let crs = info.crs.clone();
            match &common {
                None => common = Some((crs, path)),
                Some((first, first_path)) if *first != crs => {
                    return Ok(Self::Unknown(format!(
                        "{} and {} declare different coordinate systems",
                        first_path.display(),
                        path.display()
                    )))
                }
                Some(_) => {}
            }
        }
        Ok(match common {
            Some((crs, _)) => Self::of(&crs),
            None => Self::Unknown("no source files".to_owned()),
        })
    }

    /// What a file's declared CRS gives a frame.
    pub fn of(crs: &Crs) -> Self {
        let code = |c: Option<u16>| c.filter(|&c| c != 0 && c != GEOTIFF_USER_DEFINED);
        match crs {
            Crs::GeoTiff(keys) => {
                let vertical = code(keys.vertical);
                if let Some(code) = code(keys.projected) {
                    Self::Epsg {
                        kind: CrsKind::Projected,
                        code,
                        vertical,
                    }
                } else if let Some(code) = code(keys.geographic) {
                    Self::Epsg {
                        kind: CrsKind::Geographic,
                        code,
                        vertical,
                    }
                } else {
                    Self::Unknown(
                        "the files' GeoTIFF keys define their system by parameters, without an \
                         EPSG code"
                            .to_owned(),
                    )
                }
            }
            Crs::Wkt { wkt, epsg, .. } => {
                let keyword = wkt
                    .trim_start()
                    .split(['[', '('])
                    .next()
                    .unwrap_or("")
                    .trim()
                    .to_ascii_uppercase();
                let kind = match keyword.as_str() {
                    "PROJCS" | "PROJCRS" | "PROJECTEDCRS" => Some(CrsKind::Projected),
                    "GEOGCS" | "GEOGCRS" | "GEOGRAPHICCRS" => Some(CrsKind::Geographic),
                    _ => None,
                };
                let code = epsg
                    .and_then(|c| u16::try_from(c).ok())
                    .and_then(|c| code(Some(c)));
                match (kind, code) {
                    (Some(kind), Some(code)) => Self::Epsg {
                        kind,
                        code,
                        vertical: None,
                    },
                    _ => Self::Wkt(wkt.clone()),
                }
            }
            Crs::Unreadable(reason) => {
                Self::Unknown(format!("the files' GeoTIFF keys cannot be read: {reason}"))
            }
            Crs::None => Self::Unknown("the files declare no coordinate system".to_owned()),
        }
    }

    /// The GeoKeyDirectory: the model type, pixel-is-area and the EPSG codes this CRS has.
    pub(crate) fn key_directory(&self) -> Vec<u16> {
        let mut keys = Vec::new();
        if let Self::Epsg {
            kind,
            code,
            vertical,
        } = self
        {
            let (model, key) = match kind {
                CrsKind::Projected => (MODEL_PROJECTED, PROJECTED_CS_TYPE_KEY),
                CrsKind::Geographic => (MODEL_GEOGRAPHIC, GEOGRAPHIC_TYPE_KEY),
            };
            keys.push([MODEL_TYPE_KEY, 0, 1, model]);
            keys.push([RASTER_TYPE_KEY, 0, 1, RASTER_PIXEL_IS_AREA]);
            keys.push([key, 0, 1, *code]);
            if let Some(vertical) = vertical {
                keys.push([VERTICAL_CS_TYPE_KEY, 0, 1, *vertical]);
            }
        } else {
            keys.push([RASTER_TYPE_KEY, 0, 1, RASTER_PIXEL_IS_AREA]);
        }
        let mut directory = KEY_DIRECTORY_VERSION.to_vec();
        directory.push(keys.len() as u16);
        directory.extend(keys.into_iter().flatten());
        directory
    }
}

/// Where a frame lies: its pixels' map and the sources' CRS.
#[derive(Debug, Clone, PartialEq)]
pub struct Georeference {
    pub transform: GeoTransform,
    pub crs: GeoCrs,
}

/// The files written beside a georeferenced TIFF whose CRS is only WKT: the world file, the
/// WKT (`.prj`, for tools that read a world file's CRS there) and GDAL's auxiliary file
/// (`.tif.aux.xml`, since GDAL reads a TIFF's CRS from it and never from a `.prj`).
pub fn sidecar_paths(tiff: &Path) -> [PathBuf; 3] {
    let mut aux = tiff.as_os_str().to_owned();
    aux.push(".aux.xml");
    [
        tiff.with_extension("tfw"),
        tiff.with_extension("prj"),
        PathBuf::from(aux),
    ]
}

/// GDAL's auxiliary file holding `wkt` as the raster's CRS, x then y.
pub(crate) fn aux_xml(wkt: &str) -> String {
    let escaped = wkt
        .replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;");
    format!(
        "<PAMDataset>\n  <SRS dataAxisToSRSAxisMapping=\"1,2\">{escaped}</SRS>\n</PAMDataset>\n"
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ingest::GeoKeys;

    /// Looking straight down at a survey-sized coordinate, `height` world units tall.
    fn top_camera(target: DVec3, height: f64, up: DVec3) -> Camera {
        Camera {
            position: target + DVec3::Z * 500.0,
            target,
            up,
            projection: Projection::Orthographic { height },
            near: 1.0,
            far: 1000.0,
        }
    }

    #[test]
    fn a_top_view_maps_pixels_to_the_ground_from_the_top_left_corner() {
        let target = DVec3::new(637_000.25, 851_000.5, 120.0);
        let camera = top_camera(target, 64.0, DVec3::Y);
        let map = GeoTransform::of_top_view(&camera, 96, 64).expect("a top view");
        assert!(map.is_north_up(), "{map:?}");
        // 64 units over 64 rows: one unit a pixel; the image is centred on the target.
        let [x0, dx, rx, y0, ry, dy] = map.gdal();
        assert!(
            (dx - 1.0).abs() < 1e-9 && (dy + 1.0).abs() < 1e-9,
            "{map:?}"
        );
        assert_eq!((rx, ry), (0.0, 0.0));
        assert!((x0 - (target.x - 48.0)).abs() < 1e-6, "{x0}");
        assert!((y0 - (target.y + 32.0)).abs() < 1e-6, "{y0}");
        let world = map.world_file();
        let lines: Vec<f64> = world.lines().map(|l| l.parse().expect("number")).collect();
        assert_eq!(lines.len(), 6);
        assert!((lines[4] - (target.x - 47.5)).abs() < 1e-6, "{world}");
        assert!((lines[5] - (target.y + 31.5)).abs() < 1e-6, "{world}");
    }

    #[test]
    fn an_empty_file_without_a_crs_leaves_the_scans_crs() {
        let Some(scan) = crate::testing::shared_data("lone-star.laz") else {
            eprintln!("skipped: shared/data/lone-star.laz is not in this checkout");
            return;
        };
        let dir = tempfile::tempdir().expect("tempdir");
        let empty = crate::testing::write_empty_files(dir.path(), &["empty.las"]);
        let alone = GeoCrs::of_files(std::slice::from_ref(&scan)).expect("the scan's CRS");
        assert!(matches!(alone, GeoCrs::Epsg { .. }), "{alone:?}");
        let mixed = [empty[0].clone(), scan];
        assert_eq!(
            GeoCrs::of_files(&mixed).expect("with the empty file"),
            alone
        );
        // Empty files alone decide, and declare none.
        assert!(matches!(
            GeoCrs::of_files(&empty).expect("the empty file's"),
            GeoCrs::Unknown(_)
        ));
    }

    #[test]
    fn a_rotated_top_view_keeps_its_rotation_and_other_views_are_not_placed() {
        let target = DVec3::new(500_000.0, 4_000_000.0, 0.0);
        let rotated = top_camera(target, 10.0, DVec3::new(1.0, 1.0, 0.0));
        let map = GeoTransform::of_top_view(&rotated, 10, 10).expect("a top view");
        assert!(!map.is_north_up());
        // The image's up is north-east: a row down goes south-west.
        assert!(map.per_row.x < 0.0 && map.per_row.y < 0.0, "{map:?}");
        assert!((map.per_column.length() - 1.0).abs() < 1e-9);

        let oblique = Camera {
            position: target + DVec3::new(100.0, 0.0, 500.0),
            ..top_camera(target, 10.0, DVec3::Y)
        };
        assert_eq!(GeoTransform::of_top_view(&oblique, 10, 10), None);
        let perspective = Camera {
            projection: Projection::Perspective { fov_y_deg: 50.0 },
            ..top_camera(target, 10.0, DVec3::Y)
        };
        assert_eq!(GeoTransform::of_top_view(&perspective, 10, 10), None);
    }

    #[test]
    fn a_crs_becomes_epsg_keys_or_stays_wkt() {
        let projected = GeoKeys {
            projected: Some(2992),
            geographic: None,
            vertical: Some(6360),
        };
        assert_eq!(
            GeoCrs::of(&Crs::GeoTiff(projected)),
            GeoCrs::Epsg {
                kind: CrsKind::Projected,
                code: 2992,
                vertical: Some(6360)
            }
        );
        let user_defined = GeoKeys {
            projected: Some(GEOTIFF_USER_DEFINED),
            ..GeoKeys::default()
        };
        assert!(matches!(
            GeoCrs::of(&Crs::GeoTiff(user_defined)),
            GeoCrs::Unknown(_)
        ));
        let wkt = |text: &str, epsg| Crs::Wkt {
            wkt: text.to_owned(),
            name: None,
            epsg,
        };
        assert_eq!(
            GeoCrs::of(&wkt(
                "PROJCS[\"UTM 10N\",AUTHORITY[\"EPSG\",\"32610\"]]",
                Some(32610)
            )),
            GeoCrs::Epsg {
                kind: CrsKind::Projected,
                code: 32610,
                vertical: None
            }
        );
        let compound = "COMPD_CS[\"x + y\",PROJCS[\"x\"],VERT_CS[\"y\"]]";
        assert_eq!(
            GeoCrs::of(&wkt(compound, Some(9999))),
            GeoCrs::Wkt(compound.to_owned())
        );
        assert!(matches!(GeoCrs::of(&Crs::None), GeoCrs::Unknown(_)));
    }

    #[test]
    fn the_key_directory_counts_its_keys() {
        let crs = GeoCrs::Epsg {
            kind: CrsKind::Geographic,
            code: 4326,
            vertical: None,
        };
        assert_eq!(
            crs.key_directory(),
            vec![1, 1, 0, 3, 1024, 0, 1, 2, 1025, 0, 1, 1, 2048, 0, 1, 4326]
        );
    }
}

//! `pointfarm info --json`: one document, `{"files": [...], "summary": {...}}`, with the
//! lowerCamelCase keys of the other commands' JSON (the API's JSON mapping). A file that could
//! not be read has its `path` and `error`.

use anyhow::{Context, Result};
use pointfarm_render::cloud::{ColorSource, WorldBounds};
use pointfarm_render::ingest::{Attributes, Crs, FileInfo, PointSummary};
use serde::Serialize;

use crate::info::{class_name, color_words, crs_words, Report, Summary};

/// The document of `reports`, as one line of JSON.
pub(crate) fn document(reports: &[Report], summary: &Summary) -> Result<String> {
    let document = Document {
        files: reports
            .iter()
            .map(|report| match &report.outcome {
                Ok((info, points)) => {
                    FileJson::Read(Box::new(FileFacts::of(info, points.as_ref())))
                }
                Err(error) => FileJson::Unreadable {
                    path: report.path.display().to_string(),
                    error: error.to_string(),
                },
            })
            .collect(),
        summary: SummaryJson {
            files: summary.files,
            unreadable: summary.failed,
            points: summary.points,
            bounds: summary.bounds.as_ref().map(BoundsJson::of),
        },
    };
    serde_json::to_string(&document).context("encoding the JSON output")
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct Document {
    files: Vec<FileJson>,
    summary: SummaryJson,
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct SummaryJson {
    files: usize,
    unreadable: usize,
    points: u64,
    bounds: Option<BoundsJson>,
}

#[derive(Serialize)]
#[serde(untagged, rename_all_fields = "camelCase")]
enum FileJson {
    Read(Box<FileFacts>),
    Unreadable { path: String, error: String },
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct BoundsJson {
    min: [f64; 3],
    max: [f64; 3],
}

impl BoundsJson {
    fn of(bounds: &WorldBounds) -> Self {
        Self {
            min: bounds.min.to_array(),
            max: bounds.max.to_array(),
        }
    }
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct FileFacts {
    path: String,
    file_bytes: u64,
    version: String,
    point_format: u8,
    compressed: bool,
    record_bytes: u16,
    points: u64,
    points_by_return: Vec<u64>,
    vlrs: usize,
    evlrs: usize,
    bounds: BoundsJson,
    scale: [f64; 3],
    offset: [f64; 3],
    crs: Option<CrsJson>,
    attributes: AttributesJson,
    point_stats: Option<PointStats>,
}

impl FileFacts {
    fn of(info: &FileInfo, points: Option<&PointSummary>) -> Self {
        let (major, minor) = info.version;
        Self {
            path: info.path.display().to_string(),
            file_bytes: info.file_bytes,
            version: format!("{major}.{minor}"),
            point_format: info.point_format,
            compressed: info.compressed,
            record_bytes: info.record_len,
            points: info.points,
            points_by_return: info.points_by_return.clone(),
            vlrs: info.vlrs,
            evlrs: info.evlrs,
            bounds: BoundsJson::of(&info.bounds),
            scale: info.scale.to_array(),
            offset: info.offset.to_array(),
            crs: CrsJson::of(&info.crs),
            attributes: AttributesJson::of(&info.attributes),
            point_stats: points.map(PointStats::of),
        }
    }
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct AttributesJson {
    gps_time: bool,
    rgb: bool,
    nir: bool,
    waveform: bool,
    extra_bytes: u16,
    extra_names: Vec<String>,
}

impl AttributesJson {
    fn of(a: &Attributes) -> Self {
        Self {
            gps_time: a.gps_time,
            rgb: a.rgb,
            nir: a.nir,
            waveform: a.waveform,
            extra_bytes: a.extra_bytes,
            extra_names: a.extra_names.clone(),
        }
    }
}

/// The CRS: where it was read from (`source`), what it says, and in words.
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct CrsJson {
    #[serde(flatten)]
    source: CrsSource,
    description: String,
}

#[derive(Serialize)]
#[serde(tag = "source", rename_all_fields = "camelCase")]
enum CrsSource {
    #[serde(rename = "wkt")]
    Wkt {
        name: Option<String>,
        epsg: Option<u32>,
        wkt: String,
    },
    #[serde(rename = "geotiff")]
    GeoTiff {
        projected_code: Option<u16>,
        geographic_code: Option<u16>,
        vertical_code: Option<u16>,
    },
    /// A GeoKeyDirectory that cannot be read.
    #[serde(rename = "geotiff")]
    Unreadable { error: String },
}

impl CrsJson {
    fn of(crs: &Crs) -> Option<Self> {
        let source = match crs {
            Crs::Wkt { wkt, name, epsg } => CrsSource::Wkt {
                name: name.clone(),
                epsg: *epsg,
                wkt: wkt.clone(),
            },
            Crs::GeoTiff(keys) => CrsSource::GeoTiff {
                projected_code: keys.projected,
                geographic_code: keys.geographic,
                vertical_code: keys.vertical,
            },
            Crs::Unreadable(reason) => CrsSource::Unreadable {
                error: reason.clone(),
            },
            Crs::None => return None,
        };
        Some(Self {
            source,
            description: crs_words(crs),
        })
    }
}

/// What reading the points found.
#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct PointStats {
    points: u64,
    bounds: Option<BoundsJson>,
    classes: Vec<ClassCount>,
    returns: Vec<ReturnCount>,
    intensity: Option<Range<u16>>,
    color: ColorJson,
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct ClassCount {
    class: usize,
    name: Option<&'static str>,
    points: u64,
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct ReturnCount {
    #[serde(rename = "return")]
    number: usize,
    points: u64,
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct Range<T> {
    min: T,
    max: T,
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct ColorJson {
    rgb: bool,
    #[serde(flatten)]
    range: Option<RgbJson>,
    description: String,
}

#[derive(Serialize)]
#[serde(rename_all = "camelCase")]
struct RgbJson {
    varies: bool,
    eight_bit_in_16_bit_fields: bool,
    min: [u16; 3],
    max: [u16; 3],
}

impl PointStats {
    fn of(points: &PointSummary) -> Self {
        let counted = |counts: &[u64]| -> Vec<(usize, u64)> {
            counts
                .iter()
                .enumerate()
                .filter(|(_, &count)| count > 0)
                .map(|(index, &count)| (index, count))
                .collect()
        };
        Self {
            points: points.points,
            bounds: points.bounds.as_ref().map(BoundsJson::of),
            classes: counted(&points.classes)
                .into_iter()
                .map(|(class, points)| ClassCount {
                    class,
                    name: class_name(class),
                    points,
                })
                .collect(),
            returns: counted(&points.returns)
                .into_iter()
                .map(|(number, points)| ReturnCount { number, points })
                .collect(),
            intensity: points.intensity.map(|[min, max]| Range { min, max }),
            color: ColorJson {
                rgb: points.rgb.is_some(),
                range: points.rgb.map(|rgb| RgbJson {
                    varies: rgb.varies(),
                    eight_bit_in_16_bit_fields: rgb.source() == Some(ColorSource::Rgb8In16Bit),
                    min: rgb.min,
                    max: rgb.max,
                }),
                description: color_words(points),
            },
        }
    }
}

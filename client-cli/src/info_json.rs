//! `pointfarm info --json`: one document, `{"files": [...], "summary": {...}}`, named as the
//! other commands' JSON is (snake_case). A file that could not be read has its `path` and
//! `error`.

use pointfarm_render::cloud::{ColorSource, WorldBounds};
use pointfarm_render::ingest::{Crs, FileInfo, PointSummary};
use serde_json::{json, Value};

use crate::info::{class_name, color_words, crs_words, Report, Summary};

pub(crate) fn document(reports: &[Report], summary: &Summary) -> Value {
    let files: Vec<Value> = reports
        .iter()
        .map(|report| match &report.outcome {
            Ok((info, points)) => file_json(info, points.as_ref()),
            Err(error) => json!({
                "path": report.path.display().to_string(),
                "error": error.to_string(),
            }),
        })
        .collect();
    json!({
        "files": files,
        "summary": {
            "files": summary.files,
            "unreadable": summary.failed,
            "points": summary.points,
            "bounds": summary.bounds.as_ref().map(bounds_json),
        },
    })
}

fn bounds_json(bounds: &WorldBounds) -> Value {
    json!({ "min": bounds.min.to_array(), "max": bounds.max.to_array() })
}

fn file_json(info: &FileInfo, points: Option<&PointSummary>) -> Value {
    let (major, minor) = info.version;
    let a = &info.attributes;
    json!({
        "path": info.path.display().to_string(),
        "file_bytes": info.file_bytes,
        "version": format!("{major}.{minor}"),
        "point_format": info.point_format,
        "compressed": info.compressed,
        "record_bytes": info.record_len,
        "points": info.points,
        "points_by_return": info.points_by_return,
        "vlrs": info.vlrs,
        "evlrs": info.evlrs,
        "bounds": bounds_json(&info.bounds),
        "scale": info.scale.to_array(),
        "offset": info.offset.to_array(),
        "crs": crs_json(&info.crs),
        "attributes": {
            "gps_time": a.gps_time,
            "rgb": a.rgb,
            "nir": a.nir,
            "waveform": a.waveform,
            "extra_bytes": a.extra_bytes,
            "extra_names": a.extra_names,
        },
        "point_stats": points.map(points_json),
    })
}

fn crs_json(crs: &Crs) -> Value {
    let mut value = match crs {
        Crs::Wkt { wkt, name, epsg } => {
            json!({ "source": "wkt", "name": name, "epsg": epsg, "wkt": wkt })
        }
        Crs::GeoTiff(keys) => json!({
            "source": "geotiff",
            "projected_code": keys.projected,
            "geographic_code": keys.geographic,
            "vertical_code": keys.vertical,
        }),
        Crs::Unreadable(reason) => json!({ "source": "geotiff", "error": reason }),
        Crs::None => return Value::Null,
    };
    value["description"] = crs_words(crs).into();
    value
}

fn points_json(points: &PointSummary) -> Value {
    let classes: Vec<Value> = points
        .classes
        .iter()
        .enumerate()
        .filter(|(_, &count)| count > 0)
        .map(|(class, count)| json!({ "class": class, "name": class_name(class), "points": count }))
        .collect();
    let returns: Vec<Value> = points
        .returns
        .iter()
        .enumerate()
        .filter(|(_, &count)| count > 0)
        .map(|(number, count)| json!({ "return": number, "points": count }))
        .collect();
    let color = match points.rgb {
        Some(rgb) => json!({
            "rgb": true,
            "varies": rgb.varies(),
            "eight_bit_in_16_bit_fields": rgb.source() == Some(ColorSource::Rgb8In16Bit),
            "min": rgb.min,
            "max": rgb.max,
            "description": color_words(points),
        }),
        None => json!({ "rgb": false, "description": color_words(points) }),
    };
    json!({
        "points": points.points,
        "bounds": points.bounds.as_ref().map(bounds_json),
        "classes": classes,
        "returns": returns,
        "intensity": points.intensity.map(|[min, max]| json!({ "min": min, "max": max })),
        "color": color,
    })
}

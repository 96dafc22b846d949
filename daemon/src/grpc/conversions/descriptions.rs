//! What `pointfarm info` and `DescribeDataset` report, as the API describes it: a file's
//! header, CRS, attributes and points, a COPC file's octree, and a dataset's files together;
//! the one conversion, here and through a server.

use pointfarm_proto::v1 as pb;
use pointfarm_render::classification;
use pointfarm_render::cloud::{ColorSource, WorldBounds};
use pointfarm_render::copc::{CopcError, CopcSummary};
use pointfarm_render::ingest::{Attributes, Crs, PointSummary};

use super::{bounds_message, vec3_message};
use crate::describe::FileReport;

/// A file's report as the API describes it; the one conversion of what `pointfarm info`
/// reports, here and through a server.
pub fn copc_description(copc: &Result<CopcSummary, CopcError>) -> pb::CopcDescription {
    match copc {
        Ok(summary) => pb::CopcDescription {
            error: String::new(),
            center: Some(vec3_message(summary.info.center)),
            halfsize: summary.info.halfsize,
            spacing: summary.info.spacing,
            hierarchy_pages: saturating_u32(summary.pages),
            hierarchy_bytes: summary.page_bytes,
            nodes: summary.nodes as u64,
            depth: summary.depth.into(),
        },
        Err(error) => pb::CopcDescription {
            error: error.to_string(),
            ..pb::CopcDescription::default()
        },
    }
}

/// The attributes a file's points carry besides the ones every point has.
pub fn point_attributes_message(attributes: &Attributes) -> pb::PointAttributes {
    pb::PointAttributes {
        gps_time: attributes.gps_time,
        rgb: attributes.rgb,
        nir: attributes.nir,
        waveform: attributes.waveform,
        extra_bytes: attributes.extra_bytes.into(),
        extra_names: attributes.extra_names.clone(),
    }
}

pub fn file_description(report: &FileReport) -> pb::FileDescription {
    let path = report.path.display().to_string();
    let (info, points) = match &report.outcome {
        Ok((info, points)) => (info, points.as_ref()),
        Err(error) => {
            return pb::FileDescription {
                path,
                error: error.to_string(),
                ..pb::FileDescription::default()
            }
        }
    };
    let (version_major, version_minor) = info.version;
    let attributes = &info.attributes;
    pb::FileDescription {
        path,
        error: String::new(),
        file_bytes: info.file_bytes,
        version_major: version_major.into(),
        version_minor: version_minor.into(),
        point_format: info.point_format.into(),
        compressed: info.compressed,
        record_bytes: info.record_len.into(),
        points: info.points,
        points_by_return: info.points_by_return.clone(),
        vlrs: saturating_u32(info.vlrs),
        evlrs: saturating_u32(info.evlrs),
        bounds: Some(bounds_message(&info.bounds)),
        scale: Some(vec3_message(info.scale)),
        offset: Some(vec3_message(info.offset)),
        crs: crs_message(&info.crs),
        attributes: Some(point_attributes_message(attributes)),
        points_read: points.map(point_statistics_message),
        copc: report.copc.as_ref().map(copc_description),
    }
}

fn saturating_u32(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}

fn crs_message(crs: &Crs) -> Option<pb::Crs> {
    use pb::crs::Source;
    let source = match crs {
        Crs::Wkt { wkt, name, epsg } => Source::Wkt(pb::WktCrs {
            wkt: wkt.clone(),
            name: name.clone(),
            epsg: *epsg,
        }),
        Crs::GeoTiff(keys) => Source::Geotiff(pb::GeoTiffCrs {
            projected: keys.projected.map(u32::from),
            geographic: keys.geographic.map(u32::from),
            vertical: keys.vertical.map(u32::from),
        }),
        Crs::Unreadable(reason) => Source::Unreadable(reason.clone()),
        Crs::None => return None,
    };
    Some(pb::Crs {
        source: Some(source),
    })
}

fn point_statistics_message(points: &PointSummary) -> pb::PointStatistics {
    let occurring = |counts: &[u64]| -> Vec<(u32, u64)> {
        (0u32..)
            .zip(counts.iter().copied())
            .filter(|&(_, count)| count > 0)
            .collect()
    };
    pb::PointStatistics {
        points: points.points,
        bounds: points.bounds.as_ref().map(bounds_message),
        classes: occurring(&points.classes)
            .into_iter()
            .map(|(code, points)| pb::ClassCount {
                code,
                name: u8::try_from(code)
                    .ok()
                    .and_then(classification::class_name)
                    .unwrap_or_default()
                    .to_owned(),
                points,
            })
            .collect(),
        returns: occurring(&points.returns)
            .into_iter()
            .map(|(return_number, points)| pb::ReturnCount {
                return_number,
                points,
            })
            .collect(),
        intensity: points.intensity.map(|[min, max]| pb::IntensityRange {
            min: min.into(),
            max: max.into(),
        }),
        rgb: points.rgb.map(|rgb| pb::RgbRange {
            min: rgb.min.map(u32::from).to_vec(),
            max: rgb.max.map(u32::from).to_vec(),
            varies: rgb.varies(),
            eight_bit_values: rgb.source() == Some(ColorSource::Rgb8In16Bit),
        }),
    }
}

/// The description of `files` (already described, in order) with what they have together.
pub fn dataset_description(
    dataset_id: &str,
    files: Vec<pb::FileDescription>,
) -> pb::DatasetDescription {
    let read: Vec<&pb::FileDescription> = files.iter().filter(|f| f.error.is_empty()).collect();
    let corners = |b: &pb::Bounds| {
        let corner = |v: &Option<pb::Vec3>| {
            v.as_ref()
                .map(|v| glam::DVec3::new(v.x, v.y, v.z))
                .unwrap_or(glam::DVec3::NAN)
        };
        (corner(&b.min), corner(&b.max))
    };
    // A file without points (an empty tile) says nothing of where the dataset lies.
    let bounds = read
        .iter()
        .filter(|f| f.points > 0)
        .filter_map(|f| f.bounds.as_ref().map(corners))
        .filter(|(min, max)| min.is_finite() && max.is_finite() && min.cmple(*max).all())
        .reduce(|(min_a, max_a), (min_b, max_b)| (min_a.min(min_b), max_a.max(max_b)))
        .map(|(min, max)| bounds_message(&WorldBounds { min, max }));
    let summary = pb::DescriptionSummary {
        files: saturating_u32(files.len()),
        unreadable: saturating_u32(files.len() - read.len()),
        points: read.iter().map(|f| f.points).sum(),
        bounds,
    };
    pb::DatasetDescription {
        dataset_id: dataset_id.to_owned(),
        files,
        summary: Some(summary),
    }
}

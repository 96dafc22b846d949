//! The bytes around the points of a COPC 1.0 file: the LAS 1.4 header, the `copc` info VLR
//! (first, at byte 375), the LASzip VLR, and after the chunk table the hierarchy EVLR and the
//! export's node grids.
//!
//! ```text
//! header (375) | VLR "copc" 1: info (54 + 160) | VLR "laszip encoded" 22204 (54 + 34 + 6n)
//! | VLR "LASF_Spec" 4: extra bytes, the weight and what the files had (54 + 192 each)
//! | [VLR "LASF_Projection" 2112: the dataset's WKT] | offset of the chunk table (8) | one LAZ chunk per node | chunk table
//! | EVLR "copc" 1000: hierarchy (60 + 32 per node)
//! | EVLR "pointfarm" 1: node grids (60 + 20 per inner node, `node_grids.rs`)
//! ```
//!
//! The hierarchy is one page: every node's entry (key, chunk offset, chunk bytes, points),
//! in the store's key order. A store's hierarchy is small (about a node per 20,000 points),
//! so a page of a billion points' nodes is a few MB, which readers load at once anyway.

use glam::DVec3;
use laz::LazVlr;

use super::records::RecordFormat;
use super::transform::ExportTransform;
use crate::extra_bytes;

/// Bytes of a LAS 1.4 header.
pub const HEADER_BYTES: u64 = 375;
/// Bytes of a VLR's header.
const VLR_HEADER_BYTES: u64 = 54;
/// Bytes of an EVLR's header.
const EVLR_HEADER_BYTES: u64 = 60;
/// Bytes of the info VLR's payload.
const INFO_BYTES: u64 = 160;
/// Bytes of a hierarchy entry.
pub const ENTRY_BYTES: u64 = 32;
/// LAS's global encoding bit that says a CRS, if any, is WKT (required with PDRF 6 and up).
const GLOBAL_ENCODING_WKT: u16 = 1 << 4;
/// The point format's bit that marks LAZ-compressed points.
const COMPRESSED_BIT: u8 = 0x80;

/// The LASzip description of an export's points: layered (LAZ 1.4) items, variable-size
/// chunks (one a node).
pub fn laz_vlr(format: &RecordFormat) -> LazVlr {
    let items = laz::LazItemRecordBuilder::default_for_point_format_id(
        format.point_format(),
        format.extra_len() as u16,
    )
    .expect("PDRF 6, 7 and 8 with extra bytes are LAZ point formats");
    laz::LazVlrBuilder::new(items)
        .with_variable_chunk_size()
        .build()
}

/// Where the point data starts: after the header and the VLRs (the WKT's when there is one).
pub fn point_data_offset(laz: &LazVlr, format: &RecordFormat, wkt: Option<&[u8]>) -> u64 {
    let wkt = wkt.map_or(0, |w| VLR_HEADER_BYTES + w.len() as u64);
    HEADER_BYTES
        + VLR_HEADER_BYTES
        + INFO_BYTES
        + VLR_HEADER_BYTES
        + laz_payload(laz).len() as u64
        + VLR_HEADER_BYTES
        + format.extra_bytes_vlr().len() as u64
        + wkt
}

fn laz_payload(laz: &LazVlr) -> Vec<u8> {
    let mut data = Vec::new();
    laz.write_to(&mut data).expect("writing to memory");
    data
}

fn fixed<const N: usize>(text: &str) -> [u8; N] {
    let mut out = [0; N];
    let bytes = text.as_bytes();
    let n = bytes.len().min(N);
    out[..n].copy_from_slice(&bytes[..n]);
    out
}

fn vlr(user_id: &str, record_id: u16, description: &str, data: Vec<u8>, extended: bool) -> Vec<u8> {
    let record_length_after_header = if extended {
        las::raw::vlr::RecordLength::Evlr(data.len() as u64)
    } else {
        las::raw::vlr::RecordLength::Vlr(data.len() as u16)
    };
    let raw = las::raw::Vlr {
        reserved: 0,
        user_id: fixed(user_id),
        record_id,
        record_length_after_header,
        description: fixed(description),
        data,
    };
    let mut out = Vec::new();
    raw.write_to(&mut out).expect("writing to memory");
    out
}

/// What the header and the info VLR say of the file once its points are written.
pub struct FileFacts {
    pub format: RecordFormat,
    /// Lowest and highest GPS time of the points, where they carry it.
    pub gps_range: Option<[f64; 2]>,
    pub transform: ExportTransform,
    pub points: u64,
    pub by_return: [u64; 15],
    pub min: DVec3,
    pub max: DVec3,
    /// The octree's cube: centre and half its side.
    pub centre: DVec3,
    pub halfsize: f64,
    /// Distance between points at the root; halved at each level.
    pub spacing: f64,
    /// Where the hierarchy EVLR's header starts, and the entries' bytes after it.
    pub evlr_start: u64,
    pub hierarchy_bytes: u64,
    /// The dataset's OGC WKT record, carried as it is.
    pub wkt: Option<Vec<u8>>,
}

/// The header and the VLRs: every byte before the point data.
pub fn head(facts: &FileFacts, laz: &LazVlr) -> Vec<u8> {
    let data_offset = point_data_offset(laz, &facts.format, facts.wkt.as_deref());
    let header = las::raw::Header {
        global_encoding: GLOBAL_ENCODING_WKT,
        version: las::Version::new(1, 4),
        system_identifier: fixed("pointfarm COPC export"),
        generating_software: fixed(concat!("pointfarm ", env!("CARGO_PKG_VERSION"))),
        header_size: HEADER_BYTES as u16,
        offset_to_point_data: data_offset as u32,
        number_of_variable_length_records: 3 + u32::from(facts.wkt.is_some()),
        point_data_record_format: facts.format.point_format() | COMPRESSED_BIT,
        point_data_record_length: facts.format.record_len() as u16,
        // The legacy counts stay 0: PDRF 6 and up count in the 64-bit fields only.
        number_of_point_records: 0,
        number_of_points_by_return: [0; 5],
        x_scale_factor: facts.transform.scale.x,
        y_scale_factor: facts.transform.scale.y,
        z_scale_factor: facts.transform.scale.z,
        x_offset: facts.transform.offset.x,
        y_offset: facts.transform.offset.y,
        z_offset: facts.transform.offset.z,
        max_x: facts.max.x,
        min_x: facts.min.x,
        max_y: facts.max.y,
        min_y: facts.min.y,
        max_z: facts.max.z,
        min_z: facts.min.z,
        start_of_waveform_data_packet_record: Some(0),
        evlr: Some(las::raw::header::Evlr {
            start_of_first_evlr: facts.evlr_start,
            // The hierarchy and the node grids.
            number_of_evlrs: 2,
        }),
        large_file: Some(las::raw::header::LargeFile {
            number_of_point_records: facts.points,
            number_of_points_by_return: facts.by_return,
        }),
        ..Default::default()
    };
    let mut out = Vec::with_capacity(data_offset as usize);
    header.write_to(&mut out).expect("writing to memory");
    debug_assert_eq!(out.len() as u64, HEADER_BYTES);
    out.extend(vlr("copc", 1, "COPC info VLR", info(facts), false));
    out.extend(vlr(
        LazVlr::USER_ID,
        LazVlr::RECORD_ID,
        LazVlr::DESCRIPTION,
        laz_payload(laz),
        false,
    ));
    out.extend(vlr(
        extra_bytes::USER_ID,
        extra_bytes::RECORD_ID,
        "Extra Bytes Record",
        facts.format.extra_bytes_vlr(),
        false,
    ));
    if let Some(wkt) = &facts.wkt {
        out.extend(vlr(
            super::crs::PROJECTION_USER_ID,
            super::crs::WKT_RECORD_ID,
            "OGC WKT",
            wkt.clone(),
            false,
        ));
    }
    debug_assert_eq!(out.len() as u64, data_offset);
    out
}

/// The info VLR's 160 bytes.
fn info(facts: &FileFacts) -> Vec<u8> {
    let mut out = Vec::with_capacity(INFO_BYTES as usize);
    for v in [
        facts.centre.x,
        facts.centre.y,
        facts.centre.z,
        facts.halfsize,
        facts.spacing,
    ] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&(facts.evlr_start + EVLR_HEADER_BYTES).to_le_bytes());
    out.extend_from_slice(&facts.hierarchy_bytes.to_le_bytes());
    let [gps_min, gps_max] = facts.gps_range.unwrap_or([0.0; 2]);
    out.extend_from_slice(&gps_min.to_le_bytes());
    out.extend_from_slice(&gps_max.to_le_bytes());
    out.resize(INFO_BYTES as usize, 0);
    out
}

/// One hierarchy entry: a node's key, its chunk's offset and bytes, and its points.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HierarchyEntry {
    pub level: i32,
    pub x: i32,
    pub y: i32,
    pub z: i32,
    pub offset: u64,
    pub byte_size: i32,
    pub point_count: i32,
}

/// The hierarchy EVLR: its header and one page of `entries`.
pub fn hierarchy_evlr(entries: &[HierarchyEntry]) -> Vec<u8> {
    let mut data = Vec::with_capacity(entries.len() * ENTRY_BYTES as usize);
    for e in entries {
        for v in [e.level, e.x, e.y, e.z] {
            data.extend_from_slice(&v.to_le_bytes());
        }
        data.extend_from_slice(&e.offset.to_le_bytes());
        data.extend_from_slice(&e.byte_size.to_le_bytes());
        data.extend_from_slice(&e.point_count.to_le_bytes());
    }
    vlr("copc", 1000, "EPT hierarchy", data, true)
}

/// The node grids EVLR: its header and `data` (`node_grids::encode`).
pub fn node_grids_evlr(data: Vec<u8>) -> Vec<u8> {
    use super::node_grids::{DESCRIPTION, RECORD_ID, USER_ID};
    vlr(USER_ID, RECORD_ID, DESCRIPTION, data, true)
}

//! What a COPC file's header and VLRs say, read after the checks every LAS/LAZ file passes
//! (`ingest::check_file_with`, the chunk table but not each chunk, which is checked as it is
//! decoded): the point layout, the transforms and bounds, the LASzip items and
//! the COPC info VLR (the octree's cube, the root spacing, where the first hierarchy page
//! lies). The info VLR's fields are read here rather than through `las::copc::CopcInfoVlr`,
//! whose page offset and size are private.

use std::path::Path;
use std::sync::Arc;

use glam::DVec3;

use super::bytes::{CopcBytes, RangeReader};
use super::error::CopcError;
use super::node_grids::{read_node_grids, NodeGrids};
use crate::cloud::{WorldBounds, MAX_COORDINATE};
use crate::extra_bytes;
use crate::ingest::{check_file_with, ChunkChecks, IngestError};
use crate::lod::weights::WEIGHT_ATTRIBUTE;
use crate::lod::RootCube;

/// A LAS 1.4 header's size: where COPC's info VLR must start.
const COPC_INFO_OFFSET: u64 = 375;
const VLR_HEADER_LEN: u64 = 54;
const COPC_USER_ID: &[u8; 16] = b"copc\0\0\0\0\0\0\0\0\0\0\0\0";
const COPC_INFO_RECORD_ID: u16 = 1;
/// Bytes of the info VLR's data.
const COPC_INFO_LEN: u64 = 160;
const LASZIP_USER_ID: &[u8; 16] = b"laszip encoded\0\0";
const LASZIP_RECORD_ID: u16 = 22204;
/// Bytes of one hierarchy entry: voxel key (4 x i32), offset u64, byte size i32, count i32.
pub(crate) const ENTRY_BYTES: u64 = 32;

/// Where a hierarchy page lies in the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct PageRef {
    pub offset: u64,
    pub size: u64,
}

/// The COPC info VLR.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CopcInfo {
    /// The octree's cube: its centre and the distance from it to each side.
    pub center: DVec3,
    pub halfsize: f64,
    /// The spacing of the root node's points, halved at each level below.
    pub spacing: f64,
    pub(crate) root_page: PageRef,
}

impl CopcInfo {
    pub fn cube(&self) -> RootCube {
        RootCube {
            min: self.center - DVec3::splat(self.halfsize),
            side: 2.0 * self.halfsize,
        }
    }
}

/// A COPC file's header facts, checked.
pub(crate) struct CopcHeader {
    pub file_len: u64,
    pub point_count: u64,
    pub format: las::point::Format,
    pub transforms: las::Vector<las::Transform>,
    pub bounds: WorldBounds,
    pub offset_to_point_data: u64,
    pub laz_items: Vec<laz::LazItem>,
    /// The LASzip VLR's data as stored, which a worker decoding this file's chunks is sent.
    pub laszip_vlr: Vec<u8>,
    /// Where a record holds its point's weight (a pointfarm export's extra bytes attribute),
    /// in bytes from the record's start; `None` for files without one.
    pub weight_at: Option<u16>,
    pub info: CopcInfo,
    /// Inner nodes' sampling grids, where a pointfarm export records them.
    pub node_grids: Arc<NodeGrids>,
    /// VLRs and EVLRs it holds.
    pub vlrs: u32,
    pub evlrs: u32,
    /// The names the extra bytes VLR gives the records' extra bytes, in order.
    pub extra_names: Vec<String>,
}

/// Whether `path` is a COPC file: LAS 1.4 whose first VLR is COPC's info VLR (where the
/// specification puts it). A file too short to say is not; ingest reports what is wrong
/// with it.
pub fn is_copc(path: &Path) -> Result<bool, CopcError> {
    starts_as_copc(&mut CopcBytes::file(path)?.reader())
}

/// Whether the bytes `reader` reads start as a COPC file's do; a file too short to say
/// does not.
pub(crate) fn starts_as_copc(reader: &mut RangeReader<'_>) -> Result<bool, CopcError> {
    let head_len = COPC_INFO_OFFSET + VLR_HEADER_LEN;
    if reader.size() < head_len {
        return Ok(false);
    }
    let head = reader.read_at(0, head_len)?;
    Ok(head.starts_with(crate::ingest::LAS_SIGNATURE)
        && head[24..26] == [1, 4]
        && u16::from_le_bytes([head[94], head[95]]) as u64 == COPC_INFO_OFFSET
        && is_copc_info(&head[COPC_INFO_OFFSET as usize..]))
}

fn is_copc_info(vlr_header: &[u8]) -> bool {
    vlr_header[2..18] == COPC_USER_ID[..]
        && u16::from_le_bytes([vlr_header[18], vlr_header[19]]) == COPC_INFO_RECORD_ID
}

fn not_copc(path: &Path, reason: impl Into<String>) -> CopcError {
    CopcError::NotCopc {
        path: path.to_owned(),
        reason: reason.into(),
    }
}

fn bad_info(path: &Path, reason: impl Into<String>) -> CopcError {
    CopcError::Info {
        path: path.to_owned(),
        reason: reason.into(),
    }
}

/// Reads and checks the header of the COPC file `bytes`.
pub(crate) fn read_header(bytes: &CopcBytes) -> Result<CopcHeader, CopcError> {
    let mut reader = bytes.reader();
    read_header_from(&mut reader).map_err(|error| reader.error(error))
}

fn read_header_from(reader: &mut RangeReader<'_>) -> Result<CopcHeader, CopcError> {
    let (path, file_len) = (reader.name(), reader.size());
    // Each chunk's layer table is checked as the chunk is decoded (`CopcDecoder`).
    let checked = check_file_with(&path, reader, file_len, ChunkChecks::Table)?;
    let path = path.as_path();
    // Its first bytes are read already: a plain LAS/LAZ file is told apart without a request.
    if !starts_as_copc(reader)? {
        return Err(not_copc(
            path,
            "it does not start as one (LAS 1.4 with COPC's info VLR first)",
        ));
    }
    let facts = &checked.facts;
    if !facts.compressed {
        return Err(not_copc(path, "its points are not LAZ-compressed"));
    }
    if !(6..=8).contains(&facts.point_format) {
        return Err(not_copc(
            path,
            format!(
                "point format {} (COPC allows 6, 7 and 8)",
                facts.point_format
            ),
        ));
    }
    let mut format = las::point::Format::new(facts.point_format)
        .map_err(|error| not_copc(path, error.to_string()))?;
    format.extra_bytes = facts
        .record_len
        .checked_sub(format.len())
        .ok_or_else(|| not_copc(path, "records shorter than their point format"))?;

    // The header block itself: inside the file, as the pre-parse checked.
    let block = reader.read_at(0, u64::from(facts.header_size))?;
    let raw =
        las::raw::Header::read_from(block.as_slice()).map_err(|error| IngestError::Malformed {
            path: path.to_owned(),
            error,
        })?;
    let transforms = las::Vector {
        x: transform(raw.x_scale_factor, raw.x_offset),
        y: transform(raw.y_scale_factor, raw.y_offset),
        z: transform(raw.z_scale_factor, raw.z_offset),
    };
    let bounds = WorldBounds {
        min: DVec3::new(raw.min_x, raw.min_y, raw.min_z),
        max: DVec3::new(raw.max_x, raw.max_y, raw.max_z),
    };

    // The VLRs, whose extents the pre-parse checked: the info VLR first, and LASzip's.
    let mut info = None;
    let mut laz_items = None;
    let mut laszip_vlr = Vec::new();
    let mut extra_bytes_vlr = None;
    let mut offset = u64::from(facts.header_size);
    for index in 0..facts.vlr_count {
        let vlr_header = reader.read_at(offset, VLR_HEADER_LEN)?;
        let len = u64::from(u16::from_le_bytes([vlr_header[20], vlr_header[21]]));
        let data_at = offset + VLR_HEADER_LEN;
        if index == 0 && is_copc_info(&vlr_header) {
            if len < COPC_INFO_LEN {
                return Err(bad_info(path, format!("{len} bytes, 160 expected")));
            }
            let data = reader.read_at(data_at, COPC_INFO_LEN)?;
            info = Some(parse_info(path, &data)?);
        } else if vlr_header[2..18] == LASZIP_USER_ID[..]
            && u16::from_le_bytes([vlr_header[18], vlr_header[19]]) == LASZIP_RECORD_ID
        {
            let data = reader.read_at(data_at, len)?;
            let vlr = laz::LazVlr::from_buffer(&data)
                .map_err(|error| not_copc(path, format!("its LASzip VLR: {error}")))?;
            laz_items = Some(vlr.items().clone());
            laszip_vlr = data;
        } else if is_extra_bytes(&vlr_header) {
            extra_bytes_vlr = Some(reader.read_at(data_at, len)?);
        }
        offset = data_at + len;
    }
    let info = info.ok_or_else(|| not_copc(path, "its first VLR is not COPC's info VLR"))?;
    let laz_items = laz_items.ok_or_else(|| not_copc(path, "it has no LASzip VLR"))?;
    if laz_items
        .iter()
        .any(|item| u16::from(item.item_type()) < 10)
    {
        return Err(not_copc(
            path,
            "its LAZ items are not LAS 1.4's layered ones",
        ));
    }

    let extra_names = extra_bytes_vlr
        .as_deref()
        .map(|data| {
            extra_bytes::parse(data)
                .into_iter()
                .map(|d| d.name)
                .collect()
        })
        .unwrap_or_default();
    let weight_at = extra_bytes_vlr.and_then(|data| weight_offset(&format, &data));
    let node_grids = Arc::new(read_node_grids(reader, facts.evlrs)?);
    let header = CopcHeader {
        file_len,
        point_count: facts.declared_points,
        format,
        transforms,
        bounds,
        offset_to_point_data: facts.offset_to_point_data,
        laz_items,
        laszip_vlr,
        weight_at,
        info,
        node_grids,
        vlrs: facts.vlr_count,
        evlrs: facts.evlrs.map_or(0, |(_, count)| count),
        extra_names,
    };
    check_info(path, &header)?;
    Ok(header)
}

fn is_extra_bytes(vlr_header: &[u8]) -> bool {
    let user_id = &vlr_header[2..18];
    let end = user_id
        .iter()
        .position(|&b| b == 0)
        .unwrap_or(user_id.len());
    &user_id[..end] == extra_bytes::USER_ID.as_bytes()
        && u16::from_le_bytes([vlr_header[18], vlr_header[19]]) == extra_bytes::RECORD_ID
}

/// Where the weight attribute lies in a record of `format`, when the extra bytes VLR `data`
/// describes one that fits the record's extra bytes.
fn weight_offset(format: &las::point::Format, data: &[u8]) -> Option<u16> {
    let descriptors = extra_bytes::parse(data);
    let at = extra_bytes::offset_of(&descriptors, WEIGHT_ATTRIBUTE, extra_bytes::DATA_TYPE_U32)?;
    let at = u16::try_from(at).ok()?;
    (at.checked_add(4)? <= format.extra_bytes).then(|| format.len() - format.extra_bytes + at)
}

fn transform(scale: f64, offset: f64) -> las::Transform {
    las::Transform { scale, offset }
}

/// The info VLR's fields, from its [`COPC_INFO_LEN`] bytes.
fn parse_info(path: &Path, data: &[u8]) -> Result<CopcInfo, CopcError> {
    let f64_at = |at: usize| f64::from_le_bytes(data[at..at + 8].try_into().unwrap_or([0; 8]));
    let u64_at = |at: usize| u64::from_le_bytes(data[at..at + 8].try_into().unwrap_or([0; 8]));
    let center = DVec3::new(f64_at(0), f64_at(8), f64_at(16));
    let (halfsize, spacing) = (f64_at(24), f64_at(32));
    if !center.is_finite() || center.abs().max_element() > MAX_COORDINATE {
        return Err(bad_info(
            path,
            format!("centre {center} is not a usable coordinate"),
        ));
    }
    if !(halfsize.is_finite() && halfsize > 0.0 && halfsize <= MAX_COORDINATE) {
        return Err(bad_info(
            path,
            format!("half size {halfsize} is not a positive size"),
        ));
    }
    if !(spacing.is_finite() && spacing > 0.0) {
        return Err(bad_info(
            path,
            format!("spacing {spacing} is not a positive size"),
        ));
    }
    Ok(CopcInfo {
        center,
        halfsize,
        spacing,
        root_page: PageRef {
            offset: u64_at(40),
            size: u64_at(48),
        },
    })
}

/// The root page must lie in the file after the points; the header's bounds inside the cube.
fn check_info(path: &Path, header: &CopcHeader) -> Result<(), CopcError> {
    let root = header.info.root_page;
    check_page(path, header, root, "the root hierarchy page")?;
    let cube = header.info.cube();
    let b = header.bounds;
    let scale = DVec3::new(
        header.transforms.x.scale,
        header.transforms.y.scale,
        header.transforms.z.scale,
    )
    .abs();
    let slack = scale + DVec3::splat(cube.side * 1e-9);
    let inside = (cube.min - slack).cmple(b.min).all()
        && b.max
            .cmple(cube.min + DVec3::splat(cube.side) + slack)
            .all();
    if !inside {
        return Err(bad_info(
            path,
            format!(
                "the header's bounds {}..{} lie outside the octree's cube {}..{}",
                b.min,
                b.max,
                cube.min,
                cube.min + DVec3::splat(cube.side)
            ),
        ));
    }
    Ok(())
}

/// A hierarchy page must be whole entries, after the point data, inside the file.
pub(crate) fn check_page(
    path: &Path,
    header: &CopcHeader,
    page: PageRef,
    what: &str,
) -> Result<(), CopcError> {
    check_page_bounds(
        path,
        header.offset_to_point_data,
        header.file_len,
        page,
        what,
    )
}

/// [`check_page`] against a file of `file_len` bytes whose point data starts at
/// `offset_to_point_data`.
pub(crate) fn check_page_bounds(
    path: &Path,
    offset_to_point_data: u64,
    file_len: u64,
    page: PageRef,
    what: &str,
) -> Result<(), CopcError> {
    if page.size == 0 || !page.size.is_multiple_of(ENTRY_BYTES) {
        return Err(CopcError::hierarchy(
            path,
            format!(
                "{what} is {} bytes, not a whole number of 32-byte entries",
                page.size
            ),
        ));
    }
    let end = page.offset.checked_add(page.size);
    if page.offset < offset_to_point_data || end.is_none_or(|end| end > file_len) {
        return Err(CopcError::hierarchy(
            path,
            format!(
                "{what} ({} bytes at offset {}) lies outside the file's {} bytes after the point data at {}",
                page.size, page.offset, file_len, offset_to_point_data
            ),
        ));
    }
    Ok(())
}

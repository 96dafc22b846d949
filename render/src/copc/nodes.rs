//! `CopcNodes`: a COPC file's nodes as [`NodeRecords`]. A node's record is its LAZ chunk,
//! read by byte range (a wave's chunks in one read of many ranges: positioned reads on many
//! threads for a file, coalesced parallel requests for an object) and decoded here into
//! [`NodePoints`] as a store's nodes are: positions quantised in the node's cube, raw RGB,
//! intensity, classification and return number.
//!
//! A chunk is checked before the decoder sees it: its byte size is its entry's, its layer
//! table fits in it, it holds its entry's point count, and the records it decodes to are
//! bounded by its size (the decoder allocates what a chunk declares). What the decoder can
//! still panic on is contained and reported naming the file and the node.

use std::io::Cursor;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::DVec3;
use laz::record::{LayeredPointRecordDecompressor, RecordDecompressor};

use super::bytes::CopcBytes;
use super::error::CopcError;
use super::header::CopcHeader;
use crate::ingest::{contain_panics, layer_count};
use crate::lod::codec::{Detail, POSITION_BITS};
use crate::lod::weights::encode_weight;
use crate::lod::{LodError, NodeInfo, NodePoints, NodeRecords, RootCube};

/// The most bytes of records a chunk may decode to beyond [`MAX_DECODED_PER_BYTE`] times its
/// own size: enough for any real node, never a huge allocation from a forged count.
const MIN_DECODED_BOUND: u64 = 64 << 20;
/// Decoded record bytes per compressed byte that a chunk may claim beyond the bound above.
const MAX_DECODED_PER_BYTE: u64 = 1024;

/// What decoding a COPC file's LAZ chunks needs, wherever they were read (the file here, or
/// a daemon that keeps it): the point layout, transforms and LASzip items of its header.
#[derive(Clone)]
pub struct CopcDecoder {
    /// Names the file in every error.
    path: PathBuf,
    point_format: u8,
    format: las::point::Format,
    transforms: las::Vector<las::Transform>,
    laz_items: Vec<laz::LazItem>,
    /// The LASzip VLR's data, from which `laz_items` were read.
    laszip_vlr: Vec<u8>,
    /// Layer sizes a chunk stores after its first record and its point count.
    layers: u64,
    /// Where a record holds its point's weight, when the file keeps weights.
    weight_at: Option<u16>,
}

impl CopcDecoder {
    fn of_header(path: &Path, header: &CopcHeader) -> Self {
        Self::new(
            path,
            header.format,
            header.transforms,
            header.laz_items.clone(),
            header.laszip_vlr.clone(),
            header.weight_at,
        )
    }

    fn new(
        path: &Path,
        format: las::point::Format,
        transforms: las::Vector<las::Transform>,
        laz_items: Vec<laz::LazItem>,
        laszip_vlr: Vec<u8>,
        weight_at: Option<u16>,
    ) -> Self {
        let layers = laz_items
            .iter()
            .map(|item| layer_count(u16::from(item.item_type()), item.size()))
            .sum();
        Self {
            path: path.to_owned(),
            point_format: format.to_u8().unwrap_or(0),
            format,
            transforms,
            laz_items,
            laszip_vlr,
            layers,
            weight_at,
        }
    }

    /// A decoder from what a COPC file's header says, sent apart from the file (`path` names
    /// it in errors), checked as the file's header is: a point format COPC allows, records
    /// as long as their LAZ items, usable transforms, a LASzip VLR of layered items, and a
    /// weight, if any, within the records' extra bytes.
    pub fn from_parts(
        path: &Path,
        point_format: u8,
        record_len: u16,
        scale: [f64; 3],
        offset: [f64; 3],
        laszip_vlr: &[u8],
        weight_at: Option<u16>,
    ) -> Result<Self, CopcError> {
        let not_copc = |reason: String| CopcError::NotCopc {
            path: path.to_owned(),
            reason,
        };
        if !(6..=8).contains(&point_format) {
            return Err(not_copc(format!(
                "point format {point_format} (COPC allows 6, 7 and 8)"
            )));
        }
        let mut format =
            las::point::Format::new(point_format).map_err(|e| not_copc(e.to_string()))?;
        format.extra_bytes = record_len
            .checked_sub(format.len())
            .ok_or_else(|| not_copc("records shorter than their point format".into()))?;
        if scale.iter().any(|s| !s.is_finite() || *s == 0.0)
            || offset.iter().any(|o| !o.is_finite())
        {
            return Err(not_copc(format!(
                "scale {scale:?} and offset {offset:?} are not usable transforms"
            )));
        }
        let vlr = laz::LazVlr::from_buffer(laszip_vlr)
            .map_err(|error| not_copc(format!("its LASzip VLR: {error}")))?;
        let items = vlr.items().clone();
        if items.iter().any(|item| u16::from(item.item_type()) < 10) {
            return Err(not_copc(
                "its LAZ items are not LAS 1.4's layered ones".into(),
            ));
        }
        let items_len: u64 = items.iter().map(|item| u64::from(item.size())).sum();
        if items_len != u64::from(record_len) {
            return Err(not_copc(format!(
                "its LAZ items take {items_len} bytes a point, its records {record_len}"
            )));
        }
        if let Some(at) = weight_at {
            let fields = format.len() - format.extra_bytes;
            if at < fields || u32::from(at) + 4 > u32::from(record_len) {
                return Err(not_copc(format!(
                    "a weight at byte {at} lies outside the extra bytes ({fields} to {record_len})"
                )));
            }
        }
        let transform = |axis: usize| las::Transform {
            scale: scale[axis],
            offset: offset[axis],
        };
        let transforms = las::Vector {
            x: transform(0),
            y: transform(1),
            z: transform(2),
        };
        Ok(Self::new(
            path,
            format,
            transforms,
            items,
            laszip_vlr.to_vec(),
            weight_at,
        ))
    }

    pub fn point_format(&self) -> u8 {
        self.point_format
    }

    /// Bytes of one point record, extra bytes included.
    pub fn record_len(&self) -> u16 {
        self.format.len()
    }

    pub fn scale(&self) -> [f64; 3] {
        let t = &self.transforms;
        [t.x.scale, t.y.scale, t.z.scale]
    }

    pub fn offset(&self) -> [f64; 3] {
        let t = &self.transforms;
        [t.x.offset, t.y.offset, t.z.offset]
    }

    pub fn laszip_vlr(&self) -> &[u8] {
        &self.laszip_vlr
    }

    /// Where a record holds its point's weight; `None` where the file keeps none.
    pub fn weight_at(&self) -> Option<u16> {
        self.weight_at
    }

    /// A chunk's points, checked against its entry.
    pub fn decode_chunk(
        &self,
        cube: &RootCube,
        info: &NodeInfo,
        bytes: &[u8],
    ) -> Result<NodePoints, CopcError> {
        let bad = |reason: String| CopcError::Node {
            path: self.path.clone(),
            key: info.key,
            reason,
        };
        let count = u64::from(info.point_count);
        let record_len = u64::from(self.format.len());
        let len = bytes.len() as u64;
        if len != u64::from(info.byte_len) {
            return Err(bad(format!(
                "{len} bytes read, its entry says {}",
                info.byte_len
            )));
        }
        // A layered chunk: one raw record, the point count, then every layer's size.
        let count_at = record_len as usize;
        let prelude = record_len + 4 + 4 * self.layers;
        if len < prelude {
            return Err(bad(format!(
                "its chunk of {len} bytes is shorter than its layer table ({prelude} bytes)"
            )));
        }
        let chunk_count = u32::from_le_bytes([
            bytes[count_at],
            bytes[count_at + 1],
            bytes[count_at + 2],
            bytes[count_at + 3],
        ]);
        if u64::from(chunk_count) != count {
            return Err(bad(format!(
                "its chunk holds {chunk_count} points, its entry says {count}"
            )));
        }
        let layers: u64 = bytes[count_at + 4..prelude as usize]
            .chunks_exact(4)
            .map(|s| u64::from(u32::from_le_bytes([s[0], s[1], s[2], s[3]])))
            .sum();
        if prelude + layers > len {
            return Err(bad(format!(
                "its layers take {layers} bytes but its chunk has {}",
                len - prelude
            )));
        }
        let decoded_len = count * record_len;
        if decoded_len > MIN_DECODED_BOUND.max(len.saturating_mul(MAX_DECODED_PER_BYTE)) {
            return Err(bad(format!(
                "{count} points cannot be held in a chunk of {len} bytes"
            )));
        }

        let mut records = vec![0u8; decoded_len as usize];
        let decoded = contain_panics(&self.path, || {
            let mut decompressor = LayeredPointRecordDecompressor::new(Cursor::new(bytes));
            Ok(decompressor
                .set_fields_from(&self.laz_items)
                .map_err(|e| e.to_string())
                .and_then(|()| {
                    decompressor
                        .decompress_many(&mut records)
                        .map_err(|e| e.to_string())
                }))
        })?;
        decoded.map_err(|error| bad(format!("its LAZ chunk does not decode: {error}")))?;
        // A point stands for itself at least, whatever a damaged attribute says.
        let weights = match self.weight_at {
            Some(at) => records
                .chunks_exact(record_len as usize)
                .map(|r| {
                    let at = usize::from(at);
                    let w = u32::from_le_bytes([r[at], r[at + 1], r[at + 2], r[at + 3]]);
                    encode_weight(w.max(1))
                })
                .collect(),
            None => Vec::new(),
        };
        let points = las::PointDataBuilder::new()
            .with_format(self.format)
            .with_transforms(self.transforms)
            .build_from_bytes(records)
            .map_err(|error| bad(error.to_string()))?;
        let (cube_min, step) = node_frame(cube, info);
        let max = (1i64 << POSITION_BITS) - 1;
        let mut quantised = Vec::with_capacity(points.len());
        for ((x, y), z) in points.x().zip(points.y()).zip(points.z()) {
            let p = DVec3::new(x, y, z);
            let q = ((p - cube_min) / step).floor();
            let cell = q.to_array().map(|v| v as i64);
            if !q.is_finite() || cell.iter().any(|&c| !(0..=max).contains(&c)) {
                return Err(bad(format!(
                    "point {p} lies far outside the node's cube {}..{}",
                    cube.node_min(info.key),
                    cube.node_min(info.key) + DVec3::splat(cube.side_at(info.key.level))
                )));
            }
            quantised.push(cell.map(|c| c as u32));
        }
        Ok(NodePoints {
            key: info.key,
            cube_min,
            step,
            quantised,
            rgb: points
                .rgb()
                .map(|rgb| rgb.map(|(r, g, b)| [r, g, b]).collect()),
            intensity: points.intensity().collect(),
            classification: points.classification().collect(),
            return_number: points.return_number().collect(),
            // A foreign COPC file says nothing of what its points stand for: each counts once.
            weights,
            detail: Detail::Full,
        })
    }
}

/// A COPC file's node records: its LAZ chunks.
pub struct CopcNodes {
    bytes: Arc<CopcBytes>,
    decoder: CopcDecoder,
}

impl CopcNodes {
    pub(crate) fn new(bytes: Arc<CopcBytes>, header: &CopcHeader) -> Self {
        let decoder = CopcDecoder::of_header(bytes.name(), header);
        Self { bytes, decoder }
    }

    /// The file's path, or the URL it was opened by.
    pub fn path(&self) -> &Path {
        &self.decoder.path
    }

    /// How its chunks decode, for a reader elsewhere that is sent them.
    pub fn decoder(&self) -> &CopcDecoder {
        &self.decoder
    }
}

/// Where a COPC node's points are quantised: its cube widened by half its side on every
/// face, because writers place a point on a cell's face in either neighbour. 30 bits over
/// twice the side keep a step far below any file's scale.
fn node_frame(cube: &RootCube, info: &NodeInfo) -> (DVec3, f64) {
    let side = cube.side_at(info.key.level);
    let min = cube.node_min(info.key) - DVec3::splat(side / 2.0);
    (min, 2.0 * side / f64::from(1u32 << POSITION_BITS))
}

impl NodeRecords for CopcNodes {
    /// A wave's chunks in one read, so that an object's near chunks are fetched together;
    /// the hierarchy checked each range against the file's size when it was read.
    fn read_records(&self, nodes: &[NodeInfo]) -> Result<Vec<Vec<u8>>, LodError> {
        let ranges: Vec<Range<u64>> = nodes
            .iter()
            .map(|node| node.offset..node.offset + u64::from(node.byte_len))
            .collect();
        self.bytes.read_many(&ranges).map_err(LodError::from)
    }

    fn decode(
        &self,
        cube: &RootCube,
        info: &NodeInfo,
        bytes: &[u8],
    ) -> Result<NodePoints, LodError> {
        self.decoder
            .decode_chunk(cube, info, bytes)
            .map_err(LodError::from)
    }
}

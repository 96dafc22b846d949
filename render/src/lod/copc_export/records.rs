//! A node's points as LAS 1.4 point records: PDRF 6 (30 bytes), or 7 (36 bytes) with RGB,
//! and each point's weight after them as an extra bytes attribute (4 bytes,
//! [`WEIGHT_ATTRIBUTE`]), in the store's order.
//!
//! The weight is how many original points the point stands for where its node is drawn
//! without the child below it (`lod/weights.rs`), so that high quality on a cut of the file
//! averages what full detail would; other readers ignore it. A node without weights (one
//! read from a COPC file without them) writes 1.
//!
//! The order matters for size, not for COPC. The store keeps a node's points in the order its
//! build met them, which keeps runs of the files' scan order; LAZ predicts each point from
//! the one before, and on the real scans that order compresses better than a Morton order of
//! the node's points (autzen: 1.40x the plain LAZ against 1.48x).
//!
//! A store that keeps its points' attributes sections (`lod/attributes.rs`) gives every
//! field back: the PDRF 6 fields from byte 14 on are the rows' first 16 bytes as they are;
//! RGB from the record; near-infrared (PDRF 8, where every file had it) from the rows; the
//! files' wave packets as seven extra bytes attributes named as laspy names LAS's own
//! (`wavepacket_index`, `wavepacket_offset`, `wavepacket_size`,
//! `return_point_wave_location`, `x_t`, `y_t`, `z_t`), since COPC has no waveform formats;
//! the files' extra bytes after them, with their own descriptors. The weight comes first,
//! so readers find it whatever the files' descriptors are.
//!
//! A store without attributes sections (generated points, an older build) keeps position,
//! RGB, intensity, classification and return number; the other fields are written as LAS's
//! "unknown": number of returns equal to the return number (LAS wants it no smaller), scan
//! angle, user data, point source and GPS time 0.

use glam::DVec3;

use super::transform::ExportTransform;
use crate::lod::attributes::{AttributeSchema, BASE_BYTES, NIR_BYTES, WAVE_BYTES};
use crate::lod::weights::{decode_weight, WEIGHT_ATTRIBUTE};
use crate::lod::NodePoints;

/// Bytes of a PDRF 6 record.
pub const PDRF6_BYTES: usize = 30;
/// Bytes of a PDRF 7 record (PDRF 6 and three 16-bit color channels).
pub const PDRF7_BYTES: usize = 36;
/// Bytes of a PDRF 8 record (PDRF 7 and near-infrared).
pub const PDRF8_BYTES: usize = 38;
/// Bytes of the weight after a record's fields.
pub const WEIGHT_BYTES: usize = 4;
/// What the extra bytes VLR says of the weight.
pub const WEIGHT_DESCRIPTION: &str = "original points it stands for";

/// The point data record format of an export with or without color, without
/// near-infrared.
pub fn point_format(has_rgb: bool) -> u8 {
    if has_rgb {
        7
    } else {
        6
    }
}

/// The wave packet's fields as extra bytes: name and data type (1 u8, 5 u32, 7 u64, 9 f32).
const WAVE_FIELDS: [(&str, u8); 7] = [
    ("wavepacket_index", 1),
    ("wavepacket_offset", 7),
    ("wavepacket_size", 5),
    ("return_point_wave_location", 9),
    ("x_t", 9),
    ("y_t", 9),
    ("z_t", 9),
];

/// What an export's records hold: the point format and the extra bytes after its fields.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordFormat {
    pub has_rgb: bool,
    /// The store's attributes, where it keeps them.
    pub attributes: Option<AttributeSchema>,
}

impl RecordFormat {
    pub fn new(has_rgb: bool, attributes: Option<&AttributeSchema>) -> Self {
        Self {
            has_rgb,
            attributes: attributes.cloned(),
        }
    }

    fn has_nir(&self) -> bool {
        self.has_rgb && self.attributes.as_ref().is_some_and(|a| a.has_nir)
    }

    fn has_waveform(&self) -> bool {
        self.attributes.as_ref().is_some_and(|a| a.has_waveform)
    }

    /// PDRF 6, 7 with RGB, 8 with RGB and near-infrared.
    pub fn point_format(&self) -> u8 {
        match (self.has_rgb, self.has_nir()) {
            (true, true) => 8,
            (has_rgb, _) => point_format(has_rgb),
        }
    }

    /// Bytes of the point format's fields.
    pub fn fields_len(&self) -> usize {
        match self.point_format() {
            8 => PDRF8_BYTES,
            7 => PDRF7_BYTES,
            _ => PDRF6_BYTES,
        }
    }

    /// Bytes after the fields: the weight, the wave packet, the files' extra bytes.
    pub fn extra_len(&self) -> usize {
        WEIGHT_BYTES
            + if self.has_waveform() { WAVE_BYTES } else { 0 }
            + self
                .attributes
                .as_ref()
                .map_or(0, |a| usize::from(a.extra_bytes))
    }

    /// Bytes of a record.
    pub fn record_len(&self) -> usize {
        self.fields_len() + self.extra_len()
    }

    /// The extra bytes VLR's data: the weight's descriptor, the wave packet's, the files'.
    pub fn extra_bytes_vlr(&self) -> Vec<u8> {
        let mut out = crate::extra_bytes::descriptor(
            WEIGHT_ATTRIBUTE,
            crate::extra_bytes::DATA_TYPE_U32,
            WEIGHT_DESCRIPTION,
        )
        .to_vec();
        if self.has_waveform() {
            for (name, data_type) in WAVE_FIELDS {
                out.extend(crate::extra_bytes::descriptor(
                    name,
                    data_type,
                    "the source's wave packet descriptor",
                ));
            }
        }
        if let Some(a) = &self.attributes {
            let ours: Vec<&str> = std::iter::once(WEIGHT_ATTRIBUTE)
                .chain(
                    self.has_waveform()
                        .then_some(WAVE_FIELDS.map(|(name, _)| name))
                        .into_iter()
                        .flatten(),
                )
                .collect();
            for d in a
                .extra_descriptors
                .chunks_exact(crate::extra_bytes::DESCRIPTOR_BYTES)
            {
                out.extend_from_slice(&renamed_apart(d, &ours));
            }
        }
        out
    }
}

/// A file's descriptor `d`, its name prefixed with `source_` where it is one of the
/// export's own (`ours`: a file that is itself an export), so that no two attributes share
/// a name.
fn renamed_apart(d: &[u8], ours: &[&str]) -> Vec<u8> {
    let mut d = d.to_vec();
    let name = &d[4..36];
    let end = name.iter().position(|&b| b == 0).unwrap_or(name.len());
    let text = String::from_utf8_lossy(&name[..end]).trim().to_owned();
    if ours.contains(&text.as_str()) {
        let renamed = format!("source_{text}");
        let n = renamed.len().min(32);
        d[4..36].fill(0);
        d[4..4 + n].copy_from_slice(&renamed.as_bytes()[..n]);
    }
    d
}

/// A node's records and what the header needs of them.
pub struct NodeRecordBytes {
    pub bytes: Vec<u8>,
    pub count: u64,
    /// Lowest and highest written position (after rounding to the scale).
    pub min: DVec3,
    pub max: DVec3,
    /// Points by return number 1 to 15 (index 0 is return 1).
    pub by_return: [u64; 15],
    /// Lowest and highest GPS time, where the records hold it.
    pub gps_range: Option<[f64; 2]>,
}

/// The records of `node`'s points under `transform`, in `format` (a node without stored
/// color is written black); `rows` are the node's attribute rows where the store keeps them.
pub fn node_records(
    node: &NodePoints,
    rows: Option<&[u8]>,
    transform: &ExportTransform,
    format: &RecordFormat,
) -> NodeRecordBytes {
    let n = node.len();
    let len = format.record_len();
    let weight_at = format.fields_len();
    let schema = format.attributes.as_ref().filter(|_| rows.is_some());
    let row_bytes = schema.map_or(0, AttributeSchema::row_bytes);
    let mut bytes = vec![0u8; n * len];
    let mut low = [i32::MAX; 3];
    let mut high = [i32::MIN; 3];
    let mut by_return = [0u64; 15];
    let mut gps_range: Option<[f64; 2]> = None;
    for (i, (record, q)) in bytes.chunks_exact_mut(len).zip(&node.quantised).enumerate() {
        let world = node.cube_min + (DVec3::from(q.map(f64::from)) + 0.5) * node.step;
        let xyz = transform.to_integer(world);
        for axis in 0..3 {
            low[axis] = low[axis].min(xyz[axis]);
            high[axis] = high[axis].max(xyz[axis]);
            record[axis * 4..axis * 4 + 4].copy_from_slice(&xyz[axis].to_le_bytes());
        }
        record[12..14].copy_from_slice(&node.intensity[i].to_le_bytes());
        let row = rows.map(|rows| &rows[i * row_bytes..(i + 1) * row_bytes]);
        let returns = match (row, schema) {
            (Some(row), Some(schema)) => {
                record[14..14 + BASE_BYTES].copy_from_slice(&row[..BASE_BYTES]);
                let gps = f64::from_le_bytes(row[8..16].try_into().expect("8 bytes"));
                gps_range = Some(match gps_range {
                    Some([lo, hi]) => [lo.min(gps), hi.max(gps)],
                    None => [gps, gps],
                });
                if let (Some(from), 8) = (schema.nir_at(), format.point_format()) {
                    record[36..36 + NIR_BYTES].copy_from_slice(&row[from..from + NIR_BYTES]);
                }
                let mut at = weight_at + WEIGHT_BYTES;
                if let Some(from) = schema.wave_at() {
                    record[at..at + WAVE_BYTES].copy_from_slice(&row[from..from + WAVE_BYTES]);
                    at += WAVE_BYTES;
                }
                let extra = &row[schema.extra_at()..];
                record[at..at + extra.len()].copy_from_slice(extra);
                row[0] & 15
            }
            _ => {
                let returns = node.return_number[i] & 15;
                record[14] = returns | (returns << 4);
                record[16] = node.classification[i];
                returns
            }
        };
        if (1..=15).contains(&returns) {
            by_return[usize::from(returns) - 1] += 1;
        }
        if format.has_rgb {
            let rgb = node.rgb.as_ref().map_or([0; 3], |c| c[i]);
            for (c, value) in rgb.iter().enumerate() {
                record[30 + 2 * c..32 + 2 * c].copy_from_slice(&value.to_le_bytes());
            }
        }
        let weight = node.weights.get(i).map_or(1, |&code| decode_weight(code));
        record[weight_at..weight_at + WEIGHT_BYTES].copy_from_slice(&weight.to_le_bytes());
    }
    NodeRecordBytes {
        bytes,
        count: n as u64,
        min: transform.to_world(low),
        max: transform.to_world(high),
        by_return,
        gps_range,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A file that is itself an export keeps its weight, renamed apart from the new one's.
    #[test]
    fn a_sources_attribute_named_as_the_exports_own_is_renamed_apart() {
        let weight = crate::extra_bytes::descriptor(WEIGHT_ATTRIBUTE, 5, "");
        let amplitude = crate::extra_bytes::descriptor("amplitude", 3, "");
        let schema = AttributeSchema {
            extra_descriptors: [weight, amplitude].concat(),
            extra_bytes: 6,
            has_waveform: true,
            ..AttributeSchema::default()
        };
        let format = RecordFormat::new(true, Some(&schema));
        assert_eq!(format.point_format(), 7);
        assert_eq!(format.record_len(), PDRF7_BYTES + 4 + WAVE_BYTES + 6);
        let names: Vec<String> = crate::extra_bytes::parse(&format.extra_bytes_vlr())
            .into_iter()
            .map(|d| d.name)
            .collect();
        assert_eq!(names[0], WEIGHT_ATTRIBUTE);
        assert_eq!(names[1..8], WAVE_FIELDS.map(|(name, _)| name.to_string()));
        assert_eq!(names[8..], ["source_pointfarm_weight", "amplitude"]);
    }
}

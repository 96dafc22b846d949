//! Every attribute of a point beyond what frames draw, kept so that an export gives back what
//! the files held: its attributes section, stored apart from the record a frame reads.
//!
//! A point's row is the bytes 14 to 29 of a LAS 1.4 PDRF 6 record, then what the dataset's
//! files have beyond it, each in its LAS layout ([`AttributeSchema`]):
//!
//! ```text
//! returns u8 (return number, number of returns << 4) | flags u8 (classification flags:
//! synthetic, key-point, withheld, overlap; scanner channel << 4; scan direction << 6; edge
//! of flight line << 7) | classification u8 | user data u8 | scan angle i16 (0.006°) |
//! point source id u16 | GPS time f64
//! [NIR u16] [wave packet: index u8, offset u64, size u32, location f32, x(t), y(t), z(t) f32]
//! [the files' extra bytes]
//! ```
//!
//! A point of a legacy format (0 to 5) is mapped losslessly: its 3-bit return fields widen, its
//! three classification flags move to the flags byte (overlap 0, scanner channel 0), its scan
//! angle rank (whole degrees, i8) becomes `round(rank / 0.006)`, which gives the rank back as
//! `round(angle * 0.006)`; a format without GPS time writes 0.
//!
//! A node's section, little-endian: "PFA1" | count u32 | row bytes u32 | rows | checksum u64
//! of the key and everything before it.

use super::checksum::checksum64;
use super::error::LodError;
use super::key::NodeKey;
use super::point::RawPoint;

/// Bytes of the part of a row every dataset has.
pub const BASE_BYTES: usize = 16;
/// Bytes of a near-infrared value.
pub const NIR_BYTES: usize = 2;
/// Bytes of a wave packet descriptor (LAS formats 4, 5, 9, 10).
pub const WAVE_BYTES: usize = 29;
/// Bytes of one extra bytes descriptor.
pub const DESCRIPTOR_BYTES: usize = 192;
/// The most bytes of extra bytes a LAS record may carry.
const MAX_EXTRA_BYTES: usize = u16::MAX as usize;

const MAGIC: &[u8; 4] = b"PFA1";
const HEADER_BYTES: usize = 12;

/// What a dataset's rows hold beyond the base: one schema for all of a dataset's files.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct AttributeSchema {
    /// Every file has near-infrared (formats 8 and 10).
    pub has_nir: bool,
    /// Some file has wave packets (formats 4, 5, 9, 10); the others' points write zeros.
    pub has_waveform: bool,
    /// The extra bytes descriptors every file shares, 192 bytes each, in record order.
    pub extra_descriptors: Vec<u8>,
    /// Bytes of extra bytes a point: the descriptors' sizes summed.
    pub extra_bytes: u16,
    /// Bit `f` set when some file has point format `f`.
    pub source_formats: u16,
    /// The files declare extra bytes unlike each other's, which the store does not keep.
    pub extra_bytes_dropped: bool,
}

impl AttributeSchema {
    /// Bytes of a row.
    pub fn row_bytes(&self) -> usize {
        self.extra_at() + usize::from(self.extra_bytes)
    }

    /// Where a row's near-infrared lies, when it has it.
    pub fn nir_at(&self) -> Option<usize> {
        self.has_nir.then_some(BASE_BYTES)
    }

    /// Where a row's wave packet lies, when it has one.
    pub fn wave_at(&self) -> Option<usize> {
        self.has_waveform
            .then_some(BASE_BYTES + if self.has_nir { NIR_BYTES } else { 0 })
    }

    /// Where a row's extra bytes start.
    pub fn extra_at(&self) -> usize {
        BASE_BYTES
            + if self.has_nir { NIR_BYTES } else { 0 }
            + if self.has_waveform { WAVE_BYTES } else { 0 }
    }

    /// The schema's bytes in the hierarchy record.
    pub fn encode(&self, out: &mut Vec<u8>) {
        let flags = u8::from(self.has_nir)
            | u8::from(self.has_waveform) << 1
            | u8::from(self.extra_bytes_dropped) << 2;
        out.push(flags);
        out.extend_from_slice(&self.source_formats.to_le_bytes());
        out.extend_from_slice(&self.extra_bytes.to_le_bytes());
        out.extend_from_slice(&(self.extra_descriptors.len() as u32).to_le_bytes());
        out.extend_from_slice(&self.extra_descriptors);
    }

    /// A schema read back from `bytes` at `*at`, every length checked against them first.
    pub fn decode(bytes: &[u8], at: &mut usize) -> Result<Self, String> {
        let mut take = |n: usize| -> Result<&[u8], String> {
            let end = at
                .checked_add(n)
                .filter(|&end| end <= bytes.len())
                .ok_or("its attribute schema is cut short")?;
            let slice = &bytes[*at..end];
            *at = end;
            Ok(slice)
        };
        let flags = take(1)?[0];
        if flags & !0b111 != 0 {
            return Err(format!("its attribute schema has unknown flags {flags:#x}"));
        }
        let formats = take(2)?;
        let source_formats = u16::from_le_bytes([formats[0], formats[1]]);
        let extra = take(2)?;
        let extra_bytes = u16::from_le_bytes([extra[0], extra[1]]);
        let len = take(4)?;
        let len = u32::from_le_bytes([len[0], len[1], len[2], len[3]]) as usize;
        if !len.is_multiple_of(DESCRIPTOR_BYTES) {
            return Err(format!(
                "its extra bytes descriptors take {len} bytes, not whole descriptors"
            ));
        }
        let extra_descriptors = take(len)?.to_vec();
        let schema = Self {
            has_nir: flags & 1 != 0,
            has_waveform: flags & 2 != 0,
            extra_descriptors,
            extra_bytes,
            source_formats,
            extra_bytes_dropped: flags & 4 != 0,
        };
        let declared = declared_bytes(&schema.extra_descriptors);
        if declared != Some(usize::from(extra_bytes)) {
            return Err(format!(
                "its extra bytes descriptors declare {declared:?} bytes, the schema {extra_bytes}"
            ));
        }
        Ok(schema)
    }
}

/// The bytes the descriptors `data` declare, `None` when one has a size LAS does not define.
pub fn declared_bytes(data: &[u8]) -> Option<usize> {
    crate::extra_bytes::parse(data)
        .iter()
        .try_fold(0usize, |sum, d| sum.checked_add(d.bytes()?))
}

/// The descriptors of extra bytes a file's records carry: those its extra bytes VLR `vlr`
/// declares when their sizes add up to the `extra` bytes, else (no VLR, or one that does
/// not describe them) the bytes as undocumented attributes of at most 255 bytes each, named
/// `undocumented_N`, so that they are carried all the same.
pub fn extra_descriptors(vlr: Option<&[u8]>, extra: usize) -> Vec<u8> {
    if let Some(data) = vlr {
        let whole = &data[..data.len() / DESCRIPTOR_BYTES * DESCRIPTOR_BYTES];
        if declared_bytes(whole) == Some(extra) {
            return whole.to_vec();
        }
    }
    let mut out = Vec::new();
    let mut left = extra.min(MAX_EXTRA_BYTES);
    let mut n = 0;
    while left > 0 {
        let size = left.min(255);
        let mut d = crate::extra_bytes::descriptor(
            &format!("undocumented_{n}"),
            0,
            "bytes a source file did not describe",
        );
        d[3] = size as u8;
        out.extend_from_slice(&d);
        left -= size;
        n += 1;
    }
    out
}

/// How the fields of one file's records become rows of a schema.
#[derive(Debug, Clone, Copy)]
pub struct RowFiller {
    extended: bool,
    gps_at: Option<usize>,
    nir_at: Option<usize>,
    wave_at: Option<usize>,
    /// Where the record's extra bytes start, when the schema keeps them.
    extra_at: Option<usize>,
    row_nir: Option<usize>,
    row_wave: Option<usize>,
    row_extra: usize,
    extra_bytes: usize,
    row_bytes: usize,
    /// Whether a row holds a section the record does not fill, zeroed first: a row is
    /// otherwise written whole, and zeroing it would cost a pass a point.
    zero_tail: bool,
}

/// [`legacy_scan_angle`] of every rank, by the rank's byte: a division and a rounding a
/// point otherwise.
static LEGACY_SCAN_ANGLES: std::sync::LazyLock<[i16; 256]> =
    std::sync::LazyLock::new(|| std::array::from_fn(|byte| legacy_scan_angle(byte as u8 as i8)));

impl RowFiller {
    /// The filler of records of `point_format` (0 to 10) whose fields take `format_len` bytes,
    /// their extra bytes kept when `keep_extra` (the file's extra bytes are the schema's).
    pub fn new(
        point_format: u8,
        format_len: usize,
        keep_extra: bool,
        schema: &AttributeSchema,
    ) -> Self {
        let extended = point_format >= 6;
        let gps_at = match point_format {
            1 | 3 | 4 | 5 => Some(20),
            6..=10 => Some(22),
            _ => None,
        };
        let nir_at = matches!(point_format, 8 | 10).then_some(36);
        let wave_at = match point_format {
            4 => Some(28),
            5 => Some(34),
            9 => Some(30),
            10 => Some(38),
            _ => None,
        };
        let extra_at = keep_extra.then_some(format_len);
        let extra_bytes = usize::from(schema.extra_bytes);
        let zero_tail = (schema.nir_at().is_some() && nir_at.is_none())
            || (schema.wave_at().is_some() && wave_at.is_none())
            || (extra_bytes > 0 && extra_at.is_none());
        Self {
            extended,
            gps_at,
            nir_at,
            wave_at,
            extra_at,
            row_nir: schema.nir_at(),
            row_wave: schema.wave_at(),
            row_extra: schema.extra_at(),
            extra_bytes,
            row_bytes: schema.row_bytes(),
            zero_tail,
        }
    }

    /// Bytes of a row.
    pub fn row_bytes(&self) -> usize {
        self.row_bytes
    }

    /// Writes the row of `record` (one whole record of the file) into `row`, which is
    /// [`Self::row_bytes`] long and zero where the file has nothing to write.
    pub fn fill(&self, record: &[u8], row: &mut [u8]) {
        if self.zero_tail {
            row[BASE_BYTES..].fill(0);
        }
        if self.extended {
            row[..BASE_BYTES - 8].copy_from_slice(&record[14..22]);
        } else {
            let (returns, class) = (record[14], record[15]);
            row[0] = (returns & 7) | ((returns >> 3) & 7) << 4;
            row[1] = (class >> 5) | (returns & 0b1100_0000);
            row[2] = class & 0b0001_1111;
            row[3] = record[17];
            let angle = LEGACY_SCAN_ANGLES[usize::from(record[16])];
            row[4..6].copy_from_slice(&angle.to_le_bytes());
            row[6..8].copy_from_slice(&record[18..20]);
        }
        match self.gps_at {
            Some(at) => row[8..16].copy_from_slice(&record[at..at + 8]),
            None => row[8..16].fill(0),
        }
        if let (Some(to), Some(from)) = (self.row_nir, self.nir_at) {
            row[to..to + NIR_BYTES].copy_from_slice(&record[from..from + NIR_BYTES]);
        }
        if let (Some(to), Some(from)) = (self.row_wave, self.wave_at) {
            row[to..to + WAVE_BYTES].copy_from_slice(&record[from..from + WAVE_BYTES]);
        }
        if let Some(from) = self.extra_at {
            let n = self.extra_bytes;
            row[self.row_extra..self.row_extra + n].copy_from_slice(&record[from..from + n]);
        }
    }
}

/// A legacy scan angle rank (whole degrees) in the extended format's units of 0.006°.
pub fn legacy_scan_angle(rank: i8) -> i16 {
    (f64::from(rank) / 0.006).round() as i16
}

/// Rows of points being built, `row_bytes` each; a [`RawPoint`]'s `row` indexes them.
#[derive(Debug, Default)]
pub struct AttributeRows {
    row_bytes: usize,
    bytes: Vec<u8>,
}

impl AttributeRows {
    pub fn new(row_bytes: usize) -> Self {
        Self::in_buffer(row_bytes, Vec::new())
    }

    /// No rows, held in `bytes` (emptied), whose room is reused.
    pub fn in_buffer(row_bytes: usize, mut bytes: Vec<u8>) -> Self {
        bytes.clear();
        Self { row_bytes, bytes }
    }

    /// The buffer the rows were held in, for another set of rows to reuse.
    pub fn into_buffer(self) -> Vec<u8> {
        self.bytes
    }

    /// Room for `rows` more rows.
    pub fn reserve(&mut self, rows: usize) {
        self.bytes.reserve(rows * self.row_bytes);
    }

    pub fn row_bytes(&self) -> usize {
        self.row_bytes
    }

    /// Rows held.
    pub fn len(&self) -> usize {
        self.bytes.len().checked_div(self.row_bytes).unwrap_or(0)
    }

    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }

    /// Appends a row and returns its index.
    pub fn push(&mut self, row: &[u8]) -> u32 {
        debug_assert_eq!(row.len(), self.row_bytes);
        let index = self.len() as u32;
        self.bytes.extend_from_slice(row);
        index
    }

    /// The row of `p`; empty where rows are.
    pub fn of(&self, p: &RawPoint) -> &[u8] {
        let at = p.row as usize * self.row_bytes;
        &self.bytes[at..at + self.row_bytes]
    }
}

/// The attributes section of `key`'s `points`, their rows in the points' order; empty where
/// the rows are.
pub fn encode_section(key: NodeKey, points: &[RawPoint], rows: &AttributeRows) -> Vec<u8> {
    if rows.row_bytes() == 0 || points.is_empty() {
        return Vec::new();
    }
    let mut out = Vec::with_capacity(HEADER_BYTES + points.len() * rows.row_bytes() + 8);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(points.len() as u32).to_le_bytes());
    out.extend_from_slice(&(rows.row_bytes() as u32).to_le_bytes());
    for p in points {
        out.extend_from_slice(rows.of(p));
    }
    let sum = checksum64(&key.to_bytes(), &out);
    out.extend_from_slice(&sum.to_le_bytes());
    out
}

/// The rows of `key`'s attributes section `bytes`, checked: its layout, its checksum, that it
/// holds `expected` points of `row_bytes` each. `file` names where the bytes were read.
pub fn decode_section<'a>(
    key: NodeKey,
    expected: u32,
    row_bytes: usize,
    bytes: &'a [u8],
    file: &std::path::Path,
) -> Result<&'a [u8], LodError> {
    let corrupt = |reason: String| LodError::CorruptNode {
        key,
        reason: format!("its attributes section in {}: {reason}", file.display()),
    };
    if bytes.len() < HEADER_BYTES + 8 {
        return Err(corrupt(format!(
            "{} bytes is shorter than its header",
            bytes.len()
        )));
    }
    let (body, sum) = bytes.split_at(bytes.len() - 8);
    let stored = u64::from_le_bytes(sum.try_into().expect("8 bytes"));
    let computed = checksum64(&key.to_bytes(), body);
    if stored != computed {
        return Err(corrupt(format!(
            "checksum mismatch (stored {stored:016x}, computed {computed:016x})"
        )));
    }
    if &body[..4] != MAGIC {
        return Err(corrupt("not an attributes section".into()));
    }
    let count = u32::from_le_bytes([body[4], body[5], body[6], body[7]]);
    let width = u32::from_le_bytes([body[8], body[9], body[10], body[11]]) as usize;
    if count != expected || width != row_bytes {
        return Err(corrupt(format!(
            "{count} rows of {width} bytes, {expected} of {row_bytes} expected"
        )));
    }
    let rows = &body[HEADER_BYTES..];
    if Some(rows.len()) != (count as usize).checked_mul(width) {
        return Err(corrupt(format!(
            "{} bytes of rows for {count} rows of {width} bytes",
            rows.len()
        )));
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use glam::DVec3;

    use super::*;

    fn point(row: u32) -> RawPoint {
        RawPoint {
            position: DVec3::ZERO,
            rgb: [0; 3],
            intensity: 0,
            classification: 0,
            return_number: 1,
            weight: 1,
            row,
        }
    }

    fn rows(count: usize, width: usize) -> AttributeRows {
        let mut rows = AttributeRows::new(width);
        for i in 0..count {
            let row: Vec<u8> = (0..width).map(|b| (i * 31 + b) as u8).collect();
            rows.push(&row);
        }
        rows
    }

    #[test]
    fn sections_round_trip_in_the_points_order() {
        let key = NodeKey::new(2, glam::UVec3::new(1, 2, 3));
        let rows = rows(10, 21);
        let points: Vec<RawPoint> = [7, 2, 9].into_iter().map(point).collect();
        let bytes = encode_section(key, &points, &rows);
        let read = decode_section(key, 3, 21, &bytes, Path::new("p.bin")).expect("decodes");
        assert_eq!(&read[..21], rows.of(&points[0]));
        assert_eq!(&read[42..], rows.of(&points[2]));
        assert!(encode_section(key, &points, &AttributeRows::new(0)).is_empty());
    }

    /// Every damaged byte, a cut, a wrong count or width, or another key's section is an error
    /// naming the file, never a panic.
    #[test]
    fn damaged_sections_are_errors_naming_the_file() {
        let key = NodeKey::new(1, glam::UVec3::new(1, 0, 1));
        let rows = rows(4, 17);
        let points: Vec<RawPoint> = (0..4).map(point).collect();
        let bytes = encode_section(key, &points, &rows);
        let file = Path::new("/stores/x/payload.bin");
        let names_file = |result: Result<&[u8], LodError>| {
            let error = result.expect_err("refused");
            assert!(
                error.to_string().contains("/stores/x/payload.bin"),
                "{error}"
            );
            assert!(error.is_damage());
        };
        for at in 0..bytes.len() {
            let mut damaged = bytes.clone();
            damaged[at] ^= 0x40;
            names_file(decode_section(key, 4, 17, &damaged, file));
        }
        for len in 0..bytes.len() {
            names_file(decode_section(key, 4, 17, &bytes[..len], file));
        }
        names_file(decode_section(key, 5, 17, &bytes, file));
        names_file(decode_section(key, 4, 16, &bytes, file));
        names_file(decode_section(key.child(0), 4, 17, &bytes, file));
    }

    #[test]
    fn every_legacy_scan_angle_rank_comes_back() {
        for rank in i8::MIN..=i8::MAX {
            let angle = legacy_scan_angle(rank);
            assert_eq!((f64::from(angle) * 0.006).round() as i8, rank);
            assert_eq!(LEGACY_SCAN_ANGLES[usize::from(rank as u8)], angle);
        }
        assert_eq!(legacy_scan_angle(-90), -15_000);
    }

    #[test]
    fn legacy_fields_move_to_their_extended_places() {
        let schema = AttributeSchema::default();
        let filler = RowFiller::new(1, 28, false, &schema);
        let mut record = vec![0u8; 28];
        // Return 5 of 7, scan direction and edge set; class 17, synthetic and withheld.
        record[14] = 5 | 7 << 3 | 1 << 6 | 1 << 7;
        record[15] = 17 | 1 << 5 | 1 << 7;
        record[16] = (-12i8) as u8;
        record[17] = 200;
        record[18..20].copy_from_slice(&4321u16.to_le_bytes());
        record[20..28].copy_from_slice(&123.5f64.to_le_bytes());
        let mut row = vec![0u8; filler.row_bytes()];
        filler.fill(&record, &mut row);
        assert_eq!(row[0], 5 | 7 << 4);
        assert_eq!(row[1], 0b101 | 1 << 6 | 1 << 7);
        assert_eq!((row[2], row[3]), (17, 200));
        assert_eq!(i16::from_le_bytes([row[4], row[5]]), -2000);
        assert_eq!(u16::from_le_bytes([row[6], row[7]]), 4321);
        assert_eq!(f64::from_le_bytes(row[8..16].try_into().expect("8")), 123.5);

        // A row reused from another point: the sections this format lacks come back zero.
        let wider = AttributeSchema {
            has_nir: true,
            has_waveform: true,
            ..AttributeSchema::default()
        };
        let filler = RowFiller::new(1, 28, false, &wider);
        let mut row = vec![0xa5u8; filler.row_bytes()];
        filler.fill(&record, &mut row);
        assert_eq!(row[0], 5 | 7 << 4);
        assert!(row[BASE_BYTES..].iter().all(|&b| b == 0), "{row:?}");
    }

    #[test]
    fn schemas_round_trip_and_damaged_ones_are_refused() {
        let descriptors = extra_descriptors(None, 300);
        assert_eq!(descriptors.len(), 2 * DESCRIPTOR_BYTES);
        let schema = AttributeSchema {
            has_nir: true,
            has_waveform: true,
            extra_descriptors: descriptors,
            extra_bytes: 300,
            source_formats: 1 << 10,
            extra_bytes_dropped: false,
        };
        assert_eq!(schema.row_bytes(), 16 + 2 + 29 + 300);
        let mut bytes = Vec::new();
        schema.encode(&mut bytes);
        let mut at = 0;
        assert_eq!(AttributeSchema::decode(&bytes, &mut at), Ok(schema.clone()));
        assert_eq!(at, bytes.len());
        for len in 0..bytes.len() {
            assert!(AttributeSchema::decode(&bytes[..len], &mut 0).is_err());
        }
        let mut wrong = bytes.clone();
        wrong[3] ^= 1;
        assert!(
            AttributeSchema::decode(&wrong, &mut 0).is_err(),
            "extra bytes"
        );
    }
}

//! Where the fields the mutations aim at lie in a well-formed source file: header fields,
//! each VLR, the LASzip VLR, the chunk table and the EVLRs. Only ever run on the generator's
//! own sources, which are known to be valid, so it trusts what it reads.

use crate::CorpusError;

/// Byte offsets of the public header block's fields (LAS 1.0–1.4).
pub mod header {
    pub const VERSION_MAJOR: usize = 24;
    pub const VERSION_MINOR: usize = 25;
    pub const HEADER_SIZE: usize = 94;
    pub const OFFSET_TO_POINT_DATA: usize = 96;
    pub const VLR_COUNT: usize = 100;
    pub const POINT_FORMAT: usize = 104;
    pub const RECORD_LENGTH: usize = 105;
    pub const LEGACY_POINT_COUNT: usize = 107;
    pub const X_SCALE: usize = 131;
    pub const BOUNDS: usize = 179;
    pub const WAVEFORM_START: usize = 227;
    pub const FIRST_EVLR: usize = 235;
    pub const EVLR_COUNT: usize = 243;
    pub const POINT_COUNT_1_4: usize = 247;
}

/// A VLR header: user id at 2, record id at 18, length at 20; 54 bytes in all.
pub const VLR_HEADER_LEN: usize = 54;
/// An EVLR header: as a VLR's with an 8-byte length; 60 bytes in all.
pub const EVLR_HEADER_LEN: usize = 60;

/// One variable length record of a source: where its header starts and its data's length.
#[derive(Debug, Clone, Copy)]
pub struct Record {
    pub offset: usize,
    pub data_len: usize,
    pub is_laszip: bool,
}

impl Record {
    pub fn data_offset(&self) -> usize {
        self.offset + VLR_HEADER_LEN
    }
}

/// The layout of a source file.
#[derive(Debug, Clone)]
pub struct Layout {
    pub minor_version: u8,
    pub header_size: usize,
    pub data_start: usize,
    pub vlrs: Vec<Record>,
    /// LAZ: where the chunk table starts (its offset is the first 8 bytes of the data).
    pub chunk_table: Option<usize>,
    /// LAS 1.4: where the first EVLR starts, when there is one.
    pub first_evlr: Option<usize>,
}

fn u16_at(bytes: &[u8], at: usize) -> usize {
    usize::from(u16::from_le_bytes([bytes[at], bytes[at + 1]]))
}

fn u32_at(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

fn u64_at(bytes: &[u8], at: usize) -> u64 {
    let mut word = [0u8; 8];
    word.copy_from_slice(&bytes[at..at + 8]);
    u64::from_le_bytes(word)
}

impl Layout {
    pub fn of(name: &str, bytes: &[u8]) -> Result<Self, CorpusError> {
        if bytes.len() < 227 || &bytes[..4] != b"LASF" {
            return Err(CorpusError::Source(format!("{name}: not a LAS file")));
        }
        let minor_version = bytes[header::VERSION_MINOR];
        let header_size = u16_at(bytes, header::HEADER_SIZE);
        let data_start = u32_at(bytes, header::OFFSET_TO_POINT_DATA) as usize;
        let mut vlrs = Vec::new();
        let mut offset = header_size;
        for _ in 0..u32_at(bytes, header::VLR_COUNT) {
            let data_len = u16_at(bytes, offset + 20);
            let is_laszip = bytes[offset + 2..offset + 16] == *b"laszip encoded";
            vlrs.push(Record {
                offset,
                data_len,
                is_laszip,
            });
            offset += VLR_HEADER_LEN + data_len;
        }
        let compressed = bytes[header::POINT_FORMAT] & 0x80 != 0;
        let chunk_table = compressed.then(|| u64_at(bytes, data_start) as usize);
        let first_evlr = (minor_version >= 4)
            .then(|| u64_at(bytes, header::FIRST_EVLR) as usize)
            .filter(|&start| start > 0 && u32_at(bytes, header::EVLR_COUNT) > 0);
        Ok(Self {
            minor_version,
            header_size,
            data_start,
            vlrs,
            chunk_table,
            first_evlr,
        })
    }

    pub fn laszip(&self) -> Option<Record> {
        self.vlrs.iter().copied().find(|vlr| vlr.is_laszip)
    }
}

/// Appends one EVLR of `data` to a LAS 1.4 file and points the header at it.
pub fn append_evlr(bytes: &mut Vec<u8>, data: &[u8]) {
    let start = bytes.len() as u64;
    bytes[header::FIRST_EVLR..][..8].copy_from_slice(&start.to_le_bytes());
    bytes[header::EVLR_COUNT..][..4].copy_from_slice(&1u32.to_le_bytes());
    let mut record = vec![0u8; EVLR_HEADER_LEN];
    record[2..2 + 9].copy_from_slice(b"pointfarm");
    record[18..20].copy_from_slice(&1u16.to_le_bytes());
    record[20..28].copy_from_slice(&(data.len() as u64).to_le_bytes());
    record[28..28 + 12].copy_from_slice(b"corpus EVLR\0");
    bytes.extend_from_slice(&record);
    bytes.extend_from_slice(data);
}

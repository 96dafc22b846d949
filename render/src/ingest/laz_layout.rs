//! The LASzip VLR and the LAZ chunk table, checked before the `laz` crate decodes a file.
//!
//! The crate trusts both: it reserves 16 bytes per declared chunk before reading the table,
//! sizes its read buffer from the chunks' byte counts (decoded as signed 32-bit numbers, so
//! a flipped bit becomes an 18-exabyte count), its tail buffer from a chunk's point count
//! times the items' size, and asserts that a record is as long as the items it is made of.
//! In layered (LAS 1.4) chunks it allocates every layer's declared size. All of that is
//! checked here against the file's size, the header and the chunk's own byte count.

use std::io;

use laz::laszip::{ChunkTable, ChunkTableEntry};

use super::header::HeaderFacts;
use super::raw_file::{RawFile, RecordSpan};
use super::IngestError;

/// Fixed part of the LASzip VLR's data: compressor, coder, version, options, chunk size,
/// special EVLR count and offset, item count.
const LASZIP_FIXED_LEN: u64 = 34;
const LASZIP_ITEM_LEN: u64 = 6;
const CHUNK_SIZE_OFFSET: u64 = 12;
const ITEM_COUNT_OFFSET: u64 = 32;
/// The chunk size that marks variable-size chunks (the table then stores point counts).
const VARIABLE_CHUNK_SIZE: u32 = u32::MAX;
/// Larger fixed chunks than this must not exceed the declared point count: the decoder
/// allocates a whole chunk's points for the last one.
const MAX_CHUNK_POINTS_BEYOND_DECLARED: u64 = 1 << 20;

/// How a LAZ file's points are compressed, as far as reading them is concerned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum LazLayout {
    /// Pre-2011 LAZ without chunks: decoded sequentially.
    Unchunked,
    /// Chunked (point-wise or layered): decoded on all cores.
    Chunked,
}

/// One LASzip item: what it encodes, its size in the record and its coder version.
struct LazItem {
    kind: u16,
    size: u16,
    version: u16,
}

impl LazItem {
    /// The item's fixed size, or `None` for the byte items whose size is their own.
    fn fixed_size(&self) -> Option<Option<u16>> {
        match self.kind {
            0 | 14 => Some(None),
            6 => Some(Some(20)),
            7 => Some(Some(8)),
            8 | 11 => Some(Some(6)),
            9 | 13 => Some(Some(29)),
            10 => Some(Some(30)),
            12 => Some(Some(8)),
            _ => None,
        }
    }

    /// Whether the item is one of LAS 1.4's layered kinds.
    fn is_layered(&self) -> bool {
        self.kind >= 10
    }

    /// How many layer sizes a layered chunk stores for this item.
    fn layer_count(&self) -> u64 {
        layer_count(self.kind, self.size)
    }
}

/// How many layer sizes a layered chunk stores for an item of LASzip kind `kind` and `size`
/// bytes.
pub(crate) fn layer_count(kind: u16, size: u16) -> u64 {
    match kind {
        10 => 9,
        12 => 2,
        14 => u64::from(size),
        _ => 1,
    }
}

/// Checks the LASzip VLR and, for chunked files, the chunk table and every chunk's extent
/// (and, with `layers`, every layered chunk's layer table); gives the layout and the checked
/// table (empty for unchunked files), which previews read chunk starts from.
pub(super) fn check_laz(
    raw: &mut RawFile<'_>,
    facts: &HeaderFacts,
    laszip: Option<RecordSpan>,
    layers: bool,
) -> Result<(LazLayout, ChunkTable), IngestError> {
    let Some(vlr_span) = laszip else {
        return Err(raw.corrupt("compressed points but no LASzip VLR"));
    };
    if vlr_span.len < LASZIP_FIXED_LEN {
        return Err(raw.corrupt(format!(
            "LASzip VLR of {} bytes (at least {LASZIP_FIXED_LEN} expected)",
            vlr_span.len
        )));
    }
    let vlr_bytes = raw.vlr_at(vlr_span)?;
    let laszip = LaszipVlr {
        compressor: u16_in(&vlr_bytes, 0),
        chunk_size: match u32_in(&vlr_bytes, CHUNK_SIZE_OFFSET) {
            0 => VARIABLE_CHUNK_SIZE,
            size => size,
        },
        items: laz_items(raw, &vlr_bytes)?,
    };
    laszip.check_items(raw, facts)?;
    if laszip.compressor == 1 {
        return Ok((LazLayout::Unchunked, ChunkTable::default()));
    }
    let vlr = laz::LazVlr::from_buffer(&vlr_bytes)
        .map_err(|error| raw.corrupt(format!("the LASzip VLR cannot be parsed: {error}")))?;
    let chunks = check_chunk_table(raw, facts, &vlr)?;
    laszip.check_chunk_points(raw, facts, chunks.as_ref())?;
    if layers && laszip.items.iter().all(LazItem::is_layered) {
        check_layers(raw, facts, &laszip.items, chunks.as_ref())?;
    }
    Ok((LazLayout::Chunked, chunks))
}

fn u16_in(bytes: &[u8], offset: u64) -> u16 {
    let at = offset as usize;
    u16::from_le_bytes([bytes[at], bytes[at + 1]])
}

fn u32_in(bytes: &[u8], offset: u64) -> u32 {
    let at = offset as usize;
    u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

fn laz_items(raw: &RawFile<'_>, vlr: &[u8]) -> Result<Vec<LazItem>, IngestError> {
    let count = u64::from(u16_in(vlr, ITEM_COUNT_OFFSET));
    let needed = LASZIP_FIXED_LEN + count * LASZIP_ITEM_LEN;
    if (vlr.len() as u64) < needed {
        return Err(raw.corrupt(format!(
            "LASzip VLR of {} bytes cannot hold its {count} items ({needed} bytes)",
            vlr.len()
        )));
    }
    Ok((0..count)
        .map(|index| {
            let at = LASZIP_FIXED_LEN + index * LASZIP_ITEM_LEN;
            LazItem {
                kind: u16_in(vlr, at),
                size: u16_in(vlr, at + 2),
                version: u16_in(vlr, at + 4),
            }
        })
        .collect())
}

/// The parts of the LASzip VLR the checks read.
struct LaszipVlr {
    compressor: u16,
    /// Points per chunk, or [`VARIABLE_CHUNK_SIZE`].
    chunk_size: u32,
    items: Vec<LazItem>,
}

impl LaszipVlr {
    /// The items must be known, of their kind's size, of one family (point-wise or layered, as
    /// the compressor says) and together exactly one point record long.
    fn check_items(&self, raw: &RawFile<'_>, facts: &HeaderFacts) -> Result<(), IngestError> {
        let (compressor, items) = (self.compressor, &self.items);
        if !(1..=3).contains(&compressor) {
            return Err(raw.corrupt(format!("unknown LASzip compressor {compressor}")));
        }
        if items.is_empty() {
            return Err(raw.corrupt("the LASzip VLR lists no items"));
        }
        let layered = compressor == 3;
        for item in items {
            let Some(fixed_size) = item.fixed_size() else {
                return Err(raw.corrupt(format!("unknown LASzip item type {}", item.kind)));
            };
            if fixed_size.is_some_and(|size| size != item.size) || item.size == 0 {
                return Err(raw.corrupt(format!(
                    "LASzip item type {} of {} bytes",
                    item.kind, item.size
                )));
            }
            let known_versions = if layered { 3..=4 } else { 1..=2 };
            if item.is_layered() != layered || !known_versions.contains(&item.version) {
                return Err(raw.corrupt(format!(
                    "LASzip item type {} version {} does not fit compressor {compressor}",
                    item.kind, item.version
                )));
            }
        }
        // LASzip writes every item of a file with one coder version; data coded with another
        // decodes to garbage the coder's own assertions trip on.
        if let Some(odd) = items.iter().find(|item| item.version != items[0].version) {
            return Err(raw.corrupt(format!(
                "LASzip items of mixed coder versions ({} and {})",
                items[0].version, odd.version
            )));
        }
        let items_len: u64 = items.iter().map(|item| u64::from(item.size)).sum();
        if items_len != u64::from(facts.record_len) {
            return Err(raw.corrupt(format!(
                "LASzip items make {items_len}-byte records but the header says {}",
                facts.record_len
            )));
        }
        Ok(())
    }

    /// The chunks must hold the declared points, and no chunk may hold far more points than the
    /// file declares (the decoder allocates a whole chunk's records).
    fn check_chunk_points(
        &self,
        raw: &RawFile<'_>,
        facts: &HeaderFacts,
        chunks: &[ChunkTableEntry],
    ) -> Result<(), IngestError> {
        let chunk_size = self.chunk_size;
        let declared = facts.declared_points;
        let largest_allowed = declared.max(MAX_CHUNK_POINTS_BEYOND_DECLARED);
        let (largest, chunk_capacity) = if chunk_size == VARIABLE_CHUNK_SIZE {
            let largest = chunks.iter().map(|chunk| chunk.point_count).max();
            let total = chunks
                .iter()
                .fold(0u64, |sum, chunk| sum.saturating_add(chunk.point_count));
            (largest.unwrap_or(0), total)
        } else {
            let size = u64::from(chunk_size);
            (size, size.saturating_mul(chunks.len() as u64))
        };
        if largest > largest_allowed {
            return Err(raw.corrupt(format!(
                "a LAZ chunk of {largest} points in a file of {declared} points"
            )));
        }
        if declared > chunk_capacity {
            return Err(IngestError::TruncatedLaz {
                path: raw.path.to_owned(),
                declared,
                chunk_capacity,
            });
        }
        Ok(())
    }
}

/// Reads the chunk table after checking where it is and that its declared chunk count fits
/// the compressed data (every chunk starts with one raw point record); then that the chunks'
/// byte counts add up to no more than that data.
fn check_chunk_table(
    raw: &mut RawFile<'_>,
    facts: &HeaderFacts,
    vlr: &laz::LazVlr,
) -> Result<ChunkTable, IngestError> {
    let data_start = facts.offset_to_point_data;
    let table_offset = chunk_table_offset(raw, data_start)?;
    let table_missing = |raw: &RawFile<'_>, message: String| IngestError::LazChunkTable {
        path: raw.path.to_owned(),
        error: laz::LasZipError::IoError(io::Error::new(io::ErrorKind::UnexpectedEof, message)),
    };
    if table_offset.saturating_add(8) > raw.len {
        return Err(table_missing(
            raw,
            format!(
                "its offset {table_offset} lies beyond the end of the file ({} bytes)",
                raw.len
            ),
        ));
    }
    let chunk_count = u64::from(raw.u32_at(table_offset + 4, "the chunk count")?);
    let data_len = table_offset - (data_start + 8);
    let max_chunks = data_len / u64::from(facts.record_len);
    if chunk_count > max_chunks {
        return Err(raw.corrupt(format!(
            "the LAZ chunk table declares {chunk_count} chunks but the {data_len} bytes of compressed points hold at most {max_chunks}"
        )));
    }
    let path = raw.path;
    let file = raw.file_at(data_start)?;
    // The table's entries are compressed: garbage in them can panic the laz crate's decoder.
    let table = super::contain_panics(path, || {
        ChunkTable::read_from(file, vlr).map_err(|error| IngestError::LazChunkTable {
            path: path.to_owned(),
            error,
        })
    })?;
    let mut bytes = 0u64;
    for (index, chunk) in table.as_ref().iter().enumerate() {
        bytes = bytes.saturating_add(chunk.byte_count);
        if bytes > data_len {
            return Err(raw.corrupt(format!(
                "LAZ chunk {index} of {chunk_count} ends past the {data_len} bytes of compressed points"
            )));
        }
    }
    Ok(table)
}

/// The chunk table's offset: written before the points, or (by streaming writers that
/// could not seek back) in the file's last 8 bytes.
fn chunk_table_offset(raw: &mut RawFile<'_>, data_start: u64) -> Result<u64, IngestError> {
    let after_offset_field = data_start + 8;
    let at_start = raw.u64_at(data_start, "the LAZ chunk table offset")? as i64;
    if at_start >= after_offset_field as i64 {
        return Ok(at_start as u64);
    }
    let at_end = raw.u64_at(raw.len.saturating_sub(8), "the LAZ chunk table offset")? as i64;
    if at_end >= after_offset_field as i64 {
        return Ok(at_end as u64);
    }
    Err(IngestError::LazChunkTable {
        path: raw.path.to_owned(),
        error: laz::LasZipError::MissingChunkTable,
    })
}

/// A layered chunk starts with one raw record, its point count and every layer's byte size;
/// the layers must fit in the chunk's bytes.
fn check_layers(
    raw: &mut RawFile<'_>,
    facts: &HeaderFacts,
    items: &[LazItem],
    chunks: &[ChunkTableEntry],
) -> Result<(), IngestError> {
    let layer_count: u64 = items.iter().map(LazItem::layer_count).sum();
    let sizes_offset = u64::from(facts.record_len) + 4;
    let prelude = sizes_offset + 4 * layer_count;
    let mut chunk_start = facts.offset_to_point_data + 8;
    for (index, chunk) in chunks.iter().enumerate() {
        if chunk.byte_count < prelude {
            // Too short for its own layer table: only an empty last chunk may be.
            chunk_start += chunk.byte_count;
            continue;
        }
        let sizes = raw.vec_at(chunk_start + sizes_offset, 4 * layer_count, "layer sizes")?;
        let layers: u64 = sizes
            .chunks_exact(4)
            .map(|size| u64::from(u32::from_le_bytes([size[0], size[1], size[2], size[3]])))
            .sum();
        if prelude + layers > chunk.byte_count {
            return Err(raw.corrupt(format!(
                "LAZ chunk {index}'s layers take {layers} bytes but the chunk has {}",
                chunk.byte_count
            )));
        }
        chunk_start += chunk.byte_count;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::fs;
    use std::path::Path;

    use crate::ingest::test_files::*;
    use crate::ingest::IngestError;

    /// The LASzip VLR's data starts after the 227-byte (LAS 1.2) or 375-byte (LAS 1.4)
    /// header and its 54-byte VLR header.
    const LASZIP_DATA_1_2: usize = 227 + 54;
    const LASZIP_DATA_1_4: usize = 375 + 54;

    fn patched(path: &Path, original: &[u8], at: usize, value: &[u8]) {
        let mut bytes = original.to_vec();
        bytes[at..at + value.len()].copy_from_slice(value);
        fs::write(path, &bytes).expect("patch");
    }

    #[test]
    fn items_must_make_the_record_the_header_declares() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (path, original) = file_to_cut(dir.path(), "items.laz", 100);
        let first_item = LASZIP_DATA_1_2 + 34;
        // Point10's size set to 0 (the decoder divides by the items' size) and to 21.
        patched(&path, &original, first_item + 2, &0u16.to_le_bytes());
        assert!(corrupt_message(&path).contains("item type 6 of 0 bytes"));
        patched(&path, &original, first_item + 2, &21u16.to_le_bytes());
        assert!(corrupt_message(&path).contains("of 21 bytes"));
        // One item fewer: the record is shorter than the header's 34 bytes.
        let count = u16::from_le_bytes([
            original[LASZIP_DATA_1_2 + 32],
            original[LASZIP_DATA_1_2 + 33],
        ]);
        patched(
            &path,
            &original,
            LASZIP_DATA_1_2 + 32,
            &(count - 1).to_le_bytes(),
        );
        assert!(corrupt_message(&path).contains("but the header says 34"));
        // Mixed coder versions.
        patched(&path, &original, first_item + 4, &1u16.to_le_bytes());
        assert!(corrupt_message(&path).contains("mixed coder versions"));
    }

    #[test]
    fn the_chunk_table_is_checked_against_the_compressed_data() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (path, original) = file_to_cut(dir.path(), "chunks.laz", 1_000);
        let data_start = u32::from_le_bytes(original[96..100].try_into().expect("4 bytes"));
        let table = u64::from_le_bytes(
            original[data_start as usize..][..8]
                .try_into()
                .expect("8 bytes"),
        ) as usize;
        // 2^32 - 1 chunks would reserve 64 GiB before the first entry is read.
        patched(&path, &original, table + 4, &u32::MAX.to_le_bytes());
        assert!(corrupt_message(&path).contains("declares 4294967295 chunks"));
        // A chunk of 2^31 points in a file of 1,000.
        patched(
            &path,
            &original,
            LASZIP_DATA_1_2 + 12,
            &(1u32 << 31).to_le_bytes(),
        );
        assert!(corrupt_message(&path).contains("a LAZ chunk of 2147483648 points"));
        // The table's offset beyond the end of the file.
        let beyond = (original.len() as u64 + 1).to_le_bytes();
        patched(&path, &original, data_start as usize, &beyond);
        assert!(matches!(
            load_error(&path),
            IngestError::LazChunkTable { .. }
        ));
    }

    #[test]
    fn layered_chunks_must_hold_their_layers() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (path, original) = written_1_4(dir.path(), "layers.laz", 1_000, 7);
        assert_eq!(
            u16::from_le_bytes([original[LASZIP_DATA_1_4], original[LASZIP_DATA_1_4 + 1]]),
            3
        );
        let data_start =
            u32::from_le_bytes(original[96..100].try_into().expect("4 bytes")) as usize;
        // The first layer size after the chunk's raw first record (36 bytes) and point count.
        let first_layer_size = data_start + 8 + 36 + 4;
        patched(
            &path,
            &original,
            first_layer_size,
            &0x7fff_ffffu32.to_le_bytes(),
        );
        assert!(corrupt_message(&path).contains("layers take"));
    }
}

//! The variable length records, walked by hand before the `las` crate reads them: every VLR
//! must end before the point data, every EVLR inside the file. The crate allocates each
//! record's declared length before reading it, so an EVLR claiming a terabyte would be
//! allocated (and zeroed) in full before the read fails.

use super::header::HeaderFacts;
use super::raw_file::{RawFile, RecordSpan};
use super::IngestError;

/// A VLR's header: reserved (2), user id (16), record id (2), length (2), description (32).
const VLR_HEADER_LEN: u64 = 54;
/// An EVLR's header: as a VLR's, with an 8-byte length.
const EVLR_HEADER_LEN: u64 = 60;
const USER_ID_OFFSET: u64 = 2;
const RECORD_ID_OFFSET: u64 = 18;
const LENGTH_OFFSET: u64 = 20;

/// The LASzip VLR: the compressor, chunk size and item layout of a LAZ file.
const LASZIP_USER_ID: &[u8; 16] = b"laszip encoded\0\0";
const LASZIP_RECORD_ID: u16 = 22204;

/// Walks the VLRs and EVLRs, checking every one's extent; gives the LASzip VLR's data span
/// when there is one.
pub(super) fn check_records(
    raw: &mut RawFile<'_>,
    facts: &HeaderFacts,
) -> Result<Option<RecordSpan>, IngestError> {
    let vlr_end = facts.offset_to_point_data;
    let mut offset = u64::from(facts.header_size);
    let mut laszip = None;
    for index in 0..facts.vlr_count {
        // Each VLR takes at least its header, so a huge count stops at the point data.
        if offset + VLR_HEADER_LEN > vlr_end {
            return Err(raw.corrupt(format!(
                "VLR {index} of {} starts at offset {offset}, past the start of the point data ({vlr_end})",
                facts.vlr_count
            )));
        }
        let len = u64::from(raw.u16_at(offset + LENGTH_OFFSET, "a VLR header")?);
        let data = RecordSpan {
            offset: offset + VLR_HEADER_LEN,
            len,
        };
        if data.offset + len > vlr_end {
            return Err(raw.corrupt(format!(
                "VLR {index}: its {len} bytes at offset {} run past the start of the point data ({vlr_end})",
                data.offset
            )));
        }
        if is_laszip(raw, offset)? {
            laszip = Some(data);
        }
        offset = data.offset + len;
    }

    if let Some((first, count)) = facts.evlrs {
        check_evlrs(raw, facts, first, count)?;
    }
    Ok(laszip)
}

fn is_laszip(raw: &mut RawFile<'_>, record_offset: u64) -> Result<bool, IngestError> {
    let user_id: [u8; 16] = raw.array_at(record_offset + USER_ID_OFFSET, "a VLR user id")?;
    let record_id = raw.u16_at(record_offset + RECORD_ID_OFFSET, "a VLR record id")?;
    Ok(&user_id == LASZIP_USER_ID && record_id == LASZIP_RECORD_ID)
}

/// EVLRs follow the point data (for LAZ, the compressed data and its chunk table) one after
/// another up to the end of the file.
fn check_evlrs(
    raw: &mut RawFile<'_>,
    facts: &HeaderFacts,
    first: u64,
    count: u32,
) -> Result<(), IngestError> {
    if first < facts.offset_to_point_data {
        return Err(raw.corrupt(format!(
            "start of first EVLR ({first}) lies before the point data ({})",
            facts.offset_to_point_data
        )));
    }
    let mut offset = first;
    for index in 0..count {
        // Each EVLR takes at least its header, so a huge count stops at the end of the file.
        raw.check_span(offset, EVLR_HEADER_LEN, &format!("EVLR {index} of {count}"))?;
        let len = raw.u64_at(offset + LENGTH_OFFSET, "an EVLR header")?;
        raw.check_span(
            offset + EVLR_HEADER_LEN,
            len,
            &format!("EVLR {index}'s data"),
        )?;
        offset += EVLR_HEADER_LEN + len;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::fs;

    use crate::ingest::test_files::*;

    #[test]
    fn a_vlr_running_into_the_point_data_is_corrupt() {
        let dir = tempfile::tempdir().expect("temp dir");
        // A LAZ file has one VLR (LASzip's), its length at 227 + 20.
        let (path, mut bytes) = file_to_cut(dir.path(), "long_vlr.laz", 100);
        bytes[247..249].copy_from_slice(&u16::MAX.to_le_bytes());
        fs::write(&path, &bytes).expect("patch");
        assert!(corrupt_message(&path).contains("run past the start of the point data"));

        // More VLRs than fit before the point data.
        let (path, mut bytes) = file_to_cut(dir.path(), "many_vlrs.laz", 100);
        bytes[100..104].copy_from_slice(&u32::MAX.to_le_bytes());
        fs::write(&path, &bytes).expect("patch");
        assert!(corrupt_message(&path).contains("VLR 1 of 4294967295"));
    }

    #[test]
    fn an_evlr_longer_than_the_file_is_corrupt_before_anything_is_allocated() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (path, mut bytes) = written_1_4(dir.path(), "evlr.las", 100, 6);
        // One EVLR after the points, then its length set to a terabyte.
        let start = bytes.len() as u64;
        bytes[235..243].copy_from_slice(&start.to_le_bytes());
        bytes[243..247].copy_from_slice(&1u32.to_le_bytes());
        let mut evlr = vec![0u8; 60];
        evlr[20..28].copy_from_slice(&4u64.to_le_bytes());
        bytes.extend_from_slice(&evlr);
        bytes.extend_from_slice(b"data");
        fs::write(&path, &bytes).expect("append");
        assert_eq!(
            crate::ingest::load_point_cloud(&path)
                .expect("a well-formed EVLR loads")
                .len(),
            100
        );

        let at = start as usize + 20;
        bytes[at..at + 8].copy_from_slice(&(1u64 << 40).to_le_bytes());
        fs::write(&path, &bytes).expect("patch");
        assert!(corrupt_message(&path).contains("EVLR 0's data (1099511627776 bytes"));

        let data_start = u32::from_le_bytes(
            bytes[OFFSET_TO_POINT_DATA..OFFSET_TO_POINT_DATA + 4]
                .try_into()
                .expect("4 bytes"),
        );
        bytes[235..243].copy_from_slice(&u64::from(data_start - 1).to_le_bytes());
        fs::write(&path, &bytes).expect("patch");
        assert!(corrupt_message(&path).contains("lies before the point data"));
    }
}

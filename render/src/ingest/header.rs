//! The checks made before the `las` crate sees a file: the signature, version, point
//! format and declared point count against the file's size, and for LAZ against its chunk
//! table. The crate trusts the declared count: it sizes its read buffer from it, in LAS 1.4
//! files it multiplies the 64-bit count by the record length unchecked, and its parallel LAZ
//! decoder panics when asked for more points than the file's chunks hold.

use std::fs::File;
use std::io::{self, BufReader, Read, Seek, SeekFrom};
use std::path::Path;

use super::IngestError;

/// Checks the declared point count against the LAZ chunk table before decoding: the parallel
/// decompressor asserts (and in release builds underflows) when asked for more points than its
/// chunks hold. Within the last fixed-size chunk the decoder's own end-of-data error applies.
pub(super) fn check_laz_chunk_capacity(
    path: &Path,
    file: &mut File,
    declared: u64,
) -> Result<(), IngestError> {
    let malformed = |error| IngestError::Malformed {
        path: path.to_owned(),
        error,
    };
    file.seek(SeekFrom::Start(0))
        .map_err(|error| IngestError::Io {
            path: path.to_owned(),
            error,
        })?;
    let mut read = BufReader::new(file);
    // Parsing the header leaves `read` at the start of the point data, where the table offset is.
    let header = las::Header::new(&mut read).map_err(malformed)?;
    let vlr = header.laz_vlr().map_err(malformed)?;
    if !is_chunked_laz(&header) {
        return Ok(()); // Pre-2011 LAZ: no chunk table, and decoded sequentially.
    }
    let chunk_table = laz::laszip::ChunkTable::read_from(&mut read, &vlr).map_err(|error| {
        IngestError::LazChunkTable {
            path: path.to_owned(),
            error,
        }
    })?;
    let chunk_capacity = chunk_table
        .as_ref()
        .iter()
        .map(|chunk| chunk.point_count)
        .sum();
    if declared > chunk_capacity {
        return Err(IngestError::TruncatedLaz {
            path: path.to_owned(),
            declared,
            chunk_capacity,
        });
    }
    Ok(())
}

/// Whether the LASzip VLR names a chunked compressor (its first field; `laz` keeps it private).
pub(super) fn is_chunked_laz(header: &las::Header) -> bool {
    const POINT_WISE_UNCHUNKED: u16 = 1;
    header
        .vlrs()
        .iter()
        .find(|vlr| vlr.user_id == laz::LazVlr::USER_ID && vlr.record_id == laz::LazVlr::RECORD_ID)
        .and_then(|vlr| vlr.data.get(..2))
        .is_some_and(|compressor| {
            u16::from_le_bytes([compressor[0], compressor[1]]) != POINT_WISE_UNCHUNKED
        })
}

/// The header fields that decide whether a file can be read at all, validated before the
/// `las` crate parses it.
pub(super) struct HeaderFacts {
    pub version: (u8, u8),
    /// Point format number without the LAZ compression bits.
    pub point_format: u8,
    pub compressed: bool,
    pub declared_points: u64,
}

impl HeaderFacts {
    pub fn read(path: &Path, file: &mut File, file_len: u64) -> Result<Self, IngestError> {
        let mut signature = [0u8; 4];
        let signature_len = read_up_to(file, &mut signature).map_err(|error| IngestError::Io {
            path: path.to_owned(),
            error,
        })?;
        if signature[..signature_len] != *b"LASF" {
            return Err(IngestError::NotLas {
                path: path.to_owned(),
                found: String::from_utf8_lossy(&signature[..signature_len]).into_owned(),
            });
        }
        file.seek(SeekFrom::Start(0))
            .map_err(|error| IngestError::Io {
                path: path.to_owned(),
                error,
            })?;
        let raw =
            las::raw::Header::read_from(BufReader::new(&mut *file)).map_err(
                |error| match error {
                    las::Error::Io(error) if error.kind() == io::ErrorKind::UnexpectedEof => {
                        IngestError::TruncatedHeader {
                            path: path.to_owned(),
                            file_len,
                        }
                    }
                    error => IngestError::Malformed {
                        path: path.to_owned(),
                        error,
                    },
                },
            )?;

        let version = (raw.version.major, raw.version.minor);
        if version.0 != 1 || version.1 > 4 {
            return Err(IngestError::UnsupportedVersion {
                path: path.to_owned(),
                major: version.0,
                minor: version.1,
            });
        }
        // LASzip marks compressed data by setting bit 7 (and sometimes bit 6) of the format.
        let compressed = raw.point_data_record_format & 0x80 != 0;
        let point_format = raw.point_data_record_format & 0x3f;
        if point_format > 10 {
            return Err(IngestError::UnsupportedPointFormat {
                path: path.to_owned(),
                format: point_format,
            });
        }

        // LAS 1.4 keeps a 64-bit count; a non-zero legacy count wins, as the spec asks.
        let legacy_points = u64::from(raw.number_of_point_records);
        let declared_points = match raw.large_file {
            Some(large) if legacy_points == 0 => large.number_of_point_records,
            _ => legacy_points,
        };
        if declared_points == 0 {
            return Err(IngestError::NoPoints {
                path: path.to_owned(),
            });
        }

        let data_start = u64::from(raw.offset_to_point_data);
        if data_start > file_len {
            return Err(IngestError::TruncatedHeader {
                path: path.to_owned(),
                file_len,
            });
        }
        let record_len = u64::from(raw.point_data_record_length);
        let bytes_after_header = file_len - data_start;
        if compressed {
            // `las` computes `count * record_len` unchecked while parsing the header; an absurd
            // 64-bit count would overflow it.
            if declared_points.checked_mul(record_len).is_none() {
                return Err(IngestError::ImpossiblePointCount {
                    path: path.to_owned(),
                    declared: declared_points,
                });
            }
        } else if record_len > 0 && declared_points.saturating_mul(record_len) > bytes_after_header
        {
            // Uncompressed data has a fixed size: check it up front, so a short file is reported
            // with the number of points that are really there.
            return Err(IngestError::Truncated {
                path: path.to_owned(),
                declared: declared_points,
                available: bytes_after_header / record_len,
            });
        }
        Ok(Self {
            version,
            point_format,
            compressed,
            declared_points,
        })
    }

    /// Points to allocate for up front: the declared count, unless the file is too small to
    /// hold that many (then the vectors grow as points are actually decoded).
    pub fn capacity_hint(&self, file_len: u64) -> usize {
        let capacity = if self.compressed {
            self.declared_points.min(file_len)
        } else {
            self.declared_points
        };
        usize::try_from(capacity).unwrap_or(0)
    }
}

/// Like `read_exact`, but returns how many bytes there were instead of failing on a short file.
fn read_up_to(read: &mut impl Read, buf: &mut [u8]) -> io::Result<usize> {
    let mut filled = 0;
    while filled < buf.len() {
        match read.read(&mut buf[filled..]) {
            Ok(0) => break,
            Ok(n) => filled += n,
            Err(error) if error.kind() == io::ErrorKind::Interrupted => {}
            Err(error) => return Err(error),
        }
    }
    Ok(filled)
}

#[cfg(test)]
mod tests {
    use std::fs;

    use super::*;
    use crate::ingest::test_files::*;
    use crate::ingest::{IngestError, LasWriteOptions};

    const POINT_FORMAT_OFFSET: usize = 104;

    fn patch_point_count(path: &Path, count: u64) {
        let mut bytes = fs::read(path).expect("read back");
        let legacy = u32::try_from(count).unwrap_or(0);
        bytes[LEGACY_POINT_COUNT_OFFSET..][..4].copy_from_slice(&legacy.to_le_bytes());
        if bytes[VERSION_MINOR_OFFSET] == 4 {
            bytes[POINT_COUNT_OFFSET_1_4..][..8].copy_from_slice(&count.to_le_bytes());
        }
        fs::write(path, bytes).expect("patch");
    }

    /// Loads `$path`, which must fail with an error matching `$pattern` (shown when it does
    /// not), and gives the error.
    macro_rules! assert_load_fails {
        ($path:expr, $pattern:pat) => {{
            let error = load_error($path);
            assert!(matches!(error, $pattern), "{error}");
            error
        }};
    }

    #[test]
    fn rejects_files_that_are_not_las() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("notes.las");
        fs::write(&path, "x,y,z\n1,2,3\n").expect("write");
        assert!(matches!(load_error(&path), IngestError::NotLas { found, .. } if found == "x,y,"));

        let empty = dir.path().join("empty.las");
        fs::write(&empty, "").expect("write");
        assert!(matches!(load_error(&empty), IngestError::NotLas { .. }));
    }

    #[test]
    fn reports_how_many_points_a_truncated_las_file_holds() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (path, bytes) = file_to_cut(dir.path(), "cut.las", 1_000);
        // Format 3 records are 34 bytes: keep 412 and a half.
        let data_start = bytes.len() - 1_000 * 34;
        fs::write(&path, &bytes[..data_start + 412 * 34 + 17]).expect("cut");
        let error = assert_load_fails!(
            &path,
            IngestError::Truncated {
                declared: 1_000,
                available: 412,
                ..
            }
        );
        assert!(error
            .to_string()
            .ends_with("truncated: header says 1000 points but data ends after 412"));

        fs::write(&path, &bytes[..150]).expect("cut inside the header");
        assert!(matches!(
            load_error(&path),
            IngestError::TruncatedHeader { file_len: 150, .. }
        ));
    }

    #[test]
    fn rejects_a_point_count_larger_than_the_data() {
        let dir = tempfile::tempdir().expect("temp dir");
        let cloud = test_cloud(1_000);
        for (minor, point_format) in [(2, 3), (4, 1), (4, 7)] {
            let options = LasWriteOptions {
                version: (1, minor),
                point_format,
                scale: 0.001,
            };
            let las = write(
                dir.path(),
                &format!("count_1{minor}_{point_format}.las"),
                &cloud,
                &options,
            );
            patch_point_count(&las, 1_001);
            assert_load_fails!(
                &las,
                IngestError::Truncated {
                    declared: 1_001,
                    available: 1_000,
                    ..
                }
            );
            if minor == 4 {
                // A 64-bit count that would overflow `count * record_length` in `las`.
                patch_point_count(&las, u64::MAX / 2);
                assert_load_fails!(&las, IngestError::Truncated { .. });
            }

            let laz = write(
                dir.path(),
                &format!("count_1{minor}_{point_format}.laz"),
                &cloud,
                &options,
            );
            // Beyond the one 50,000-point chunk: caught from the chunk table, before decoding.
            let beyond_u32: &[u64] = if minor == 4 {
                &[u64::from(u32::MAX) + 1]
            } else {
                &[]
            };
            for &declared in [60_000].iter().chain(beyond_u32) {
                patch_point_count(&laz, declared);
                assert_load_fails!(
                    &laz,
                    IngestError::TruncatedLaz {
                        chunk_capacity: 50_000,
                        ..
                    }
                );
            }
            if minor == 4 {
                patch_point_count(&laz, u64::MAX / 2);
                assert_load_fails!(&laz, IngestError::ImpossiblePointCount { .. });
            }
        }
    }

    #[test]
    fn rejects_a_laz_file_cut_short() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (path, bytes) = file_to_cut(dir.path(), "cut.laz", 1_000);
        fs::write(&path, &bytes[..bytes.len() * 2 / 3]).expect("cut");
        assert_load_fails!(&path, IngestError::LazChunkTable { .. });
    }

    #[test]
    fn rejects_a_file_without_points() {
        let dir = tempfile::tempdir().expect("temp dir");
        for name in ["empty_cloud.las", "empty_cloud.laz"] {
            let path = write_default(dir.path(), name, &test_cloud(0));
            assert!(matches!(load_error(&path), IngestError::NoPoints { .. }));
        }
    }

    #[test]
    fn rejects_unsupported_point_formats_and_versions() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (path, original) = file_to_cut(dir.path(), "odd.las", 10);

        let mut bytes = original.clone();
        bytes[POINT_FORMAT_OFFSET] = 42;
        fs::write(&path, &bytes).expect("patch");
        assert_load_fails!(
            &path,
            IngestError::UnsupportedPointFormat { format: 42, .. }
        );

        let mut bytes = original;
        bytes[VERSION_MINOR_OFFSET] = 9;
        fs::write(&path, &bytes).expect("patch");
        assert_load_fails!(
            &path,
            IngestError::UnsupportedVersion {
                major: 1,
                minor: 9,
                ..
            }
        );
    }
}

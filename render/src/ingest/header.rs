//! The public header block, read and checked before the `las` crate sees a file: signature,
//! version, point format and record length, the declared point count against the file's size,
//! the header size against the offset to the point data, and the scale factors and offsets.
//! The crate trusts the declared count: it sizes its read buffer from it, and it computes
//! `offset + count * record_length` unchecked.

use std::io::{self, BufReader, Read, SeekFrom};
use std::path::Path;

use super::raw_file::ReadSeek;
use super::transforms::check_transforms;
use super::IngestError;

/// The header fields that decide whether and how a file can be read, validated before the
/// `las` crate parses it.
pub(crate) struct HeaderFacts {
    pub version: (u8, u8),
    /// Point format number without the LAZ compression bits.
    pub point_format: u8,
    pub compressed: bool,
    pub declared_points: u64,
    /// Bytes of one point record, extra bytes included.
    pub record_len: u16,
    /// Where the VLRs start (the header's declared size).
    pub header_size: u16,
    pub vlr_count: u32,
    pub offset_to_point_data: u64,
    /// LAS 1.4: the first EVLR's offset and the number of EVLRs, when both are non-zero.
    pub evlrs: Option<(u64, u32)>,
}

impl HeaderFacts {
    pub fn read(path: &Path, file: &mut dyn ReadSeek, file_len: u64) -> Result<Self, IngestError> {
        let mut signature = [0u8; 4];
        let signature_len = read_up_to(file, &mut signature).map_err(|error| IngestError::Io {
            path: path.to_owned(),
            error,
        })?;
        if signature[..signature_len] != *super::LAS_SIGNATURE {
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
        // The raw header allocates nothing the file does not hold (its padding is at most
        // 65,535 bytes, read up to the end of the file).
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
        let corrupt = |what: String| IngestError::Corrupt {
            path: path.to_owned(),
            what,
        };

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
        let Some(format_len) = point_record_len(point_format) else {
            return Err(IngestError::UnsupportedPointFormat {
                path: path.to_owned(),
                format: point_format,
            });
        };
        let record_len = raw.point_data_record_length;
        if record_len < format_len {
            return Err(corrupt(format!(
                "point record length {record_len} is shorter than point format {point_format} ({format_len} bytes)"
            )));
        }
        check_transforms(path, &raw)?;

        // LAS 1.4 keeps a 64-bit count; a non-zero legacy count wins, as the spec asks.
        let legacy_points = u64::from(raw.number_of_point_records);
        let declared_points = match raw.large_file {
            Some(large) if legacy_points == 0 => large.number_of_point_records,
            _ => legacy_points,
        };

        let data_start = u64::from(raw.offset_to_point_data);
        if data_start > file_len {
            return Err(IngestError::TruncatedHeader {
                path: path.to_owned(),
                file_len,
            });
        }
        let standard_header_size = raw.version.header_size();
        if raw.header_size < standard_header_size || u64::from(raw.header_size) > data_start {
            return Err(corrupt(format!(
                "header size {} must lie between {standard_header_size} (LAS {}.{}) and the offset to the point data ({data_start})",
                raw.header_size, version.0, version.1
            )));
        }
        let bytes_after_header = file_len - data_start;
        if !compressed && declared_points.saturating_mul(u64::from(record_len)) > bytes_after_header
        {
            // Uncompressed data has a fixed size: check it up front, so a short file is reported
            // with the number of points that are really there.
            return Err(IngestError::Truncated {
                path: path.to_owned(),
                declared: declared_points,
                available: bytes_after_header / u64::from(record_len),
            });
        }
        // `las` adds the offset to `count * record_length` unchecked; no real file comes close.
        let data_end = declared_points
            .checked_mul(u64::from(record_len))
            .and_then(|len| len.checked_add(data_start));
        if data_end.is_none() {
            return Err(IngestError::ImpossiblePointCount {
                path: path.to_owned(),
                declared: declared_points,
            });
        }
        let evlrs = raw
            .evlr
            .filter(|evlr| evlr.start_of_first_evlr > 0 && evlr.number_of_evlrs > 0)
            .map(|evlr| (evlr.start_of_first_evlr, evlr.number_of_evlrs));
        Ok(Self {
            version,
            point_format,
            compressed,
            declared_points,
            record_len,
            header_size: raw.header_size,
            vlr_count: raw.number_of_variable_length_records,
            offset_to_point_data: data_start,
            evlrs,
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

/// The record length of a point format without extra bytes (LAS 1.4 R15, table 7 onwards).
fn point_record_len(point_format: u8) -> Option<u16> {
    const LENGTHS: [u16; 11] = [20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67];
    LENGTHS.get(usize::from(point_format)).copied()
}

/// Like `read_exact`, but returns how many bytes there were instead of failing on a short file.
fn read_up_to(read: &mut (impl Read + ?Sized), buf: &mut [u8]) -> io::Result<usize> {
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

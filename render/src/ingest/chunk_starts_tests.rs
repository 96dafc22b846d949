use std::fs;
use std::path::{Path, PathBuf};

use las::{PointDataBuilder, Reader};

use super::*;
use crate::ingest::test_files::*;
use crate::ingest::{load_dataset, LasWriteOptions};
use crate::testing::{laz_of_las, LazChunks};

/// Every record of `path`, decoded by the `las` crate (the `laz` decompressor for LAZ).
fn all_records(path: &Path) -> las::PointData {
    let mut reader = Reader::from_path(path).expect("las reader");
    let mut points = PointDataBuilder::new().for_header(reader.header()).build();
    let count = reader.header().number_of_points();
    reader.fill_points(count, &mut points).expect("decode");
    points
}

/// Samples `path` and checks that each sampled record is, byte for byte, the record the
/// decompressor gives at the same index; gives the sampled indices.
fn sample_matches_decoder(path: &Path, las_stride: u64) -> Vec<u64> {
    let (indices, points) = sample_one(path, las_stride).unwrap_or_else(|e| panic!("{e}"));
    let all = all_records(path);
    let len = all.record_len();
    assert_eq!(points.record_len(), len);
    assert_eq!(indices.len(), points.len());
    assert!(!indices.is_empty(), "{} gave no sample", path.display());
    for (k, &index) in indices.iter().enumerate() {
        let index = index as usize;
        assert_eq!(
            &points.raw_bytes()[k * len..][..len],
            &all.raw_bytes()[index * len..][..len],
            "{}: sampled record {k} (point {index}) differs from the decoded one",
            path.display()
        );
    }
    indices
}

fn shared(name: &str) -> Option<PathBuf> {
    let path = shared_data_dir()?.join(name);
    if path.is_file() {
        Some(path)
    } else {
        eprintln!("skipped: shared/data/{name} is not in this checkout");
        None
    }
}

#[test]
fn real_pointwise_laz_chunk_starts_are_the_decoded_points() {
    for (name, points) in [("autzen_trim.laz", 110_000u64), ("lone-star.laz", 518_862)] {
        let Some(path) = shared(name) else {
            continue;
        };
        let indices = sample_matches_decoder(&path, LAS_PREVIEW_STRIDE);
        // Fixed chunks of 50,000 points: one sampled point each.
        let expected: Vec<u64> = (0..points.div_ceil(50_000)).map(|k| k * 50_000).collect();
        assert_eq!(indices, expected, "{name}");
    }
}

#[test]
fn real_las_is_sampled_every_stride_records() {
    let Some(path) = shared("autzen_trim.las") else {
        return;
    };
    let indices = sample_matches_decoder(&path, 997);
    assert_eq!(indices.len(), 110_000usize.div_ceil(997));
    assert_eq!(indices[1], 997);
}

#[test]
fn layered_laz_chunk_starts_are_the_decoded_points() {
    let dir = tempfile::tempdir().expect("temp dir");
    for format in [6u8, 7, 8] {
        let (path, _) = written_1_4(dir.path(), &format!("f{format}.laz"), 120_000, format);
        let indices = sample_matches_decoder(&path, LAS_PREVIEW_STRIDE);
        assert_eq!(indices, vec![0, 50_000, 100_000], "format {format}");
    }
}

#[test]
fn pointwise_laz_of_each_format_matches_the_decoder() {
    let dir = tempfile::tempdir().expect("temp dir");
    for format in [0u8, 1, 2, 3] {
        let options = LasWriteOptions {
            point_format: format,
            ..LasWriteOptions::default()
        };
        let path = write(
            dir.path(),
            &format!("f{format}.laz"),
            &test_cloud(100_001),
            &options,
        );
        let indices = sample_matches_decoder(&path, LAS_PREVIEW_STRIDE);
        assert_eq!(indices, vec![0, 50_000, 100_000], "format {format}");
    }
}

#[test]
fn variable_size_chunks_of_copc_files_match_the_decoder() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/data/copc");
    for name in ["simple.copc.laz", "simple_with_page.copc.laz"] {
        let indices = sample_matches_decoder(&dir.join(name), LAS_PREVIEW_STRIDE);
        // COPC chunks are the octree's nodes, of varying sizes.
        assert!(indices.len() > 1, "{name}: {indices:?}");
        assert!(indices.windows(2).all(|pair| pair[0] < pair[1]), "{name}");
    }
}

#[test]
fn the_sample_cloud_has_the_loaded_datasets_origin_and_points() {
    let dir = tempfile::tempdir().expect("temp dir");
    let a = write_default(dir.path(), "a.laz", &test_cloud(120_000));
    let b = write_default(dir.path(), "b.las", &test_cloud(60_000));
    let files = vec![a, b];
    let full = load_dataset(&files).expect("load");
    let sample = sample_dataset(&files, 25_000).expect("sample");
    assert_eq!(sample.points_in_files, 180_000);
    assert_eq!(sample.cloud.origin, full.origin);
    // a.laz's chunk starts, then every 25,000th record of b.las after a's 120,000 points.
    let indices = [0, 50_000, 100_000, 120_000, 145_000, 170_000];
    assert_eq!(sample.cloud.len(), indices.len());
    for (k, &index) in indices.iter().enumerate() {
        assert_eq!(
            sample.cloud.positions[k], full.positions[index],
            "point {index}"
        );
        assert_eq!(sample.cloud.intensity[k], full.intensity[index]);
        assert_eq!(sample.cloud.classification[k], full.classification[index]);
    }
    assert_eq!(sample.cloud.color_source, full.color_source);
}

#[test]
fn empty_files_leave_the_sample_as_it_is() {
    let dir = tempfile::tempdir().expect("temp dir");
    let a = write_default(dir.path(), "a.laz", &test_cloud(120_000));
    let b = write_default(dir.path(), "b.las", &test_cloud(60_000));
    let empties = crate::testing::write_empty_files(dir.path(), &["0.laz", "1.las"]);
    let alone = sample_dataset(&[a.clone(), b.clone()], 25_000).expect("sample");
    let mixed = [empties[0].clone(), a, empties[1].clone(), b];
    let sample = sample_dataset(&mixed, 25_000).expect("sample with empty files");
    assert_eq!(sample.points_in_files, alone.points_in_files);
    assert_eq!(sample.cloud.origin, alone.cloud.origin);
    assert_eq!(sample.cloud.positions, alone.cloud.positions);
    assert_eq!(sample.cloud.colors, alone.cloud.colors);
    assert_eq!(sample.cloud.color_source, alone.cloud.color_source);
}

/// `las` (an uncompressed LAS 1.2 file without VLRs) compressed as point-wise LAZ in chunks
/// of `chunks` points each (variable-size chunks, which the crate's writer does not make).
fn variable_chunk_laz(las: &Path, chunks: &[usize]) -> PathBuf {
    let bytes = fs::read(las).expect("read LAS");
    let path = las.with_extension("laz");
    fs::write(&path, laz_of_las(&bytes, LazChunks::Variable(chunks))).expect("write LAZ");
    path
}

#[test]
fn variable_size_point_wise_chunks_match_the_decoder() {
    let dir = tempfile::tempdir().expect("temp dir");
    let las = write_default(dir.path(), "variable.las", &test_cloud(10_000));
    let laz = variable_chunk_laz(&las, &[1_000, 3_000, 17, 5_983]);
    let indices = sample_matches_decoder(&laz, LAS_PREVIEW_STRIDE);
    assert_eq!(indices, vec![0, 1_000, 4_000, 4_017]);
}

/// Samples a file that must fail, and gives the message, which must name the file.
fn sample_error(path: &Path) -> String {
    let message = match sample_chunk_starts(&[path.to_path_buf()]) {
        Ok(sample) => panic!("sampled {} points, expected an error", sample.cloud.len()),
        Err(error) => error.to_string(),
    };
    assert!(message.contains(&file_name(path)), "{message}");
    message
}

#[test]
fn corrupt_chunk_tables_are_refused_naming_the_file() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (path, original) = file_to_cut(dir.path(), "chunks.laz", 120_000);
    let data_start = u32::from_le_bytes(original[96..100].try_into().expect("4 bytes")) as usize;
    let table = u64::from_le_bytes(original[data_start..][..8].try_into().expect("8 bytes"));
    let patch = |at: usize, value: &[u8]| {
        let mut bytes = original.clone();
        bytes[at..at + value.len()].copy_from_slice(value);
        fs::write(&path, bytes).expect("patch");
    };
    // The table's offset beyond the end of the file.
    patch(data_start, &(original.len() as u64 + 100).to_le_bytes());
    assert!(sample_error(&path).contains("chunk table"));
    // 2^32 - 1 chunks would reserve 64 GiB of table and 2^32 sampled records.
    patch(table as usize + 4, &u32::MAX.to_le_bytes());
    assert!(sample_error(&path).contains("declares 4294967295 chunks"));
    // Two chunks more than the table holds, few enough to fit the compressed data: the
    // table's entries run out of the file.
    patch(table as usize + 4, &5u32.to_le_bytes());
    let message = sample_error(&path);
    assert!(message.contains("chunk"), "{message}");
    // The file cut in its second chunk: the table (at the end) is gone, and so are chunks.
    fs::write(&path, &original[..original.len() * 2 / 3]).expect("cut");
    sample_error(&path);
}

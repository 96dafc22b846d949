//! The well-formed files the corpus is made from: the real scans (when the checkout has
//! them) and clouds written by `write_las` across LAS 1.2/1.3/1.4, point formats and LAS/LAZ.
//! Every written source gets a VLR of its own (so VLR mutations have one to aim at), and the
//! LAS 1.4 ones an EVLR.

use std::fs;
use std::path::{Path, PathBuf};

use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::sample::sample_scene;

use crate::layout::{append_evlr, header, Layout, VLR_HEADER_LEN};
use crate::CorpusError;

/// The real scans next to the repository, used when present.
pub const REAL_SCANS: [&str; 3] = ["autzen_trim.las", "autzen_trim.laz", "lone-star.laz"];

/// The COPC file in the repository's test data, written by another tool (laspy's test data):
/// a layered LAZ whose chunks are the octree's nodes.
pub const COPC_SOURCE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../tests/data/copc/simple.copc.laz"
);

/// A source file: its name (with extension) and bytes.
pub struct Source {
    pub name: String,
    pub bytes: Vec<u8>,
}

impl Source {
    pub fn extension(&self) -> &str {
        Path::new(&self.name)
            .extension()
            .and_then(|extension| extension.to_str())
            .unwrap_or("las")
    }

    pub fn stem(&self) -> &str {
        Path::new(&self.name)
            .file_stem()
            .and_then(|stem| stem.to_str())
            .unwrap_or("source")
    }
}

/// One written source: version, point format, extension and points.
struct Written {
    minor: u8,
    point_format: u8,
    extension: &'static str,
    points: usize,
}

/// The written sources of the full corpus; two LAZ files span several 50,000-point chunks.
const FULL: [Written; 11] = [
    written(2, 0, "las", 5_000),
    written(2, 3, "las", 5_000),
    written(2, 1, "laz", 5_000),
    written(2, 3, "laz", 120_000),
    written(3, 5, "las", 3_000),
    written(3, 2, "laz", 5_000),
    written(4, 6, "las", 5_000),
    written(4, 7, "laz", 5_000),
    written(4, 8, "laz", 120_000),
    written(4, 10, "las", 3_000),
    written(4, 1, "laz", 5_000),
];

/// The small written sources of the fast subset: one of each family (LAS, point-wise LAZ,
/// layered LAZ with an EVLR).
const FAST: [Written; 3] = [
    written(2, 3, "las", 2_000),
    written(3, 1, "laz", 2_000),
    written(4, 7, "laz", 2_000),
];

const fn written(minor: u8, point_format: u8, extension: &'static str, points: usize) -> Written {
    Written {
        minor,
        point_format,
        extension,
        points,
    }
}

/// Writes the written sources into `dir` and gives them with the repository's COPC file and
/// the real scans found in `real_dir`.
pub fn sources(
    dir: &Path,
    real_dir: Option<&Path>,
    fast: bool,
) -> Result<Vec<Source>, CorpusError> {
    fs::create_dir_all(dir).map_err(|error| CorpusError::io(dir, error))?;
    let specs: &[Written] = if fast { &FAST } else { &FULL };
    let mut sources = Vec::new();
    for (index, spec) in specs.iter().enumerate() {
        sources.push(write_source(dir, index as u64, spec)?);
    }
    let real = REAL_SCANS
        .iter()
        .filter_map(|name| real_dir.map(|real| real.join(name)))
        .filter(|path| path.is_file());
    for path in std::iter::once(PathBuf::from(COPC_SOURCE)).chain(real) {
        let name = path
            .file_name()
            .map(|name| name.to_string_lossy().into_owned())
            .unwrap_or_default();
        let bytes = fs::read(&path).map_err(|error| CorpusError::io(&path, error))?;
        let copy = dir.join(&name);
        fs::write(&copy, &bytes).map_err(|error| CorpusError::io(&copy, error))?;
        sources.push(Source { name, bytes });
    }
    Ok(sources)
}

fn write_source(dir: &Path, seed: u64, spec: &Written) -> Result<Source, CorpusError> {
    let name = format!(
        "written-v1{}-f{}-{}k.{}",
        spec.minor,
        spec.point_format,
        spec.points / 1000,
        spec.extension
    );
    let path: PathBuf = dir.join(&name);
    let options = LasWriteOptions {
        version: (1, spec.minor),
        point_format: spec.point_format,
        scale: 0.001,
    };
    write_las(&path, &sample_scene(spec.points, seed), &options)?;
    let mut bytes = fs::read(&path).map_err(|error| CorpusError::io(&path, error))?;
    insert_vlr(
        &name,
        &mut bytes,
        b"written by the pointfarm corpus generator",
    )?;
    if spec.minor == 4 {
        append_evlr(
            &mut bytes,
            b"an EVLR after the points, for the EVLR mutations",
        );
    }
    fs::write(&path, &bytes).map_err(|error| CorpusError::io(&path, error))?;
    Ok(Source { name, bytes })
}

/// Inserts a text VLR after the existing ones, moving the point data (and for LAZ the chunk
/// table offset stored at its start) along.
fn insert_vlr(name: &str, bytes: &mut Vec<u8>, text: &[u8]) -> Result<(), CorpusError> {
    let layout = Layout::of(name, bytes)?;
    let mut record = vec![0u8; VLR_HEADER_LEN];
    record[2..2 + 9].copy_from_slice(b"pointfarm");
    record[18..20].copy_from_slice(&7u16.to_le_bytes());
    record[20..22].copy_from_slice(&(text.len() as u16).to_le_bytes());
    record[22..22 + 11].copy_from_slice(b"corpus note");
    record.extend_from_slice(text);
    let shift = record.len();
    let at = layout
        .vlrs
        .last()
        .map_or(layout.header_size, |vlr| vlr.data_offset() + vlr.data_len);
    bytes.splice(at..at, record);

    let data_start = (layout.data_start + shift) as u32;
    bytes[header::OFFSET_TO_POINT_DATA..][..4].copy_from_slice(&data_start.to_le_bytes());
    let vlr_count = layout.vlrs.len() as u32 + 1;
    bytes[header::VLR_COUNT..][..4].copy_from_slice(&vlr_count.to_le_bytes());
    if let Some(table) = layout.chunk_table {
        let moved = (table + shift) as u64;
        bytes[data_start as usize..][..8].copy_from_slice(&moved.to_le_bytes());
    }
    Ok(())
}

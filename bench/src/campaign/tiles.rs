//! Writing a campaign's tiles: a generated terrain ([`GeneratedSource::terrain`]) split on a
//! grid of `files` tiles, each tile a LAZ file and, when asked, a LAS file beside it. Written
//! streaming: the generator's batches are routed to per-tile buffers of bounded size, which go
//! to their tiles' writers as they fill, so the campaign is never in memory.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use las::point::{Classification, Format};
use las::{Color, Point, PointDataBuilder, Transform, Vector, Writer};
use pointfarm_render::cloud::WorldBounds;
use pointfarm_render::lod::{GeneratedSource, PointBatch, PointSource};

use crate::BenchError;

/// The files' LAS version and point format: 1.2, format 3 (GPS time and RGB), 34 bytes a
/// record, as most airborne deliveries.
const VERSION: (u8, u8) = (1, 2);
const POINT_FORMAT: u8 = 3;
/// Millimetre coordinates.
const SCALE: f64 = 0.001;
/// Bytes of a LAS record of [`POINT_FORMAT`].
pub const LAS_RECORD_BYTES: u64 = 34;
/// What the tiles' buffers hold at most, all tiles together (the buffers of one tile are at
/// least a LAZ chunk and at most 256k points).
const TILE_BUFFERS_BYTES: usize = 128 << 20;
/// The fewest points a tile is generated with on average: fewer would leave a tile empty.
pub const MIN_POINTS_PER_FILE: u64 = 1_000;

/// A point as the buffers hold it until it is written.
#[derive(Debug, Clone, Copy)]
struct Record {
    position: [f64; 3],
    rgb: [u16; 3],
    intensity: u16,
    classification: u8,
    return_number: u8,
}

/// The files written: per tile a LAZ path and (with LAS) a LAS path.
#[derive(Debug)]
pub struct CampaignFiles {
    pub laz: Vec<PathBuf>,
    pub las: Vec<PathBuf>,
    /// Points written, all tiles together.
    pub points: u64,
}

/// Rows and columns of a grid of `files` tiles, as square as `files` allows.
pub fn grid(files: usize) -> (usize, usize) {
    let rows = (1..=files)
        .take_while(|r| r * r <= files)
        .filter(|r| files.is_multiple_of(*r))
        .last()
        .unwrap_or(1);
    (rows, files / rows)
}

struct Tile {
    laz: Writer<BufWriter<File>>,
    las: Option<Writer<BufWriter<File>>>,
    buffer: Vec<Record>,
    written: u64,
}

fn las_error(path: &Path, error: las::Error) -> BenchError {
    BenchError::Scratch(format!("writing {}: {error}", path.display()))
}

impl Tile {
    fn writer(path: &Path, bounds: &WorldBounds) -> Result<Writer<BufWriter<File>>, BenchError> {
        let mut builder = las::Builder::from(VERSION);
        builder.point_format = Format::new(POINT_FORMAT).map_err(|e| las_error(path, e))?;
        let axis = |min: f64| Transform {
            scale: SCALE,
            offset: min.floor(),
        };
        builder.transforms = Vector {
            x: axis(bounds.min.x),
            y: axis(bounds.min.y),
            z: axis(bounds.min.z),
        };
        builder.generating_software = "pointfarm bench".to_owned();
        let header = builder.into_header().map_err(|e| las_error(path, e))?;
        Writer::from_path(path, header).map_err(|e| las_error(path, e))
    }

    /// Encodes the buffered points once and appends them to the tile's files.
    fn flush(&mut self, path: &Path) -> Result<(), BenchError> {
        if self.buffer.is_empty() {
            return Ok(());
        }
        let points = self.buffer.drain(..).map(|r| Point {
            x: r.position[0],
            y: r.position[1],
            z: r.position[2],
            intensity: r.intensity,
            return_number: r.return_number,
            number_of_returns: r.return_number,
            classification: Classification::new(r.classification).unwrap_or_default(),
            gps_time: Some(0.0),
            color: Some(Color::new(r.rgb[0], r.rgb[1], r.rgb[2])),
            ..Point::default()
        });
        let data = PointDataBuilder::new()
            .for_header(self.laz.header())
            .build_from_points(points)
            .map_err(|e| las_error(path, e))?;
        self.written += data.len() as u64;
        self.laz
            .write_points(&data)
            .map_err(|e| las_error(path, e))?;
        if let Some(las) = &mut self.las {
            las.write_points(&data).map_err(|e| las_error(path, e))?;
        }
        Ok(())
    }
}

/// Writes the terrain of `points` points (seeded by `seed`) as `files` tiles into `dir`:
/// `tile-RR-CC.laz`, and `tile-RR-CC.las` when `with_las`.
pub fn write_campaign(
    dir: &Path,
    points: u64,
    files: usize,
    seed: u64,
    with_las: bool,
) -> Result<CampaignFiles, BenchError> {
    if files == 0 || points < files as u64 * MIN_POINTS_PER_FILE {
        return Err(BenchError::Scratch(format!(
            "a campaign of {files} files needs at least {MIN_POINTS_PER_FILE} points a file, \
             not {points} points in all"
        )));
    }
    let source = GeneratedSource::terrain(points, seed);
    let bounds = source.bounds();
    let (rows, cols) = grid(files);
    let size = bounds.size();
    let (tile_x, tile_y) = (size.x / cols as f64, size.y / rows as f64);
    let buffer_points = (TILE_BUFFERS_BYTES / size_of::<Record>() / files).clamp(50_000, 1 << 18);

    let mut names = Vec::with_capacity(files);
    let mut tiles = Vec::with_capacity(files);
    for row in 0..rows {
        for col in 0..cols {
            let min = bounds.min + glam::DVec3::new(col as f64 * tile_x, row as f64 * tile_y, 0.0);
            let tile_bounds = WorldBounds {
                min,
                max: min + glam::DVec3::new(tile_x, tile_y, size.z),
            };
            let laz = dir.join(format!("tile-{row:02}-{col:02}.laz"));
            let las = with_las.then(|| laz.with_extension("las"));
            tiles.push(Tile {
                laz: Tile::writer(&laz, &tile_bounds)?,
                las: las
                    .as_deref()
                    .map(|path| Tile::writer(path, &tile_bounds))
                    .transpose()?,
                buffer: Vec::with_capacity(buffer_points),
                written: 0,
            });
            names.push((laz, las));
        }
    }

    let tile_of = |x: f64, y: f64| {
        let col = (((x - bounds.min.x) / tile_x) as usize).min(cols - 1);
        let row = (((y - bounds.min.y) / tile_y) as usize).min(rows - 1);
        row * cols + col
    };
    let mut route = |batch: PointBatch<'_>| -> Result<(), BenchError> {
        let rgb = batch.rgb.unwrap_or_default();
        for (i, p) in batch.positions.iter().enumerate() {
            let index = tile_of(p.x, p.y);
            let tile = &mut tiles[index];
            tile.buffer.push(Record {
                position: p.to_array(),
                rgb: rgb.get(i).copied().unwrap_or_default(),
                intensity: batch.intensity[i],
                classification: batch.classification[i],
                return_number: batch.return_number[i],
            });
            if tile.buffer.len() >= buffer_points {
                tile.flush(&names[index].0)?;
            }
        }
        Ok(())
    };
    // The routing's own error is kept apart from the generator's.
    let mut failed = None;
    let walked = source.for_each_batch(&mut |batch| {
        route(batch).map_err(|error| {
            let message = error.to_string();
            failed = Some(error);
            pointfarm_render::lod::LodError::Source(message)
        })
    });
    if let Err(error) = walked {
        return Err(failed.unwrap_or(BenchError::Lod(error)));
    }

    let mut written = 0;
    for (tile, (laz, las)) in tiles.iter_mut().zip(&names) {
        tile.flush(laz)?;
        tile.laz.close().map_err(|e| las_error(laz, e))?;
        if let (Some(writer), Some(path)) = (&mut tile.las, las) {
            writer.close().map_err(|e| las_error(path, e))?;
        }
        written += tile.written;
    }
    if written != points {
        return Err(BenchError::Scratch(format!(
            "{written} points were written of the {points} generated"
        )));
    }
    let (laz, las): (Vec<PathBuf>, Vec<Option<PathBuf>>) = names.into_iter().unzip();
    Ok(CampaignFiles {
        laz,
        las: las.into_iter().flatten().collect(),
        points: written,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use pointfarm_render::ingest::{load_dataset, DatasetSource};

    #[test]
    fn grids_are_as_square_as_the_count_allows() {
        assert_eq!(grid(1), (1, 1));
        assert_eq!(grid(4), (2, 2));
        assert_eq!(grid(20), (4, 5));
        assert_eq!(grid(7), (1, 7));
        assert_eq!(grid(1000), (25, 40));
    }

    #[test]
    fn the_tiles_hold_every_generated_point_once_and_split_the_terrain() {
        let dir = tempfile::tempdir().expect("tempdir");
        let files = write_campaign(dir.path(), 40_000, 4, 3, true).expect("written");
        assert_eq!(
            (files.laz.len(), files.las.len(), files.points),
            (4, 4, 40_000)
        );
        let laz = DatasetSource::open(&files.laz).expect("laz");
        let las = DatasetSource::open(&files.las).expect("las");
        assert_eq!(laz.point_count(), 40_000);
        assert_eq!(las.point_count(), 40_000);
        let generated = GeneratedSource::terrain(40_000, 3).bounds();
        assert!(generated.min.cmple(laz.bounds().min + 1e-3).all());
        assert!(laz.bounds().max.cmple(generated.max + 1e-2).all());
        // Each tile covers about a quarter of the ground.
        let first = load_dataset(&files.laz[..1]).expect("tile");
        let whole = generated.size();
        let tile = first.bounds.max - first.bounds.min;
        assert!(
            tile.x < whole.x * 0.51 && tile.y < whole.y * 0.51,
            "{tile} of {whole}"
        );
        assert!(
            first.len() > 8_000 && first.len() < 12_000,
            "{}",
            first.len()
        );
        // LAS and LAZ hold the same points.
        let same = load_dataset(&files.las[..1]).expect("las tile");
        assert_eq!(same.positions, first.positions);
    }
}

use super::*;
use crate::ingest::{load_dataset, write_las, LasWriteOptions};
use crate::lod::{build_lod, LodBuildOptions, LodStore};
use crate::sample::sample_scene;

#[test]
fn the_files_of_a_dataset_build_a_hierarchy_holding_every_point_once() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = sample_scene(30_000, 4);
    let half = scene.len() / 2;
    let (a, b) = (dir.path().join("a.laz"), dir.path().join("b.las"));
    let first: Vec<usize> = (0..half).collect();
    let second: Vec<usize> = (half..scene.len()).collect();
    write_las(&a, &scene.select(&first), &LasWriteOptions::default()).expect("a");
    write_las(&b, &scene.select(&second), &LasWriteOptions::default()).expect("b");
    let files = [a, b];

    let source = DatasetSource::open(&files).expect("open");
    assert_eq!(source.point_count(), scene.len() as u64);
    let loaded = load_dataset(&files).expect("load");
    assert!(source.bounds().min.cmple(loaded.bounds.min).all());
    assert!(loaded.bounds.max.cmple(source.bounds().max).all());

    let db = sled::Config::new().temporary(true).open().expect("sled");
    let store = LodStore::open(
        db.open_tree("lod").expect("tree"),
        dir.path().join("lod.bin"),
    )
    .expect("store");
    let mut options = LodBuildOptions::new(dir.path().join("spill"));
    options.max_leaf_points = 4_000;
    let report = build_lod(&source, &store, &options).expect("build");
    let hierarchy = store.read_hierarchy().expect("hierarchy");
    assert_eq!(hierarchy.point_count, scene.len() as u64);
    let stored: u64 = hierarchy
        .nodes()
        .iter()
        .map(|node| store.read_node(&hierarchy, node.key).expect("node").len() as u64)
        .sum();
    assert_eq!(
        stored,
        scene.len() as u64,
        "every point in exactly one node"
    );
    assert!(hierarchy.stats.has_rgb);
    assert!(report.hierarchy.nodes().len() > 1);
}

/// What a build stored, to compare builds: nodes, their records without the offsets
/// (which follow the order threads finished nodes in), and the statistics.
#[derive(Debug, PartialEq)]
struct Stored {
    infos: Vec<crate::lod::NodeInfo>,
    nodes: Vec<crate::lod::NodePoints>,
    stats: crate::lod::DatasetStats,
}

/// `source` built into the store `name` of `db` (payload in `dir`), with small leaves.
fn built_store(
    source: &dyn PointSource,
    db: &sled::Db,
    dir: &std::path::Path,
    name: &str,
) -> (crate::lod::LodBuildReport, Stored) {
    let store = LodStore::open(
        db.open_tree(name).expect("tree"),
        dir.join(format!("{name}.bin")),
    )
    .expect("store");
    let mut options = LodBuildOptions::new(dir.join("spill"));
    options.max_leaf_points = 2_000;
    let report = build_lod(source, &store, &options).expect("build");
    let hierarchy = store.read_hierarchy().expect("hierarchy");
    let nodes = hierarchy
        .nodes()
        .iter()
        .map(|node| store.read_node(&hierarchy, node.key).expect("node"))
        .collect();
    let infos = hierarchy
        .nodes()
        .iter()
        .map(|n| crate::lod::NodeInfo {
            offset: 0,
            rest_offset: 0,
            attributes_offset: 0,
            ..*n
        })
        .collect();
    let stats = hierarchy.stats.clone();
    (
        report,
        Stored {
            infos,
            nodes,
            stats,
        },
    )
}

/// LAZ, decoded once like every source, builds the store LAS builds.
#[test]
fn laz_builds_what_las_builds() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = sample_scene(20_000, 3);
    let db = sled::Config::new().temporary(true).open().expect("sled");
    let mut built = Vec::new();
    for name in ["c.las", "c.laz"] {
        let path = dir.path().join(name);
        write_las(&path, &scene, &LasWriteOptions::default()).expect("write");
        let source = DatasetSource::open(&[path]).expect("open");
        let (_, store) = built_store(&source, &db, dir.path(), name);
        built.push(store);
    }
    assert!(built[0].infos.len() > 1);
    assert!(built[0] == built[1], "LAS and LAZ built different stores");
}

/// The attribute rows of `points`' format, without their extra bytes.
fn no_extra_rows(points: &las::PointData) -> RowFiller {
    let format = points.format();
    let len = usize::from(format.len() - format.extra_bytes);
    let number = format.to_u8().expect("a format number");
    RowFiller::new(number, len, false, &AttributeSchema::default())
}

/// The parallel fill gives what the `las` crate's column iterators give, in every point
/// format, over more than one block.
#[test]
fn columns_are_the_crates_in_every_point_format() {
    use crate::ingest::test_files::written_1_4;
    let dir = tempfile::tempdir().expect("tempdir");
    for format in 0..=10u8 {
        let (path, _) = written_1_4(dir.path(), &format!("f{format}.las"), 40_000, format);
        let mut reader = las::Reader::from_path(&path).expect("reader");
        let points = reader.read_all().expect("read");
        let mut columns = BatchColumns::default();
        let rows = no_extra_rows(&points);
        fill(
            &mut columns,
            &points,
            points.transforms(),
            true,
            None,
            &rows,
        );
        let positions = crate::testing::las_world_positions(&points);
        assert_eq!(columns.positions, positions, "format {format}");
        // On the file's own grid, the same positions bit for bit.
        let t = points.transforms();
        let grid = PositionGrid::new(
            DVec3::new(t.x.scale, t.y.scale, t.z.scale),
            DVec3::new(t.x.offset, t.y.offset, t.z.offset),
        )
        .expect("a grid");
        let mut on_grid = BatchColumns::default();
        fill(&mut on_grid, &points, t, true, Some((&grid, [0; 3])), &rows);
        assert_eq!(on_grid.rows, columns.rows, "format {format}");
        let bits = |p: &[DVec3]| -> Vec<[u64; 3]> {
            p.iter().map(|p| p.to_array().map(f64::to_bits)).collect()
        };
        assert_eq!(
            bits(&on_grid.positions),
            bits(&positions),
            "format {format}"
        );
        let intensity: Vec<u16> = points.intensity().collect();
        assert_eq!(columns.intensity, intensity, "format {format}");
        let classes: Vec<u8> = points.classification().collect();
        assert_eq!(columns.classification, classes, "format {format}");
        let returns: Vec<u8> = points.return_number().collect();
        assert_eq!(columns.return_number, returns, "format {format}");
        let rgb: Vec<[u16; 3]> = points
            .rgb()
            .map(|rgb| rgb.map(|(r, g, b)| [r, g, b]).collect())
            .unwrap_or_default();
        assert_eq!(columns.rgb, rgb, "format {format}");
    }
}

/// What [`Without`] holds back of a source.
#[derive(Clone, Copy, PartialEq)]
enum Withheld {
    /// No grid declared: the builder spills world records.
    Grid,
    /// Batches without their attribute rows and no schema, as a source that keeps none.
    Attributes,
}

/// A source's points with one part of what it offers held back.
struct Without<'a>(&'a DatasetSource, Withheld);

impl PointSource for Without<'_> {
    fn bounds(&self) -> WorldBounds {
        self.0.bounds()
    }
    fn point_count(&self) -> u64 {
        self.0.point_count()
    }
    fn position_grid(&self) -> Option<PositionGrid> {
        (self.1 != Withheld::Grid)
            .then(|| self.0.position_grid())
            .flatten()
    }
    fn for_each_batch(&self, visit: &mut BatchVisitor<'_>) -> Result<(), LodError> {
        match self.1 {
            Withheld::Grid => self.0.for_each_batch(visit),
            Withheld::Attributes => self
                .0
                .for_each_batch(&mut |batch| visit(crate::lod::PointBatch { rows: &[], ..batch })),
        }
    }
    fn attributes(&self) -> Option<AttributeSchema> {
        (self.1 != Withheld::Attributes)
            .then(|| self.0.attributes())
            .flatten()
    }
}

/// The attributes sections change nothing a frame reads: a build that keeps them stores
/// the same nodes, records and statistics as one that does not, and only it lists
/// attributes sections, whose rows give back each point's GPS time.
#[test]
fn attributes_sections_leave_what_frames_read_unchanged() {
    use crate::ingest::test_files::written_1_4;
    let dir = tempfile::tempdir().expect("tempdir");
    let (path, _) = written_1_4(dir.path(), "f3.las", 30_000, 3);
    let source = DatasetSource::open(&[path]).expect("open");
    let db = sled::Config::new().temporary(true).open().expect("sled");
    let (_, with) = built_store(&source, &db, dir.path(), "with");
    let (_, without) = built_store(
        &Without(&source, Withheld::Attributes),
        &db,
        dir.path(),
        "without",
    );
    let records = |stored: &Stored| -> Vec<crate::lod::NodeInfo> {
        let no_attributes = |n: &crate::lod::NodeInfo| crate::lod::NodeInfo {
            attributes_len: 0,
            ..*n
        };
        stored.infos.iter().map(no_attributes).collect()
    };
    assert!(with.infos.len() > 1);
    assert_eq!(records(&with), records(&without));
    assert!(with.nodes == without.nodes && with.stats == without.stats);
    assert!(with
        .infos
        .iter()
        .all(|n| n.attributes_len > 0 || n.point_count == 0));
    assert!(without.infos.iter().all(|n| n.attributes_len == 0));
}

/// Tiles written with offsets of their own share one grid: their points read onto it
/// within an f64 step of their own decoding, and the build from grid records stores
/// exactly what the build from f64 records stores, in less spill.
#[test]
fn tiles_on_one_grid_spill_grid_records_and_build_the_same_store() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = sample_scene(24_000, 5);
    let mut files = Vec::new();
    for (k, shift) in [0.0, 137.0, -2_041.0].into_iter().enumerate() {
        let mut tile = scene.select(&(k * 8_000..(k + 1) * 8_000).collect::<Vec<_>>());
        // Another origin gives the tile another offset, a whole number of metres away.
        tile.origin += DVec3::new(shift, -shift, 0.0);
        for p in &mut tile.positions {
            *p -= glam::Vec3::new(shift as f32, -shift as f32, 0.0);
        }
        let path = dir
            .path()
            .join(format!("t{k}.{}", if k == 1 { "laz" } else { "las" }));
        write_las(&path, &tile, &LasWriteOptions::default()).expect("write");
        files.push(path);
    }
    let source = DatasetSource::open(&files).expect("open");
    let shared = source.grid.clone().expect("one grid");
    assert!(shared.shifts.iter().any(|s| *s != [0; 3]), "{shared:?}");

    for (k, file) in files.iter().enumerate() {
        let mut reader = las::Reader::from_path(file).expect("reader");
        let points = reader.read_all().expect("read");
        let own = crate::testing::las_world_positions(&points);
        let mut columns = BatchColumns::default();
        fill(
            &mut columns,
            &points,
            points.transforms(),
            true,
            Some((&shared.grid, shared.shifts[k])),
            &no_extra_rows(&points),
        );
        for (a, b) in columns.positions.iter().zip(&own) {
            let step = b.abs().max_element() * f64::EPSILON;
            assert!((*a - *b).abs().max_element() <= step, "{a} against {b}");
        }
    }

    let db = sled::Config::new().temporary(true).open().expect("sled");
    let mut built = Vec::new();
    let grid_source: &dyn PointSource = &source;
    let world_source: &dyn PointSource = &Without(&source, Withheld::Grid);
    for (name, source) in [("grid", grid_source), ("world", world_source)] {
        built.push(built_store(source, &db, dir.path(), name));
    }
    let ((grid_report, grid), (world_report, world)) = (&built[0], &built[1]);
    let record_bytes = (
        grid_report.spill_record_bytes,
        world_report.spill_record_bytes,
    );
    // The positions' 26 or 38 bytes, then the 16 of a row of format 1's attributes.
    assert_eq!(record_bytes, (26 + 16, 38 + 16));
    let spilled = (grid_report.spilled_bytes, world_report.spilled_bytes);
    assert!(
        spilled.0 * (38 + 16) == spilled.1 * (26 + 16),
        "{spilled:?} bytes spilled"
    );
    assert!(grid.infos.len() > 1);
    assert!(
        grid.infos == world.infos && grid.nodes == world.nodes,
        "the stores differ"
    );
}

#[test]
fn files_of_other_scales_or_offsets_off_the_grid_share_none() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = sample_scene(4_000, 2);
    let write = |name: &str, scale: f64, shift: f64| {
        let mut tile = scene.clone();
        tile.origin += DVec3::splat(shift);
        for p in &mut tile.positions {
            *p -= glam::Vec3::splat(shift as f32);
        }
        let path = dir.path().join(name);
        let options = LasWriteOptions {
            scale,
            ..LasWriteOptions::default()
        };
        write_las(&path, &tile, &options).expect("write");
        path
    };
    let mm = write("mm.las", 0.001, 0.0);
    let cm = write("cm.las", 0.01, 0.0);
    let one = DatasetSource::open(std::slice::from_ref(&mm)).expect("open");
    assert!(one.position_grid().is_some());
    let mixed = DatasetSource::open(&[mm.clone(), cm.clone()]).expect("open");
    assert!(mixed.position_grid().is_none(), "two scales");
    // The second file is decoded into the records of the first, made for its transforms: its
    // positions are still its own.
    let mut read = Vec::new();
    mixed
        .for_each_batch(&mut |batch| {
            read.extend_from_slice(batch.positions);
            Ok(())
        })
        .expect("read");
    let mut own = Vec::new();
    for path in [&mm, &cm] {
        let mut reader = las::Reader::from_path(path).expect("reader");
        let points = reader.read_all().expect("read");
        own.extend(crate::testing::las_world_positions(&points));
    }
    assert_eq!(read, own);
    // write_las rounds its offset to whole metres: a 0.4 m shift stays on the grid only
    // if the rounding does, so build the off-grid case from the headers directly.
    let mut files = DatasetFile::check_all(&[mm.clone(), mm]).expect("files");
    files[1].offset.x += 0.000_5;
    assert!(
        shared_grid(&files, &one.bounds()).is_none(),
        "half a step off"
    );
    files[1].offset.x += 0.000_5;
    assert!(
        shared_grid(&files, &one.bounds()).is_some(),
        "a whole step off"
    );
}

#[test]
fn a_bad_file_fails_the_source_naming_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let bad = dir.path().join("bad.las");
    std::fs::write(&bad, b"LASF and nothing else").expect("write");
    let error = DatasetSource::open(&[bad]).err().expect("a bad file");
    assert!(error.to_string().contains("bad.las"), "{error}");
}

#[test]
fn a_point_beyond_its_headers_bounds_is_named_by_its_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = sample_scene(8_000, 5);
    let world = |i: usize| scene.origin.x + f64::from(scene.positions[i].x);
    let middle = scene.bounds.center().x;
    let (west, east): (Vec<usize>, Vec<usize>) = (0..scene.len()).partition(|&i| world(i) < middle);
    let options = LasWriteOptions::default();
    let paths = ["west.laz", "empty.las", "east.las"].map(|name| dir.path().join(name));
    write_las(&paths[0], &scene.select(&west), &options).expect("west");
    write_las(&paths[1], &scene.select(&[]), &options).expect("empty");
    write_las(&paths[2], &scene.select(&east), &options).expect("east");
    // The east file's header says its points end a metre past the middle: LAS 1.2 keeps the
    // largest x at byte 179.
    let mut bytes = std::fs::read(&paths[2]).expect("read");
    bytes[179..187].copy_from_slice(&(middle + 1.0).to_le_bytes());
    std::fs::write(&paths[2], bytes).expect("patch");

    let source = DatasetSource::open(&paths).expect("open");
    let db = sled::Config::new().temporary(true).open().expect("sled");
    let tree = db.open_tree("lod").expect("tree");
    let store = LodStore::open(tree, dir.path().join("lod.bin")).expect("store");
    let options = LodBuildOptions::new(dir.path().join("spill"));
    let error = build_lod(&source, &store, &options).expect_err("a refusal");
    match source.naming_the_file(error) {
        Ok(IngestError::PointOutsideHeaderBounds {
            path,
            position,
            max,
            ..
        }) => {
            assert_eq!(path, paths[2]);
            assert!(position[0] > middle + 1.0 && max[0] == middle + 1.0);
        }
        other => panic!("expected the east file named, got {other:?}"),
    }
    // Another error is left as it is.
    let other = LodError::MissingHierarchy;
    assert!(matches!(
        source.naming_the_file(other),
        Err(LodError::MissingHierarchy)
    ));
}

/// The visitor runs while the next batch decodes: every batch reaches it in order, its
/// error stops the reading and is what the read returns, and a file that fails while
/// the visitor works is named.
#[test]
fn batches_decoded_ahead_reach_the_visitor_in_order_and_errors_stop_the_read() {
    let dir = tempfile::tempdir().expect("tempdir");
    let scene = sample_scene(9_000, 6);
    let files: Vec<PathBuf> = (0..3)
        .map(|k| {
            let path = dir.path().join(format!("{k}.laz"));
            let part: Vec<usize> = (k * 3_000..(k + 1) * 3_000).collect();
            write_las(&path, &scene.select(&part), &LasWriteOptions::default()).expect("write");
            path
        })
        .collect();
    let source = DatasetSource::open(&files).expect("open");
    let mut firsts = Vec::new();
    source
        .for_each_batch(&mut |batch| {
            firsts.push(batch.positions[0]);
            Ok(())
        })
        .expect("read");
    let loaded = load_dataset(&files).expect("load");
    let expected: Vec<DVec3> = [0, 3_000, 6_000]
        .iter()
        .map(|&i| loaded.origin + loaded.positions[i].as_dvec3())
        .collect();
    assert_eq!(firsts.len(), 3, "a batch a file");
    for (got, want) in firsts.iter().zip(&expected) {
        assert!((*got - *want).abs().max_element() < 1e-3, "{got} vs {want}");
    }

    let mut visits = 0;
    let error = source
        .for_each_batch(&mut |_| {
            visits += 1;
            Err(LodError::Source("the visitor stopped".into()))
        })
        .expect_err("the visitor's error");
    assert_eq!(visits, 1);
    assert!(error.to_string().contains("the visitor stopped"), "{error}");

    // The last file cut short after the source was opened: its error names it.
    let bytes = std::fs::read(&files[2]).expect("read");
    std::fs::write(&files[2], &bytes[..bytes.len() / 2]).expect("truncate");
    let error = source
        .for_each_batch(&mut |_| Ok(()))
        .expect_err("a truncated file");
    assert!(error.to_string().contains("2.laz"), "{error}");
}

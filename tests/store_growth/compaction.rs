//! A growth from a store whose payload is mostly dead bytes compacts it into one file: a
//! store of the tiles and a file spread over all of them, grown without that file (every
//! region rebuilt, the whole earlier payload dead below the grown one's), is grown again with
//! a tile. The compacted store holds one payload file and no layer list, shares no file with
//! the earlier stores, holds a fresh build's points and draws its frame, and draws the same
//! once the earlier stores are deleted.

use pointfarm_render::lod::disk_usage::DiskUsage;

use super::*;

/// Every this many points of the scene lie in the file spread over all of it.
const SPREAD_EVERY: usize = 3;

/// The finished store of the dataset `id` under `data`.
fn store_named(data: &Path, id: &str) -> PathBuf {
    let name = id.trim_start_matches("ds-");
    std::fs::read_dir(data.join("lod"))
        .expect("the daemon's stores")
        .map(|entry| entry.expect("entry").path())
        .find(|path| {
            StoredLod::is_built(path)
                && path
                    .file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with(name))
        })
        .unwrap_or_else(|| panic!("no store of {id} in {}", data.display()))
}

/// The names of the payload's files in the store `folder`: its own, its layers and their list.
fn payload_files(folder: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(folder)
        .expect("the store's folder")
        .map(|entry| {
            entry
                .expect("entry")
                .file_name()
                .to_string_lossy()
                .into_owned()
        })
        .filter(|name| name.starts_with("nodes.bin"))
        .collect();
    names.sort();
    names
}

/// Folders of links to the files `names` in `all`, one a dataset.
fn dataset_folder(dir: &Path, all: &Path, name: &str, names: &[String]) -> PathBuf {
    let folder = dir.join(name);
    std::fs::create_dir_all(&folder).expect("folder");
    for file in names {
        std::fs::hard_link(all.join(file), folder.join(file)).expect("link a file");
    }
    folder
}

#[test]
fn a_growth_from_a_store_mostly_of_dead_bytes_compacts_it_into_one_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cloud = sample_scene(KILLED_POINTS, 11);
    let all = dir.path().join("all");
    std::fs::create_dir_all(&all).expect("folder");
    let options = LasWriteOptions::default();
    let spread: Vec<usize> = (0..cloud.len()).step_by(SPREAD_EVERY).collect();
    write_las(&all.join("spread.las"), &cloud.select(&spread), &options).expect("spread");
    let tiles = ground_plan_tiles(&cloud, ACROSS, ALONG);
    for (index, points) in tiles.iter().enumerate() {
        let kept: Vec<usize> = points
            .iter()
            .copied()
            .filter(|i| i % SPREAD_EVERY != 0)
            .collect();
        write_las(&all.join(tile_name(index)), &cloud.select(&kept), &options).expect("tile");
    }
    let middle = ACROSS * ALONG / 2;
    let names = |leave_out: Option<usize>| -> Vec<String> {
        (0..tiles.len())
            .filter(|&i| Some(i) != leave_out)
            .map(tile_name)
            .collect()
    };
    let with_spread = [names(Some(middle)), vec!["spread.las".to_owned()]].concat();
    let with_spread = dataset_folder(dir.path(), &all, "with-spread", &with_spread);
    let day1 = dataset_folder(dir.path(), &all, "day1", &names(Some(middle)));
    let day2 = dataset_folder(dir.path(), &all, "day2", &names(None));
    let camera = &camera_flags(&cloud);

    // Built whole, grown without the spread file, then grown with the middle tile.
    let data = dir.path().join("daemon");
    let address = free_address();
    let mut server = serve(&address, &data, None);
    let first_png = dir.path().join("with-spread.png");
    let first = dataset_of(&run(
        &mut render(&server, &with_spread, &first_png, camera),
        &server,
    ));
    let day1_png = dir.path().join("day1.png");
    let earlier = dataset_of(&run(
        &mut render(&server, &day1, &day1_png, camera),
        &server,
    ));
    let compacted_png = dir.path().join("compacted.png");
    let grown = dataset_of(&run(
        &mut render(&server, &day2, &compacted_png, camera),
        &server,
    ));
    let log = server.log();
    for (from, change) in [
        (&first, "0 files added, 1 removed"),
        (&earlier, "1 files added, 0 removed"),
    ] {
        let said = format!("from the store of dataset {from}: {change}");
        assert!(log.contains(&said), "{said}:\n{log}");
    }
    assert_eq!(log.matches("levels of detail built").count(), 1, "{log}");
    let line = log
        .lines()
        .find(|l| l.contains("compacted the earlier store's payload into one file"))
        .unwrap_or_else(|| panic!("no compaction:\n{log}"));
    let field = |name: &str| number_after(line, &format!(" {name}=")).expect(name);
    let (payload, freed) = (field("payload_bytes"), field("freed_bytes"));
    assert_eq!(field("layers"), 2.0, "{line}");
    assert!(freed * 2.0 > payload, "most bytes dead: {line}");
    assert_eq!(field("compacted_bytes") + freed, payload, "{line}");
    println!("{line}");
    stop(&mut server);

    // One payload file, no list, sharing nothing; the earlier store still links the first's.
    let compacted = store_named(&data, &grown);
    assert_eq!(payload_files(&compacted), ["nodes.bin"]);
    let alone = DiskUsage::of(&compacted);
    assert_eq!(
        alone.freed_bytes(),
        alone.bytes(),
        "the compacted store shares no file"
    );
    let (first_store, earlier_store) = (store_named(&data, &first), store_named(&data, &earlier));
    assert_eq!(
        payload_files(&earlier_store),
        ["nodes.bin", "nodes.bin.0", "nodes.bin.layers"]
    );
    let linking = DiskUsage::of(&earlier_store);
    assert!(
        linking.freed_bytes() < linking.bytes(),
        "the first store's payload is shared"
    );

    // The earlier stores deleted, the compacted one draws the same without a build.
    std::fs::remove_dir_all(&first_store).expect("the first store deleted");
    std::fs::remove_dir_all(&earlier_store).expect("the earlier store deleted");
    let restarted = (address.as_str(), data.as_path());
    let again = (
        dir.path().join("compacted-alone.png"),
        compacted_png.as_path(),
    );
    let what = "the compacted store once the earlier stores are gone";
    let log = render_restarted(restarted, &day2, camera, again, what);
    assert!(
        !log.contains("levels of detail built") && !log.contains("updated the store of"),
        "made again:\n{log}"
    );

    // It draws a fresh build's frame and holds its points.
    let what = "the compacted store";
    let served = (compacted, compacted_png.as_path());
    let points =
        assert_as_a_fresh_build(dir.path(), "fresh-day2", (&day2, 21), camera, served, what);
    assert_eq!(
        points.len(),
        KILLED_POINTS - spread.len(),
        "every point once"
    );
}

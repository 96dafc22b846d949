//! Where a frame's points come from, decided once for a local render and a server: a small
//! dataset renders resident until a render with a pixel error builds its store, and from that
//! store's cut afterwards, here as through a server, with the same images; a worker holding
//! the resident cloud follows the server once it has built the store.

use std::path::Path;

use pointfarm_tests::service::scratch_sample;
use pointfarm_tests::{json_lines, output_text, path_arg, pointfarm_ok, ServeProcess};

const FRAMES: [&str; 2] = ["frame_00000.png", "frame_00001.png"];

/// `pointfarm render FILE --out OUT --json` with `extra`; one JSON object per frame.
fn render(file: &Path, out: &Path, extra: &[&str]) -> Vec<serde_json::Value> {
    let mut args = vec![
        "render",
        path_arg(file),
        "--out",
        path_arg(out),
        "--size=160x120",
        "--turntable",
        "2",
        "--json",
    ];
    args.extend(extra);
    let frames = json_lines(&pointfarm_ok(&args));
    assert_eq!(frames.len(), 2, "{frames:?}");
    frames
}

/// Whether each frame a local render reports was drawn from a cut.
fn local_cuts(frames: &[serde_json::Value]) -> Vec<bool> {
    frames.iter().map(|f| f.get("cut").is_some()).collect()
}

/// The job of the frames a server reports, as `jobs show` lists it.
fn job_of(frames: &[serde_json::Value], server: &ServeProcess) -> pointfarm_proto::v1::Job {
    let id = frames[0]["jobId"].as_str().expect("a job id");
    serde_json::from_value(server.job_json(id)).expect("a Job")
}

/// Whether each frame a server reports was drawn from a cut, as `jobs show` lists the job.
fn server_cuts(frames: &[serde_json::Value], server: &ServeProcess) -> Vec<bool> {
    let from_render: Vec<bool> = frames
        .iter()
        .map(|f| f["finished"].get("cut").is_some())
        .collect();
    let mut frames = job_of(frames, server).frames;
    frames.sort_by_key(|f| f.index);
    let from_job: Vec<bool> = frames.iter().map(|f| f.cut.is_some()).collect();
    assert_eq!(from_render, from_job);
    from_job
}

#[test]
fn a_small_dataset_whose_store_is_built_renders_from_its_cut_here_and_through_a_server() {
    let (dir, file) = scratch_sample("sample.las", 60_000, 11);
    let cache = dir.path().join("cache");
    let here = |out: &str, extra: &[&str]| {
        let mut args = vec!["--cache-dir", path_arg(&cache)];
        args.extend(extra);
        render(&file, &dir.path().join(out), &args)
    };
    let server = ServeProcess::start(&dir.path().join("data"));
    let there = |out: &str, extra: &[&str]| {
        let mut args = vec!["--server", server.address.as_str()];
        args.extend(extra);
        render(&file, &dir.path().join(out), &args)
    };

    // Far fewer points than a store is built for: resident, here and there.
    assert_eq!(local_cuts(&here("local_resident", &[])), [false, false]);
    let resident = there("remote_resident", &[]);
    assert_eq!(server_cuts(&resident, &server), [false, false]);

    // The server builds the store for an export while its worker holds the resident cloud:
    // the worker asks again, and the next job is cut as the server decides.
    let dataset = job_of(&resident, &server).dataset_id;
    let exported = dir.path().join("export.copc.laz");
    pointfarm_ok(&[
        "dataset",
        "export",
        &dataset,
        "--copc",
        path_arg(&exported),
        "--server",
        &server.address,
    ]);
    let after_export = there("remote_after_export", &[]);
    assert_eq!(server_cuts(&after_export, &server), [true, true]);

    // A pixel error builds the store, here and on the server.
    assert_eq!(
        local_cuts(&here("local_lod", &["--lod-error", "0.5"])),
        [true, true]
    );
    let lod = there("remote_lod", &["--lod-error", "0.5"]);
    assert_eq!(server_cuts(&lod, &server), [true, true]);

    // Without a pixel error again: the built store is cut at the default error, both ways.
    let local_out = dir.path().join("local_stored");
    let said = output_text(&pointfarm_ok(&[
        "render",
        path_arg(&file),
        "--out",
        path_arg(&local_out),
        "--size=160x120",
        "--turntable",
        "2",
        "--cache-dir",
        path_arg(&cache),
    ]));
    assert!(said.contains("levels of detail from"), "{said}");
    let local = here("local_stored_json", &[]);
    assert_eq!(local_cuts(&local), [true, true], "{local:?}");
    let remote = there("remote_stored", &[]);
    assert_eq!(server_cuts(&remote, &server), [true, true], "{remote:?}");
    let image = |out: &str, frame: &str| {
        image::open(dir.path().join(out).join(frame))
            .expect("png")
            .to_rgba8()
    };
    for frame in FRAMES {
        assert!(
            image("local_stored", frame) == image("remote_stored", frame),
            "{frame} from the store's cut differs through the server\n{}",
            server.log()
        );
        assert!(
            image("local_stored", frame) == image("local_stored_json", frame),
            "{frame} differs between two renders of the same cut"
        );
    }
    // Each side's counts of the cut agree too.
    for (local, remote) in local.iter().zip(&remote) {
        assert_eq!(
            local["cut"]["pointsTotal"].as_u64(),
            Some(60_000),
            "{local}"
        );
        assert_eq!(
            remote["finished"]["cut"]["pointsTotal"], "60000",
            "{remote}"
        );
        assert_eq!(
            local["cut"]["pointsRendered"]
                .as_u64()
                .map(|p| p.to_string()),
            remote["finished"]["cut"]["pointsRendered"]
                .as_str()
                .map(str::to_owned),
            "{local}\n{remote}"
        );
    }
}

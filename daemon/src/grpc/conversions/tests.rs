//! The conversions' tests: one table of cases per message.

use pointfarm_render::raster::{FillSettings, Shading};
use pointfarm_render::request::{PointSize, RenderOptions};

use super::*;
use crate::describe::FileReport;
use crate::lease::{TaskDataset, TaskFile};
use crate::model::JobSpec;

fn valid() -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        request_id: "r1".into(),
        dataset_id: "ds-1".into(),
        camera_path: Some(pb::CameraPath::turntable(pb::Turntable::of_frames(4))),
        width: 64,
        height: 48,
        render: None,
        priority: 0,
        requirements: None,
        preview: false,
        after_job_ids: Vec::new(),
        name: "turntable of the hall".into(),
        labels: [("shot".to_string(), "010".to_string())].into(),
        video: None,
        output_url: String::new(),
        build_unseen: 0,
    }
}

#[test]
fn a_job_says_whether_the_files_its_frames_do_not_see_are_built() {
    use pointfarm_render::source::BuildUnseen;
    let asked = |value: pb::BuildUnseen| {
        let r = pb::SubmitJobRequest {
            build_unseen: value as i32,
            ..valid()
        };
        JobSpec::try_from(&r).expect("valid").build_unseen
    };
    assert_eq!(asked(pb::BuildUnseen::Unspecified), BuildUnseen::default());
    assert_eq!(asked(pb::BuildUnseen::After), BuildUnseen::After);
    assert_eq!(asked(pb::BuildUnseen::Never), BuildUnseen::Never);
    let unknown = pb::SubmitJobRequest {
        build_unseen: 7,
        ..valid()
    };
    assert_eq!(field_of(&unknown), "build_unseen");
    // A job's spec shows the choice, default or not, and submits it again as it was.
    for unseen in [BuildUnseen::After, BuildUnseen::Never] {
        let spec = JobSpec {
            build_unseen: unseen,
            ..JobSpec::try_from(&valid()).expect("valid")
        };
        let shown = pb::SubmitJobRequest::from(&spec);
        assert_ne!(shown.build_unseen, pb::BuildUnseen::Unspecified as i32);
        assert_eq!(JobSpec::try_from(&shown).expect("valid"), spec);
    }
}

fn field_of(r: &pb::SubmitJobRequest) -> String {
    match JobSpec::try_from(r) {
        Err(DaemonError::InvalidArgument { field, .. }) => field,
        other => panic!("expected InvalidArgument, got {other:?}"),
    }
}

fn vec3(x: f64, y: f64, z: f64) -> Option<pb::Vec3> {
    Some(pb::Vec3 { x, y, z })
}

fn kernel(kernel: u32) -> pb::FillOptions {
    pb::FillOptions { kernel }
}

#[test]
fn copc_chunks_convert_both_ways_and_bad_fields_are_named() {
    let path = pointfarm_render::testing::copc_file("simple.copc.laz");
    let opened = pointfarm_render::copc::open_copc(&path).expect("opens");
    let served = CopcServed {
        file_name: "simple.copc.laz".into(),
        decoder: opened.decoder,
        root_spacing: opened.info.spacing,
        elevation: opened.dataset.elevation(),
        point_spacing: opened.dataset.point_spacing(),
    };
    assert!(served.point_spacing.is_some());
    let message = copc_chunks_message(&served);
    let back = copc_chunks(&message).expect("valid");
    assert_eq!(back.file_name, served.file_name);
    assert_eq!(back.root_spacing, served.root_spacing);
    assert_eq!(back.elevation, served.elevation);
    assert_eq!(back.point_spacing, served.point_spacing);
    assert_eq!(back.decoder.scale(), served.decoder.scale());
    assert_eq!(back.decoder.laszip_vlr(), served.decoder.laszip_vlr());
    assert_eq!(copc_chunks_message(&back), message);

    type Damage = fn(&mut pb::CopcChunks);
    let bad: [(&str, Damage); 9] = [
        ("copc.file_name", |m| m.file_name.clear()),
        ("copc.point_format", |m| m.point_format = 300),
        ("copc.point_record_length", |m| {
            m.point_record_length = 70_000
        }),
        ("copc.scale", |m| m.scale = None),
        ("copc.root_spacing", |m| m.root_spacing = -1.0),
        ("copc.elevation", |m| {
            m.elevation = Some(pb::ElevationStretch {
                low: 2.0,
                high: 1.0,
            })
        }),
        ("copc.laszip_vlr", |m| m.laszip_vlr.truncate(10)),
        ("copc.point_spacing", |m| m.point_spacing = Some(f64::NAN)),
        ("copc.weight_offset", |m| m.weight_offset = Some(70_000)),
    ];
    for (field, damage) in bad {
        let mut damaged = message.clone();
        damage(&mut damaged);
        let error = copc_chunks(&damaged).err().expect("refused");
        assert!(error.to_string().contains(field), "{field}: {error}");
    }
}

/// A file pointfarm exported keeps each point's weight; a worker is told where.
#[test]
fn copc_chunks_carry_where_an_exported_file_keeps_its_weights() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = pointfarm_render::testing::exported_terrain(dir.path(), 20_000, 1_000).path;
    let opened = pointfarm_render::copc::open_copc(&path).expect("opens");
    let served = CopcServed {
        file_name: "terrain.copc.laz".into(),
        decoder: opened.decoder,
        root_spacing: opened.info.spacing,
        elevation: None,
        point_spacing: None,
    };
    let message = copc_chunks_message(&served);
    let at = served.decoder.weight_at().expect("a weight");
    assert_eq!(message.weight_offset, Some(u32::from(at)));
    let back = copc_chunks(&message).expect("valid");
    assert_eq!(back.decoder.weight_at(), Some(at));
    let mut beyond = message.clone();
    beyond.weight_offset = Some(message.point_record_length - 2);
    let error = copc_chunks(&beyond).err().expect("refused");
    assert!(error.to_string().contains("terrain.copc.laz"), "{error}");
}

#[test]
fn requirements_are_checked_sorted_and_convert_both_ways() {
    let mut r = valid();
    r.requirements = Some(pb::WorkerRequirements {
        tags: vec!["site-x".into(), "gpu:a100".into(), "site-x".into()],
        gpu: true,
    });
    let spec = JobSpec::try_from(&r).expect("valid");
    assert_eq!(
        spec.requirements,
        WorkerRequirements {
            tags: vec!["gpu:a100".into(), "site-x".into()],
            gpu: true
        }
    );
    let resubmitted = pb::SubmitJobRequest::from(&spec);
    assert_eq!(JobSpec::try_from(&resubmitted).expect("valid"), spec);
    assert_eq!(
        JobSpec::try_from(&valid()).expect("valid").requirements,
        WorkerRequirements::default()
    );
    r.requirements = Some(pb::WorkerRequirements {
        tags: vec!["two words".into()],
        gpu: false,
    });
    assert_eq!(field_of(&r), "requirements.tags");
}

#[test]
fn capabilities_convert_both_ways_and_bad_tags_are_refused() {
    let capabilities = WorkerCapabilities {
        adapter: AdapterKind::Software,
        adapter_name: "llvmpipe (LLVM 19)".into(),
        device_memory_bytes: None,
        int64_atomics: true,
        max_storage_binding_bytes: 1 << 31,
        max_buffer_bytes: 1 << 32,
        max_frame_side: Some(4096),
        tags: ["site-x".to_string()].into(),
        video_encoders: vec!["libx264".into(), "gif".into()],
    };
    let message = pb::WorkerCapabilities::from(&capabilities);
    assert_eq!(
        WorkerCapabilities::try_from(Some(&message)).expect("valid"),
        capabilities
    );
    assert_eq!(
        WorkerCapabilities::try_from(None).expect("none sent"),
        WorkerCapabilities::default()
    );
    let bad = pb::WorkerCapabilities {
        tags: vec![String::new()],
        ..message
    };
    let error = WorkerCapabilities::try_from(Some(&bad)).expect_err("an empty tag");
    assert!(error.to_string().contains("capabilities.tags"), "{error}");
}

#[test]
fn invalid_submissions_name_the_field() {
    assert!(JobSpec::try_from(&valid()).is_ok());
    let mut r = valid();
    r.camera_path = Some(pb::CameraPath::turntable(pb::Turntable::of_frames(0)));
    assert_eq!(field_of(&r), "camera_path.turntable.frames");
    let mut r = valid();
    r.camera_path = Some(pb::CameraPath::turntable(pb::Turntable {
        frames: 2,
        center: vec3(f64::NAN, 0.0, 0.0),
        ..Default::default()
    }));
    assert_eq!(field_of(&r), "camera_path.turntable.center");
    let mut r = valid();
    let key = |x: f64| pb::Keyframe {
        position: vec3(x, 0.0, 10.0),
        target: vec3(0.0, 0.0, 0.0),
        up: None,
        fov_y_deg: 50.0,
    };
    r.camera_path = Some(pb::CameraPath {
        path: Some(pb::camera_path::Path::Keyframes(pb::KeyframePath {
            keyframes: vec![key(1.0), key(f64::NAN)],
            frames: 3,
            interpolation: 0,
        })),
        lens: None,
    });
    assert_eq!(field_of(&r), "camera_path.keyframes.keyframes[1].position");
    let mut r = valid();
    r.width = 0;
    assert_eq!(field_of(&r), "width");
    let mut r = valid();
    r.camera_path = None;
    assert_eq!(field_of(&r), "camera_path");
    const PINTUS: i32 = pb::Shading::Pintus as i32;
    type Edit = fn(&mut pb::RenderOptions);
    let render_cases: [(Edit, &str); 8] = [
        (|o| o.point_size = 1000, "render.point_size"),
        (
            |o| (o.quality, o.depth_band) = (pb::Quality::High as i32, Some(f32::NAN)),
            "render.depth_band",
        ),
        (
            |o| (o.shading, o.pintus_levels) = (PINTUS, Some(0)),
            "render.pintus_levels",
        ),
        (
            |o| (o.shading, o.pintus_exponent) = (PINTUS, Some(f32::NAN)),
            "render.pintus_exponent",
        ),
        (|o| o.quality = 99, "render.quality"),
        (|o| o.fill = Some(kernel(1)), "render.fill.kernel"),
        (|o| o.fill = Some(kernel(4)), "render.fill.kernel"),
        (|o| o.fill = Some(kernel(11)), "render.fill.kernel"),
    ];
    type FilterEdit = fn(&mut pb::PointFilter);
    let filter_cases: [(FilterEdit, &str); 5] = [
        (|f| f.classes = vec![2, 256], "render.filter.classes"),
        (
            |f| f.return_numbers = vec![16],
            "render.filter.return_numbers",
        ),
        (
            |f| f.intensity = Some(pb::IntensityRange { min: 9, max: 3 }),
            "render.filter.intensity",
        ),
        (
            |f| {
                f.clip = Some(pb::ClipBox {
                    min: vec3(0.0, 0.0, f64::NAN),
                    max: vec3(1.0, 1.0, 1.0),
                })
            },
            "render.filter.clip",
        ),
        (
            |f| {
                f.clip = Some(pb::ClipBox {
                    min: vec3(0.0, 0.0, 0.0),
                    max: None,
                })
            },
            "render.filter.clip.max",
        ),
    ];
    let check = |options: pb::RenderOptions, field: &str| {
        let mut r = valid();
        r.render = Some(options);
        assert_eq!(field_of(&r), field);
    };
    for (edit, field) in render_cases {
        let mut options = pb::RenderOptions::default();
        edit(&mut options);
        check(options, field);
    }
    // A filter case sets that filter and nothing else.
    for (edit, field) in filter_cases {
        let mut filter = pb::PointFilter::default();
        edit(&mut filter);
        let options = pb::RenderOptions {
            filter: Some(filter),
            ..Default::default()
        };
        check(options, field);
    }
}

#[test]
fn fill_and_pintus_shading_convert_with_defaults() {
    let mut r = valid();
    r.render = Some(pb::RenderOptions {
        shading: pb::Shading::Pintus as i32,
        fill: Some(pb::FillOptions { kernel: 0 }),
        ..Default::default()
    });
    let render = JobSpec::try_from(&r).expect("valid").request.render;
    assert_eq!(render.fill, Some(FillSettings { kernel: 7 }));
    assert_eq!(render.shading, Shading::PINTUS);
    assert_eq!(
        JobSpec::try_from(&valid())
            .expect("valid")
            .request
            .render
            .fill,
        None
    );
}

#[test]
fn unset_options_are_the_requests_defaults() {
    let mut r = valid();
    r.render = Some(pb::RenderOptions::default());
    let render = JobSpec::try_from(&r).expect("valid").request.render;
    assert_eq!(render, RenderOptions::default());
    assert_eq!(render.shading, Shading::EDL);
    assert_eq!(render.point_size, PointSize::Adaptive);
    // Unset shading with parameters: the default kind with them; none asked for: none.
    r.render = Some(pb::RenderOptions {
        edl_strength: Some(2.0),
        ..Default::default()
    });
    let render = JobSpec::try_from(&r).expect("valid").request.render;
    assert!(matches!(render.shading, Shading::Edl { strength, .. } if strength == 2.0));
    r.render = Some(pb::RenderOptions {
        shading: pb::Shading::None as i32,
        ..Default::default()
    });
    let render = JobSpec::try_from(&r).expect("valid").request.render;
    assert_eq!(render.shading, Shading::None);
}

#[test]
fn tasks_carry_the_job_spec_unchanged_across_the_wire() {
    let mut r = valid();
    r.render = Some(pb::RenderOptions {
        point_size: 3,
        quality: pb::Quality::High as i32,
        depth_band: Some(0.02),
        shading: pb::Shading::Edl as i32,
        edl_strength: Some(2.0),
        edl_radius: Some(2.5),
        color_mode: pb::ColorMode::Fixed as i32,
        fixed_color: Some(pb::Color { rgba: 0x10203040 }),
        background: Some(pb::Color { rgba: 0x01020304 }),
        fill: Some(pb::FillOptions { kernel: 5 }),
        supersample: Some(2),
        filter: Some(pb::PointFilter {
            classes: vec![2, 6],
            return_numbers: vec![1],
            intensity: Some(pb::IntensityRange { min: 10, max: 900 }),
            clip: Some(pb::ClipBox {
                min: vec3(-5.0, -6.0, -7.0),
                max: vec3(5.0, 6.0, 7.5),
            }),
        }),
        ..Default::default()
    });
    let key = |x: f64| pb::Keyframe {
        position: vec3(x, 0.0, 10.0),
        target: vec3(0.0, 1.0, 0.0),
        up: None,
        fov_y_deg: 40.0,
    };
    let keyframes = pb::CameraPath {
        path: Some(pb::camera_path::Path::Keyframes(pb::KeyframePath {
            keyframes: vec![key(1.0), key(5.0), key(9.0)],
            frames: 7,
            interpolation: pb::Interpolation::Spline as i32,
        })),
        lens: None,
    };
    let turntable = pb::CameraPath::turntable(pb::Turntable {
        frames: 5,
        center: vec3(1e6, 2e6, 3.0),
        radius: Some(12.5),
        ..Default::default()
    });
    let still = pb::CameraPath {
        path: Some(pb::camera_path::Path::Still(pb::StillCamera {
            position: vec3(1.0, 2.0, 30.0),
            ..Default::default()
        })),
        lens: Some(pb::Lens {
            orthographic: true,
            ortho_height: Some(7.5),
            near: Some(0.5),
            far: Some(90.0),
        }),
    };
    for path in [keyframes, turntable, still] {
        r.camera_path = Some(path);
        let spec = JobSpec::try_from(&r).expect("valid");
        let filter = spec.request.render.filter;
        assert_eq!(filter.classes.map(|c| c.codes()), Some(vec![2, 6]));
        assert_eq!(filter.clip.map(|c| c.max), Some([5.0, 6.0, 7.5]));
        let task = FrameTask {
            lease: Lease {
                id: "lease-1".into(),
                job_id: "job-1".into(),
                index: 4,
                worker: "w".into(),
                embedded: false,
                expires_unix_ms: 1234,
                preview_version: Some(3),
            },
            lease_timeout: std::time::Duration::from_secs(30),
            dataset: TaskDataset {
                id: "ds-1".into(),
                sha256: "ab".repeat(32),
                size_bytes: 99,
                files: vec![
                    TaskFile {
                        sha256: "cd".repeat(32),
                        size_bytes: 40,
                    },
                    TaskFile {
                        sha256: "ef".repeat(32),
                        size_bytes: 59,
                    },
                ],
                remote: None,
                published: None,
            },
            request: spec.request.clone(),
            failed_attempts: 2,
        };
        let crosses_unchanged = |task: &FrameTask| {
            let received = frame_task(&frame_task_message(task), "w").expect("valid task");
            assert_eq!(&received, task);
        };
        let with_dataset = |dataset: TaskDataset| FrameTask {
            dataset,
            ..task.clone()
        };
        crosses_unchanged(&task);
        // A dataset by URL reaches the worker as its URL and version, with no file to fetch.
        let by_url = with_dataset(TaskDataset {
            files: Vec::new(),
            remote: Some(crate::model::RemoteSource {
                url: "s3://campaigns/team/site.copc.laz".into(),
                version: "\"e1\"".into(),
            }),
            ..task.dataset.clone()
        });
        crosses_unchanged(&by_url);
        let mut message = frame_task_message(&by_url);
        message.dataset.as_mut().expect("dataset").url = "s3://user:pw@b/k".into();
        let refused = frame_task(&message, "w")
            .expect_err("credentials")
            .to_string();
        assert!(
            refused.contains("credentials") && !refused.contains("pw@"),
            "{refused}"
        );
        // A published store reaches the worker as its prefix and versions; an object URL
        // or a URL with credentials in it is refused.
        let published = with_dataset(TaskDataset {
            published: Some(crate::lease::PublishedStore {
                url: format!("s3://stores/farm/{}/", "ab".repeat(32)),
                hierarchy_version: "\"h1\"".into(),
                payload_version: "\"p1\"".into(),
            }),
            ..task.dataset.clone()
        });
        crosses_unchanged(&published);
        for url in ["s3://stores/farm/nodes.bin", "s3://user:pw@stores/farm/"] {
            let mut message = frame_task_message(&published);
            let dataset = message.dataset.as_mut().expect("dataset");
            dataset.published_store.as_mut().expect("published").url = url.into();
            let refused = frame_task(&message, "w").expect_err(url).to_string();
            assert!(!refused.contains("pw@"), "{refused}");
        }
        // And the submission a client builds from the spec is the same spec.
        let resubmitted = pb::SubmitJobRequest::from(&spec);
        assert_eq!(JobSpec::try_from(&resubmitted).expect("valid"), spec);
    }
}

#[test]
fn color_ranges_and_ramps_convert_both_ways() {
    use pointfarm_render::color::{ColorMode, ColorRamp, ColorRange};
    let mut r = valid();
    r.render = Some(pb::RenderOptions {
        color_mode: pb::ColorMode::Elevation as i32,
        color_range: Some(pb::ColorRange {
            min: -12.5,
            max: 340.0,
        }),
        color_ramp: pb::ColorRamp::Inferno as i32,
        ..Default::default()
    });
    let spec = JobSpec::try_from(&r).expect("valid");
    let render = &spec.request.render;
    assert_eq!(render.color_mode, ColorMode::Elevation);
    assert_eq!(
        render.color_range,
        Some(ColorRange {
            min: -12.5,
            max: 340.0
        })
    );
    assert_eq!(render.color_ramp, Some(ColorRamp::Inferno));
    let resubmitted = pb::SubmitJobRequest::from(&spec);
    assert_eq!(JobSpec::try_from(&resubmitted).expect("valid"), spec);
    // Absent: the robust range and the mode's default ramp.
    r.render = Some(pb::RenderOptions {
        color_mode: pb::ColorMode::Intensity as i32,
        ..Default::default()
    });
    let spec = JobSpec::try_from(&r).expect("valid");
    assert_eq!(spec.request.render.color_range, None);
    assert_eq!(spec.request.render.color_ramp, None);
    if let Some(render) = r.render.as_mut() {
        render.color_range = Some(pb::ColorRange { min: 5.0, max: 1.0 });
    }
    assert_eq!(field_of(&r), "render.color_range");
}

#[test]
fn a_description_sums_the_readable_files_and_names_the_others() {
    let described = |min: [f64; 3], max: [f64; 3], points: u64| pb::FileDescription {
        path: "a.las".into(),
        points,
        bounds: Some(pb::Bounds {
            min: vec3(min[0], min[1], min[2]),
            max: vec3(max[0], max[1], max[2]),
        }),
        ..Default::default()
    };
    let unreadable = file_description(&FileReport {
        path: "gone.las".into(),
        outcome: Err(pointfarm_render::ingest::IngestError::Io {
            path: "gone.las".into(),
            error: std::io::Error::from(std::io::ErrorKind::NotFound),
        }),
        copc: None,
    });
    assert!(unreadable.error.contains("gone.las"), "{unreadable:?}");
    let files = vec![
        described([0.0, 0.0, 0.0], [1.0, 2.0, 3.0], 10),
        // Inverted bounds (an empty file's header) do not widen the union.
        described([9.0, 9.0, 9.0], [-9.0, -9.0, -9.0], 0),
        // Nor do an empty file's plausible ones: a file without points lies nowhere.
        described([100.0, 100.0, 100.0], [100.0, 100.0, 100.0], 0),
        described([-1.0, 0.5, 0.0], [0.5, 0.5, 4.0], 5),
        unreadable,
    ];
    let description = dataset_description("ds", files);
    let summary = description.summary.expect("summary");
    assert_eq!(
        (summary.files, summary.unreadable, summary.points),
        (5, 1, 15)
    );
    let bounds = summary.bounds.expect("bounds");
    assert_eq!(bounds.min, vec3(-1.0, 0.0, 0.0));
    assert_eq!(bounds.max, vec3(1.0, 2.0, 4.0));
}

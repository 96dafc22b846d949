use super::*;

fn run(daemon: &str, run: u32, frames_per_s: f64, submit: f64, lease: f64) -> ServiceLoadRun {
    ServiceLoadRun {
        daemon: daemon.into(),
        run,
        load_average: Some(1.5),
        adapter: "llvmpipe".into(),
        jobs: 4,
        frames: 8,
        wall_s: 8.0 / frames_per_s,
        frames_per_s,
        submit_median_ms: submit,
        submit_p95_ms: submit * 2.0,
        get_job_calls: 10,
        get_job_median_ms: submit,
        leases: 5,
        lease_median_ms: lease,
        lease_p95_ms: lease * 2.0,
        release_median_ms: lease,
        stopped_cleanly: true,
    }
}

#[test]
fn binaries_are_summarised_against_the_first() {
    let runs = [
        run("before", 1, 10.0, 40.0, 40.0),
        run("after", 1, 100.0, 1.0, 2.0),
        run("before", 2, 20.0, 50.0, 44.0),
        run("after", 2, 140.0, 2.0, 2.0),
    ];
    let binaries = [PathBuf::from("before"), PathBuf::from("after")];
    let summaries = summarise(&binaries, &runs);
    assert_eq!(summaries.len(), 2);
    let (before, after) = (&summaries[0], &summaries[1]);
    assert_eq!((before.runs, before.frames_per_s), (2, 15.0));
    assert_eq!(before.frames_per_s_over_baseline, 1.0);
    assert_eq!(after.frames_per_s, 120.0);
    assert_eq!(after.frames_per_s_over_baseline, 8.0);
    assert_eq!(after.submit_speedup, 45.0 / 1.5);
    assert_eq!(after.lease_speedup, 21.0);

    let result = ServiceLoadResult {
        load: ServiceLoad {
            jobs: 4,
            frames_per_job: 2,
            clients: 2,
            leases: 5,
            width: 64,
            height: 48,
        },
        dataset_points: DATASET_POINTS,
        runs: runs.to_vec(),
        summaries,
    };
    let table = markdown(&result);
    assert!(
        table.contains("| after | 2 | 1.50 | llvmpipe | 140.0 | 2.00 |"),
        "{table}"
    );
    assert!(
        table.contains("| after | 2 | 120.0 | 8.00x | 1.50 | 30.00x |"),
        "{table}"
    );
}

#[test]
fn nothing_to_run_is_refused_before_any_work() {
    let mut options = ServiceLoadOptions::new(PathBuf::from("pointfarm"));
    options.load.clients = 0;
    let refused = measure(&options, &mut |_| {}).expect_err("no clients");
    assert!(refused.to_string().contains("clients"), "{refused}");
}

//! A state database that was truncated or bit-flipped while the daemon was down: the daemon
//! refuses to start and says what was lost, and with `recover_state` starts on what is left
//! and says so; never a quiet partial start. Real sled files, real jobs submitted over gRPC.

use std::path::Path;

use pointfarm_daemon::service::{Daemon, DaemonConfig};
use pointfarm_tests::service::{scratch_sample, submit, turntable_job, upload};

/// A daemon's data folder holding one dataset and `jobs` queued jobs, the daemon stopped.
async fn state_with_jobs(data_dir: &Path, jobs: usize) {
    let daemon = Daemon::open(DaemonConfig::new(data_dir.to_path_buf())).expect("open");
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let address = listener.local_addr().expect("address").to_string();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(pointfarm_daemon::server::serve(
        daemon,
        None,
        listener,
        pointfarm_daemon::server::ServeOptions::default(),
        async {
            let _ = stopped.await;
        },
    ));
    let (mut datasets, mut job_service) = pointfarm_tests::service::clients(&address).await;
    let (_scratch, file) = scratch_sample("s.las", 500, 1);
    let dataset = upload(&mut datasets, "s.las", &std::fs::read(file).expect("read")).await;
    for i in 0..jobs {
        submit(
            &mut job_service,
            turntable_job(&format!("r{i}"), &dataset.id, 1, 8, 8),
        )
        .await;
    }
    let _ = stop.send(());
    server.await.expect("join").expect("serve");
}

/// Opens the daemon on `data_dir`, waiting for the previous one's last threads to let go of
/// the database.
fn open(data_dir: &Path, recover: bool) -> Result<std::sync::Arc<Daemon>, String> {
    let mut config = DaemonConfig::new(data_dir.to_path_buf());
    config.recover_state = recover;
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    loop {
        match Daemon::open(config.clone()) {
            Err(e) if e.to_string().contains("in use") && std::time::Instant::now() < deadline => {
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            opened => return opened.map_err(|e| e.to_string()),
        }
    }
}

fn job_count(daemon: &Daemon) -> usize {
    daemon.list_jobs(None, 1000, "").expect("list").items.len()
}

/// The database's largest file (sled's log).
fn log_file(data_dir: &Path) -> std::path::PathBuf {
    std::fs::read_dir(data_dir.join("state.sled"))
        .expect("state folder")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_file())
        .max_by_key(|p| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0))
        .expect("a database file")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_intact_state_opens_with_every_job() {
    let dir = tempfile::tempdir().expect("tempdir");
    state_with_jobs(dir.path(), 30).await;
    let daemon = open(dir.path(), false).expect("an intact state opens");
    assert_eq!(job_count(&daemon), 30);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_truncated_state_is_refused_with_what_it_lost_and_recovered_on_request() {
    let dir = tempfile::tempdir().expect("tempdir");
    state_with_jobs(dir.path(), 30).await;
    let log = log_file(dir.path());
    let length = std::fs::metadata(&log).expect("log").len();
    let file = std::fs::OpenOptions::new()
        .write(true)
        .open(&log)
        .expect("open log");
    file.set_len(length / 2).expect("truncate");
    drop(file);

    let Err(refused) = open(dir.path(), false) else {
        panic!("a truncated state must not open quietly");
    };
    assert!(
        refused.contains("damaged") || refused.contains("lost"),
        "{refused}"
    );
    let daemon = open(dir.path(), true).expect("recovering opens");
    let kept = job_count(&daemon);
    assert!(kept < 30, "{kept} of 30 jobs after truncation");
    drop(daemon);
    // Recovered once, the state is whole again by its own account.
    let daemon = open(dir.path(), false).expect("a recovered state opens");
    assert_eq!(job_count(&daemon), kept);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bit_flipped_state_is_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    state_with_jobs(dir.path(), 30).await;
    let log = log_file(dir.path());
    let mut bytes = std::fs::read(&log).expect("read log");
    let middle = bytes.len() / 2;
    for byte in &mut bytes[middle..middle + 64] {
        *byte ^= 0x5a;
    }
    std::fs::write(&log, bytes).expect("write log");
    match open(dir.path(), false) {
        Err(message) => assert!(!message.is_empty()),
        // sled may find the flipped bytes in a part of its log that holds nothing live.
        Ok(daemon) => assert_eq!(job_count(&daemon), 30, "a quiet partial start"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_of_a_job_the_state_lacks_are_a_loss_even_without_a_manifest() {
    let dir = tempfile::tempdir().expect("tempdir");
    state_with_jobs(dir.path(), 3).await;
    std::fs::remove_file(dir.path().join("state.manifest.json")).expect("no manifest");
    let frames = dir.path().join("jobs").join("job-000000099999");
    std::fs::create_dir_all(&frames).expect("frames folder");
    std::fs::write(frames.join("frame_00000.png"), b"png").expect("frame");
    let Err(refused) = open(dir.path(), false) else {
        panic!("frames without their job must not pass unnoticed");
    };
    assert!(refused.contains("lost 1 jobs"), "{refused}");
    assert!(refused.contains("job-000000099999"), "{refused}");
    assert_eq!(
        job_count(&open(dir.path(), true).expect("recovering opens")),
        3
    );
}

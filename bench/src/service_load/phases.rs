//! The two phases of a run: many clients' submissions against a daemon with its worker,
//! and a worker's leases against a daemon without one.

use super::*;

/// A turntable job as `pointfarm render --server` submits one: every render option spelled out.
fn job_request(
    request_id: String,
    dataset_id: &str,
    options: &ServiceLoadOptions,
) -> pb::SubmitJobRequest {
    let load = &options.load;
    let spec = JobSpec::new(
        request_id,
        dataset_id.into(),
        RenderRequest::turntable(load.width, load.height, load.frames_per_job),
    );
    pb::SubmitJobRequest::from(&spec)
}

fn ms_since(started: Instant) -> f64 {
    started.elapsed().as_secs_f64() * 1e3
}

/// What the load phase measured.
pub(super) struct LoadFigures {
    pub(super) frames: u64,
    pub(super) wall: Duration,
    pub(super) submit_ms: Vec<f64>,
    pub(super) get_job_ms: Vec<f64>,
}

/// What one client measured.
struct ClientFigures {
    frames: u64,
    finished: Instant,
    submit_ms: Vec<f64>,
    get_job_ms: Vec<f64>,
}

pub(super) async fn load_phase(
    endpoint: &ServerEndpoint,
    dataset_id: &str,
    options: &ServiceLoadOptions,
) -> Result<LoadFigures, String> {
    // Connected before the clock starts: a connection's set-up is not the service's work.
    let mut clients = Vec::new();
    for client in 0..options.load.clients.min(options.load.jobs) {
        let jobs: Vec<String> = (client..options.load.jobs)
            .step_by(options.load.clients as usize)
            .map(|job| format!("service-load-{job}"))
            .collect();
        clients.push((JobServiceClient::new(connect(endpoint).await?), jobs));
    }
    let started = Instant::now();
    let tasks: Vec<_> = clients
        .into_iter()
        .map(|(client, jobs)| {
            let requests = jobs
                .into_iter()
                .map(|id| job_request(id, dataset_id, options))
                .collect();
            tokio::spawn(client_load(client, requests))
        })
        .collect();
    let mut figures = LoadFigures {
        frames: 0,
        wall: Duration::ZERO,
        submit_ms: Vec::new(),
        get_job_ms: Vec::new(),
    };
    for task in tasks {
        let client = task.await.map_err(|e| format!("a client task: {e}"))??;
        figures.frames += client.frames;
        figures.wall = figures.wall.max(client.finished - started);
        figures.submit_ms.extend(client.submit_ms);
        figures.get_job_ms.extend(client.get_job_ms);
    }
    Ok(figures)
}

/// Submits `requests` one after another, then polls them until each has succeeded.
async fn client_load(
    mut jobs: JobServiceClient<Channel>,
    requests: Vec<pb::SubmitJobRequest>,
) -> Result<ClientFigures, String> {
    let mut submit_ms = Vec::with_capacity(requests.len());
    let mut unfinished = Vec::with_capacity(requests.len());
    for request in requests {
        let started = Instant::now();
        let job = jobs
            .submit_job(request)
            .await
            .map_err(call_failed("SubmitJob"))?;
        submit_ms.push(ms_since(started));
        unfinished.push(job.into_inner().id);
    }
    let (mut frames, mut finished) = (0, Instant::now());
    let mut get_job_ms = Vec::new();
    while !unfinished.is_empty() {
        let mut waiting = Vec::with_capacity(unfinished.len());
        for id in unfinished {
            let started = Instant::now();
            let job = jobs
                .get_job(pb::GetJobRequest { id: id.clone() })
                .await
                .map_err(call_failed("GetJob"))?
                .into_inner();
            get_job_ms.push(ms_since(started));
            match job.state() {
                pb::JobState::Succeeded => {
                    frames += u64::from(job.frames_done);
                    finished = Instant::now();
                }
                pb::JobState::Failed | pb::JobState::Cancelled => {
                    return Err(format!(
                        "job {id} ended {}: {}",
                        job.state().as_str_name(),
                        job.error
                    ))
                }
                _ => waiting.push(id),
            }
        }
        unfinished = waiting;
        if !unfinished.is_empty() {
            tokio::time::sleep(POLL_INTERVAL).await;
        }
    }
    Ok(ClientFigures {
        frames,
        finished,
        submit_ms,
        get_job_ms,
    })
}

/// What the lease phase measured.
pub(super) struct LeaseFigures {
    pub(super) lease_ms: Vec<f64>,
    pub(super) release_ms: Vec<f64>,
}

/// The capabilities the benchmark leases with: a software adapter with no frame limit.
fn capabilities() -> pb::WorkerCapabilities {
    pb::WorkerCapabilities {
        adapter_kind: pb::AdapterKind::Software.into(),
        adapter_name: "pointfarm bench (renders nothing)".into(),
        ..Default::default()
    }
}

pub(super) async fn lease_phase(
    endpoint: &ServerEndpoint,
    dataset_id: &str,
    options: &ServiceLoadOptions,
) -> Result<LeaseFigures, String> {
    let mut jobs = JobServiceClient::new(connect(endpoint).await?);
    for job in 0..LEASE_PHASE_JOBS {
        let request = job_request(format!("lease-{job}"), dataset_id, options);
        jobs.submit_job(request)
            .await
            .map_err(call_failed("SubmitJob"))?;
    }
    // A connection of its own, as a worker process has.
    let mut worker = WorkerServiceClient::new(connect(endpoint).await?);
    let request = pb::LeaseFrameRequest {
        worker_name: WORKER_NAME.into(),
        wait_ms: 0,
        capabilities: Some(capabilities()),
    };
    let mut figures = LeaseFigures {
        lease_ms: Vec::with_capacity(options.load.leases as usize),
        release_ms: Vec::with_capacity(options.load.leases as usize),
    };
    for lease in 0..WARM_LEASES + options.load.leases as usize {
        let started = Instant::now();
        let task = worker
            .lease_frame(request.clone())
            .await
            .map_err(call_failed("LeaseFrame"))?
            .into_inner()
            .task
            .ok_or("LeaseFrame: no frame to lease with frames queued")?;
        let lease_ms = ms_since(started);
        let started = Instant::now();
        worker
            .release_frame(pb::ReleaseFrameRequest {
                lease_id: task.lease_id,
            })
            .await
            .map_err(call_failed("ReleaseFrame"))?;
        if lease >= WARM_LEASES {
            figures.lease_ms.push(lease_ms);
            figures.release_ms.push(ms_since(started));
        }
    }
    Ok(figures)
}

//! `pointfarm render --server URL`: the request of the local render, carried out by a daemon
//! (or refused, naming the option the service does not have).
//! Uploads the file if the server lacks it, submits, follows with a progress bar and
//! downloads the frames; with `--detach`, returns once the job is submitted, its id printed. A job with previews has each preview downloaded as it comes, where
//! its final frame will be written over it. With `--json`, one object per frame on stdout:
//! its file and the frame as the API reports it.

use anyhow::{bail, Context, Result};
use pointfarm_daemon::capabilities::{checked_tags, WorkerRequirements};
use pointfarm_daemon::job_control::{check_labels, check_name};
use pointfarm_daemon::model::JobSpec;
use pointfarm_proto::v1 as pb;
use pointfarm_render::ingest::dataset_files;
use pointfarm_render::raster::AtomicsMode;
use pointfarm_render::request::RenderRequest;

use crate::output::Reporter;
use crate::remote::{answer, require_success, timings_line, Client};
use crate::render_args::RenderArgs;
use crate::render_json::ServerFrameJson;
use crate::render_outputs::{Outputs, VideoPlan};

/// Refuses what the service cannot do, so that no option is dropped on the way.
fn refuse_local_only_options(args: &RenderArgs, request: &RenderRequest) -> Result<()> {
    if request.render.depth {
        bail!(
            "--depth is not available through a server: the service returns color frames \
             only; render locally for depth images"
        );
    }
    if let Some(flag) = args.cache_flag() {
        bail!(
            "{flag} sizes this machine's node caches; a server's workers have their own \
             (`pointfarm worker --memory-budget`); render locally to use it"
        );
    }
    let coloring = request.render.coloring();
    if args.legend.is_some() && coloring.mode.is_ramped() && coloring.range.is_none() {
        bail!(
            "--legend through a server needs --range with --color {}: the server's workers \
             choose the data's own range; give one, or render locally",
            coloring.mode.name()
        );
    }
    if args.atomics() != AtomicsMode::Auto {
        bail!(
            "--atomics chooses this machine's point pass and is not available through a \
             server (its workers choose theirs); render locally to force the 32-bit path"
        );
    }
    Ok(())
}

/// The job `request` describes, its frames going to `outputs`.
fn submission(
    args: &RenderArgs,
    request: &RenderRequest,
    outputs: &Outputs,
    dataset_id: String,
) -> Result<pb::SubmitJobRequest> {
    let nonce = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    let spec = JobSpec {
        request_id: format!("cli-{}-{nonce}", std::process::id()),
        dataset_id,
        request: request.clone(),
        priority: args.priority,
        requirements: requirements(args)?,
        preview: args.preview,
        after: args.after.clone(),
        name: args.name.clone().unwrap_or_default(),
        labels: args.labels.iter().cloned().collect(),
        video: outputs.video.as_ref().map(VideoPlan::settings),
        output_url: args.output_url.clone(),
        build_unseen: args.build_unseen,
    };
    check_name("--name", &spec.name)?;
    check_labels("--label", &spec.labels)?;
    Ok(pb::SubmitJobRequest::from(&spec))
}

/// What the job asks of its workers (`--require-tag`, `--require-gpu`), checked as the server
/// checks it.
fn requirements(args: &RenderArgs) -> Result<WorkerRequirements> {
    let tags = checked_tags(
        "--require-tag",
        args.require_tags.iter().map(String::as_str),
    )?;
    Ok(WorkerRequirements {
        tags: tags.into_iter().collect(),
        gpu: args.require_gpu,
    })
}

pub fn run(
    server: &str,
    args: &RenderArgs,
    request: &RenderRequest,
    outputs: &Outputs,
) -> Result<()> {
    refuse_local_only_options(args, request)?;
    let submitted = |dataset_id| submission(args, request, outputs, dataset_id);
    // Bad tags are refused before anything is uploaded.
    submitted(String::new())?;
    let coloring = request.render.coloring();
    if let Some(line) = outputs.write_legend(coloring, || coloring.range)? {
        outln!("{line}");
    }
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    // Detached, stdout carries the job's id alone, for scripts to read.
    let reporter = Reporter::new(args.json || args.detach);
    runtime.block_on(async {
        let mut client = Client::connect(server, &args.credentials).await?;
        let dataset = match &args.dataset {
            Some(id) => answer(
                client
                    .datasets
                    .get_dataset(pb::GetDatasetRequest { id: id.clone() })
                    .await,
            )?,
            None => client.ensure_dataset(&dataset_files(&args.inputs)?).await?,
        };
        let file_count = dataset.files.len().max(1);
        let found = format!(
            "dataset {} of {file_count} file{} on {server}",
            dataset.id,
            if file_count == 1 { "" } else { "s" }
        );
        match args.dataset {
            Some(_) => reporter.say(found),
            None => reporter.say(format_args!("{}: {found}", args.inputs_label())),
        }
        let job = client
            .jobs
            .submit_job(submitted(dataset.id)?)
            .await
            .map_err(crate::remote::status_error)?
            .into_inner();
        reporter.say(format_args!(
            "job {} submitted: {} frame{}",
            job.id,
            job.frames_total,
            crate::source_words::plural(job.frames_total as usize)
        ));
        if args.detach {
            if args.json {
                outln!("{}", crate::admin_json::json_line(&job)?);
            } else {
                outln!("{}", job.id);
            }
            return Ok(());
        }
        // A job that the connected workers all refuse waits for another: say why, once.
        if let Ok(shown) = client
            .jobs
            .get_job(pb::GetJobRequest { id: job.id.clone() })
            .await
        {
            let shown = shown.into_inner();
            if !shown.waiting_reason.is_empty() && !shown.refusals.is_empty() {
                reporter.say(format_args!("waiting: {}", shown.waiting_reason));
            }
        }
        let previews = args
            .preview
            .then(|| PreviewFetcher::start(&client, &job, reporter, outputs));
        let finished = client
            .follow(&job.id, args.json, |frame| {
                if let Some(previews) = &previews {
                    previews.fetch(frame);
                }
            })
            .await;
        // Every preview is in place before a final frame is written over it.
        if let Some(previews) = previews {
            previews.finish().await?;
        }
        let finished = finished?;
        require_success(&finished)?;
        // Fetched beside the frames' folder (one file system, so placing them is a rename),
        // then named and converted as --out says.
        let files = &outputs.files;
        files.create_dir()?;
        let temp = tempdir_in(files.dir())?;
        let fetched = client.fetch_frames(&job.id, 0, &temp).await;
        let placed = fetched.and_then(|fetched| {
            fetched
                .iter()
                .map(|(index, png)| Ok((*index, files.place_png(png, *index)?)))
                .collect::<Result<Vec<_>>>()
        });
        let _ = std::fs::remove_dir_all(&temp);
        let placed = placed?;
        let written: Vec<_> = placed.iter().map(|(_, path)| path.clone()).collect();
        let details = client
            .jobs
            .get_job(pb::GetJobRequest { id: job.id.clone() })
            .await
            .map_err(crate::remote::status_error)?
            .into_inner();
        if args.json {
            for (index, path) in &placed {
                let frame = ServerFrameJson::new(*index, path, &details);
                outln!("{}", crate::admin_json::json_line(&frame)?);
            }
        }
        let previewed = args.preview;
        let what = if previewed { "final frames" } else { "frames" };
        match written.as_slice() {
            [] => bail!("the server returned no frame"),
            [one] if previewed => reporter.say(format_args!("final frame: {}", one.display())),
            [one] => reporter.say(one.display()),
            many => reporter.say(format_args!(
                "{} {what} in {}",
                many.len(),
                files.dir().display()
            )),
        }
        if let Some(video) = &outputs.video {
            let bytes = crate::jobs_video::download(&mut client, &job.id, video.path()).await?;
            reporter.say(format_args!(
                "video: {} ({bytes} bytes, made on the server)",
                video.path().display()
            ));
        }
        if let Some(first) = details.frames.first() {
            reporter.say(format_args!(
                "frame {} on the server: {}",
                first.index,
                timings_line(&first.timings)
            ));
        }
        Ok(())
    })
}

/// A fresh folder in `parent` (same file system, so a rename can move frames into place).
fn tempdir_in(parent: &std::path::Path) -> Result<std::path::PathBuf> {
    let dir = parent.join(format!(".pointfarm-fetch-{}", std::process::id()));
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    Ok(dir)
}

/// Downloads a preview job's preview frames as the server reports them (each frame's latest
/// image) into the frames' files, where the final frames replace them, each reported as a
/// local preview is.
struct PreviewFetcher {
    frames: tokio::sync::mpsc::UnboundedSender<pb::FrameFinished>,
    task: tokio::task::JoinHandle<Result<()>>,
}

impl PreviewFetcher {
    fn start(client: &Client, job: &pb::Job, reporter: Reporter, outputs: &Outputs) -> Self {
        let frames_total = job.frames_total;
        let (frames, mut reported) = tokio::sync::mpsc::unbounded_channel::<pb::FrameFinished>();
        let mut jobs = client.jobs.clone();
        let job_id = job.id.clone();
        let files = outputs.files.clone();
        let task = tokio::spawn(async move {
            files.create_dir()?;
            let temp = tempdir_in(files.dir())?;
            let mut placed = std::collections::HashSet::new();
            let mut result = Ok(());
            while let Some(frame) = reported.recv().await {
                let png = temp.join(format!("preview_{:05}.png", frame.index));
                let fetched = crate::remote::fetch_frame(&mut jobs, &job_id, frame.index, &png)
                    .await
                    .and_then(|found| {
                        found
                            .then(|| files.place_png(&png, frame.index))
                            .transpose()
                    });
                let path = match fetched {
                    Ok(Some(path)) => path,
                    // The server has no image of the frame (any more): nothing to show.
                    Ok(None) => continue,
                    Err(e) => {
                        result = Err(e);
                        break;
                    }
                };
                if reporter.is_json() {
                    let line = ServerFrameJson::of_frame(&path, &job_id, &frame);
                    match crate::admin_json::json_line(&line) {
                        Ok(line) => outln!("{line}"),
                        Err(e) => {
                            result = Err(e);
                            break;
                        }
                    }
                }
                if placed.insert(frame.index) && placed.len() == frames_total as usize {
                    reporter.say(format_args!(
                        "previews: {frames_total} frame{} in {}; the final frames replace them \
                         as the server renders them",
                        if frames_total == 1 { "" } else { "s" },
                        files.dir().display()
                    ));
                }
            }
            let _ = std::fs::remove_dir_all(&temp);
            result
        });
        Self { frames, task }
    }

    /// Fetches `frame` when it is a preview.
    fn fetch(&self, frame: &pb::FrameFinished) {
        if frame.preview {
            // Sending fails only once the fetcher stopped on an error, which `finish` returns.
            let _ = self.frames.send(frame.clone());
        }
    }

    /// Waits for the previews reported so far to be in place.
    async fn finish(self) -> Result<()> {
        drop(self.frames);
        self.task.await.context("the preview download stopped")?
    }
}

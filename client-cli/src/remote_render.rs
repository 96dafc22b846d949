//! `pointfarm render --server URL`: the request of the local render, carried out by a daemon
//! (or refused, naming the option the service does not have).
//! Uploads the file if the server lacks it, submits, follows with a progress bar and
//! downloads the frames. With `--json`, one object per frame on stdout: its file and the frame
//! as the API reports it.

use anyhow::{bail, Context, Result};
use pointfarm_daemon::capabilities::{checked_tags, WorkerRequirements};
use pointfarm_daemon::model::JobSpec;
use pointfarm_proto::v1 as pb;
use pointfarm_render::ingest::dataset_files;
use pointfarm_render::legend::Legend;
use pointfarm_render::raster::AtomicsMode;
use pointfarm_render::request::RenderRequest;

use crate::remote::{require_success, timings_line, Client};
use crate::render_args::RenderArgs;
use crate::render_json::ServerFrameJson;
use crate::render_outputs::{write_legend, Outputs};

/// Refuses what the service cannot do, so that no option is dropped on the way.
fn refuse_local_only_options(args: &RenderArgs, request: &RenderRequest) -> Result<()> {
    if request.render.depth {
        bail!(
            "--depth is not available through a server: the service returns colour frames \
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

/// The job `request` describes.
fn submission(
    args: &RenderArgs,
    request: &RenderRequest,
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
    };
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
    let submitted = |dataset_id| submission(args, request, dataset_id);
    // Bad tags are refused before anything is uploaded.
    submitted(String::new())?;
    if let Some(path) = &outputs.legend {
        let coloring = request.render.coloring();
        outln!(
            "{}",
            write_legend(path, Legend::of(coloring, coloring.range))?
        );
    }
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    let say = |line: String| crate::output::say(args.json, line);
    runtime.block_on(async {
        let files = dataset_files(&args.inputs)?;
        let mut client = Client::connect(server, &args.credentials).await?;
        let dataset = client.ensure_dataset(&files).await?;
        say(format!(
            "{}: dataset {} of {} file{} on {server}",
            args.inputs_label(),
            dataset.id,
            files.len(),
            if files.len() == 1 { "" } else { "s" }
        ));
        let job = client
            .jobs
            .submit_job(submitted(dataset.id)?)
            .await
            .map_err(crate::remote::status_error)?
            .into_inner();
        say(format!(
            "job {} submitted: {} frames",
            job.id, job.frames_total
        ));
        // A job that the connected workers all refuse waits for another: say why, once.
        if let Ok(shown) = client
            .jobs
            .get_job(pb::GetJobRequest { id: job.id.clone() })
            .await
        {
            let shown = shown.into_inner();
            if !shown.waiting_reason.is_empty() && !shown.refusals.is_empty() {
                say(format!("waiting: {}", shown.waiting_reason));
            }
        }
        let finished = client.follow(&job.id, args.json).await?;
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
            [one] if previewed => say(format!("final frame: {}", one.display())),
            [one] => say(one.display().to_string()),
            many => say(format!(
                "{} {what} in {}",
                many.len(),
                files.dir().display()
            )),
        }
        if let Some(video) = &outputs.video {
            video.assemble(&written)?;
            say(format!("video: {}", video.path().display()));
        }
        if let Some(first) = details.frames.first() {
            say(format!(
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

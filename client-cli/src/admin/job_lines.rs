//! What the `jobs` commands print of a job beyond its table row: its previews, its cuts,
//! its stage timings, its workers and why it waits.

use pointfarm_proto::v1 as pb;

use crate::admin_json::StageStatistics;

/// One line on a job's preview frames (drawn from the dataset's chunk starts while the
/// server builds its store), which final frames replace: how many, and how complete.
pub(super) fn preview_summary(job: &pb::Job) -> Option<String> {
    let previews: Vec<&pb::FrameFinished> = job.frames.iter().filter(|f| f.preview).collect();
    let first = previews.first()?;
    let (low, high) = previews
        .iter()
        .fold((first.completeness, first.completeness), |(l, h), f| {
            (l.min(f.completeness), h.max(f.completeness))
        });
    Some(format!(
        "previews: {} of {} frames, {:.3}% to {:.3}% of the points; final: {}/{}",
        previews.len(),
        job.frames_total,
        low * 100.0,
        high * 100.0,
        job.frames_done,
        job.frames_total
    ))
}

/// One line on the frames rendered from levels of detail: the median cut and what was read.
pub(super) fn cut_summary(frames: &[pb::FrameFinished]) -> Option<String> {
    let cuts: Vec<&pb::FrameCut> = frames.iter().filter_map(|f| f.cut.as_ref()).collect();
    let first = cuts.first()?;
    let median = |value: fn(&pb::FrameCut) -> u64| {
        let mut values: Vec<u64> = cuts.iter().map(|c| value(c)).collect();
        values.sort_unstable();
        values[values.len() / 2]
    };
    let sum = |value: fn(&pb::FrameCut) -> u64| cuts.iter().map(|c| value(c)).sum::<u64>();
    Some(format!(
        "levels of detail, {} frames: median cut {} nodes, {} of {} points; {} nodes read ({:.1} MiB, {:.1} MiB ahead), {} host and {} GPU cache hits{}",
        cuts.len(), median(|c| c.nodes), median(|c| c.points_rendered), first.points_total,
        sum(|c| c.nodes_read), sum(|c| c.bytes_read) as f64 / f64::from(1 << 20),
        sum(|c| c.read_ahead_bytes) as f64 / f64::from(1 << 20), sum(|c| c.host_hits), sum(|c| c.gpu_hits),
        if cuts.iter().any(|c| c.limited_by_budget) { "; some cuts bounded by the GPU budget" } else { "" },
    ) + &object_reads(&cuts))
}

/// What frames of a dataset by URL read of its object: fetched, and from the workers' caches.
fn object_reads(cuts: &[&pb::FrameCut]) -> String {
    let sum = |value: fn(&pb::FrameCut) -> u64| cuts.iter().map(|c| value(c)).sum::<u64>();
    let (requests, cached) = (sum(|c| c.object_requests), sum(|c| c.range_cache_bytes));
    if requests == 0 && cached == 0 {
        return String::new();
    }
    format!(
        "; by URL {requests} requests ({:.1} MiB), {:.1} MiB from the workers' range caches",
        sum(|c| c.object_bytes) as f64 / f64::from(1 << 20),
        cached as f64 / f64::from(1 << 20),
    )
}

/// Median and 95th percentile of each stage over a job's frames, in stage order.
pub(super) fn stage_statistics(frames: &[pb::FrameFinished]) -> Vec<StageStatistics> {
    let mut stages: Vec<(String, Vec<f64>)> = Vec::new();
    for timing in frames.iter().flat_map(|f| &f.timings) {
        match stages.iter_mut().find(|(name, _)| *name == timing.stage) {
            Some((_, values)) => values.push(timing.ms),
            None => stages.push((timing.stage.clone(), vec![timing.ms])),
        }
    }
    stages
        .into_iter()
        .map(|(name, mut values)| {
            values.sort_by(f64::total_cmp);
            let at = |q: f64| values[((values.len() - 1) as f64 * q).round() as usize];
            StageStatistics {
                stage: name,
                median_ms: at(0.5),
                p95_ms: at(0.95),
            }
        })
        .collect()
}

/// A worker's name as the tables show it, marked when it is the daemon's embedded worker.
/// `jobs workers`' table: a header, then each worker's name, adapter kind, largest frame
/// side, adapter name and tags.
pub(super) fn worker_table(workers: &[pb::ConnectedWorker]) -> Vec<String> {
    let header = format!(
        "{:<24} {:<9} {:>10}  {:<32} tags",
        "worker", "adapter", "max side", "name"
    );
    let rows = workers.iter().map(|w| {
        let caps = w.capabilities.clone().unwrap_or_default();
        let kind = match pb::AdapterKind::try_from(caps.adapter_kind) {
            Ok(pb::AdapterKind::Hardware) => "GPU",
            Ok(pb::AdapterKind::Software) => "software",
            _ => "unknown",
        };
        let side = if caps.max_frame_side == 0 {
            "any".to_string()
        } else {
            caps.max_frame_side.to_string()
        };
        let name = worker_label(&w.worker_name, w.embedded);
        format!(
            "{name:<24} {kind:<9} {side:>10}  {:<32} {}",
            caps.adapter_name,
            caps.tags.join(", ")
        )
    });
    std::iter::once(header).chain(rows).collect()
}

/// `jobs leases`' table: a header, then each lease's id, job, frame, worker and the seconds
/// until it expires from `now_ms`.
pub(super) fn lease_table(leases: &[pb::Lease], now_ms: i64) -> Vec<String> {
    let header = format!(
        "{:<38} {:<18} {:>6}  {:<24} expires",
        "lease", "job", "frame", "worker"
    );
    let rows = leases.iter().map(|l| {
        let expires = (l.expires_unix_ms - now_ms) as f64 / 1e3;
        let worker = worker_label(&l.worker_name, l.embedded);
        format!(
            "{:<38} {:<18} {:>6}  {:<24} in {expires:.1} s",
            l.lease_id, l.job_id, l.frame_index, worker
        )
    });
    std::iter::once(header).chain(rows).collect()
}

fn worker_label(name: &str, embedded: bool) -> String {
    if embedded {
        format!("{name} (embedded)")
    } else {
        name.to_string()
    }
}

/// What `jobs show` says of a job's workers: what it requires of them, who rendered its
/// frames, who is blocklisted, the jobs it runs after, whether it leaves the files its frames
/// do not see unbuilt, why it waits (for one of those, or for
/// a connected worker that can render it), and where its videos stand.
pub(super) fn scheduling_lines(job: &pb::Job) -> Vec<String> {
    let mut lines = Vec::new();
    if let Some(required) = job.requirements.as_ref() {
        let mut parts = Vec::new();
        if required.gpu {
            parts.push("a GPU".to_string());
        }
        if !required.tags.is_empty() {
            parts.push(format!("tags {}", required.tags.join(", ")));
        }
        if !parts.is_empty() {
            lines.push(format!("requires: {}", parts.join(" and ")));
        }
    }
    let mut rendered: std::collections::BTreeMap<&str, u32> = Default::default();
    for frame in &job.frames {
        if !frame.worker_name.is_empty() {
            *rendered.entry(frame.worker_name.as_str()).or_default() += 1;
        }
    }
    if !rendered.is_empty() {
        let by: Vec<String> = rendered
            .iter()
            .map(|(worker, frames)| format!("{worker} {frames}"))
            .collect();
        lines.push(format!("frames by worker: {}", by.join(", ")));
    }
    if !job.blocklisted_workers.is_empty() {
        let listed: Vec<String> = job
            .blocklisted_workers
            .iter()
            .map(|w| format!("{} ({} failed frames)", w.worker_name, w.failed_frames))
            .collect();
        lines.push(format!("blocklisted workers: {}", listed.join(", ")));
    }
    if !job.after_job_ids.is_empty() {
        lines.push(format!("runs after: {}", job.after_job_ids.join(", ")));
    }
    if job.build_unseen == pb::BuildUnseen::Never as i32 {
        lines.push(
            "build unseen: never (the files its frames do not see are not built for it)".into(),
        );
    }
    if !job.waiting_reason.is_empty() {
        lines.push(format!("waiting: {}", job.waiting_reason));
    }
    match (job.stage.as_str(), job.video_size_bytes) {
        ("video", _) => {
            lines.push("stage: video (every frame is final; its video is being made)".into())
        }
        (_, 0) => {}
        (_, bytes) => lines.push(format!(
            "video: {bytes} bytes (jobs video {} --out FILE)",
            job.id
        )),
    }
    match job.preview_video.as_str() {
        "" => {}
        "ready" => lines.push(format!(
            "preview video: ready (jobs video {} --preview --out FILE)",
            job.id
        )),
        state => lines.push(format!("preview video: {state}")),
    }
    if job.outputs_uploaded > 0 || job.outputs_pending > 0 || !job.output_errors.is_empty() {
        lines.push(format!(
            "outputs: {} uploaded, {} pending",
            job.outputs_uploaded, job.outputs_pending
        ));
    }
    for error in &job.output_errors {
        lines.push(format!("  output not written: {error}"));
    }
    for refusal in &job.refusals {
        lines.push(format!(
            "  worker {} cannot render it: {}",
            refusal.worker_name, refusal.reason
        ));
    }
    lines
}

/// Whether a job in `state` has ended (succeeded, failed or cancelled).
pub(super) fn has_ended(state: i32) -> bool {
    matches!(
        pb::JobState::try_from(state),
        Ok(pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scheduling_lines_say_a_job_never_builds_the_files_its_frames_do_not_see() {
        let never = "build unseen: never (the files its frames do not see are not built for it)";
        let mut job = pb::Job {
            build_unseen: pb::BuildUnseen::Never as i32,
            ..Default::default()
        };
        assert!(scheduling_lines(&job).contains(&never.to_owned()));
        job.build_unseen = pb::BuildUnseen::After as i32;
        assert!(!scheduling_lines(&job).iter().any(|l| l.contains("unseen")));
    }

    #[test]
    fn scheduling_lines_follow_the_preview_video() {
        let mut job = pb::Job {
            id: "job-1".into(),
            preview_video: "encoding".into(),
            ..Default::default()
        };
        assert!(scheduling_lines(&job).contains(&"preview video: encoding".to_owned()));
        job.preview_video = "ready".into();
        assert!(scheduling_lines(&job)
            .contains(&"preview video: ready (jobs video job-1 --preview --out FILE)".to_owned()));
        job.preview_video.clear();
        assert!(!scheduling_lines(&job)
            .iter()
            .any(|l| l.contains("preview video")));
    }

    #[test]
    fn stage_statistics_give_median_and_p95_per_stage() {
        let frames: Vec<pb::FrameFinished> = (0..20)
            .map(|i| pb::FrameFinished {
                index: i,
                dataset_cache_hit: None,
                failed_attempts: 0,
                cut: None,
                worker_name: String::new(),
                preview: false,
                completeness: 0.0,
                timings: vec![
                    pb::StageTiming {
                        stage: "rasterize".into(),
                        ms: i as f64,
                        gpu_clock: true,
                    },
                    pb::StageTiming {
                        stage: "encode".into(),
                        ms: 1.0,
                        gpu_clock: false,
                    },
                ],
            })
            .collect();
        let stats = stage_statistics(&frames);
        assert_eq!(stats[0].stage, "rasterize");
        assert_eq!(stats[0].median_ms, 10.0);
        assert_eq!(stats[0].p95_ms, 18.0);
        assert_eq!(
            stats[1],
            StageStatistics {
                stage: "encode".to_string(),
                median_ms: 1.0,
                p95_ms: 1.0
            }
        );
    }

    #[test]
    fn a_cut_summary_says_what_frames_by_url_read_only_where_they_did() {
        let frame = |cut: pb::FrameCut| pb::FrameFinished {
            cut: Some(cut),
            ..Default::default()
        };
        let local = [frame(pb::FrameCut::default())];
        let line = cut_summary(&local).expect("a cut");
        assert!(!line.contains("by URL"), "{line}");
        let by_url = [
            frame(pb::FrameCut {
                object_requests: 5,
                object_bytes: 3 << 20,
                ..Default::default()
            }),
            frame(pb::FrameCut {
                object_requests: 1,
                range_cache_bytes: 2 << 20,
                ..Default::default()
            }),
        ];
        let line = cut_summary(&by_url).expect("cuts");
        assert!(
            line.ends_with("; by URL 6 requests (3.0 MiB), 2.0 MiB from the workers' range caches"),
            "{line}"
        );
    }
}

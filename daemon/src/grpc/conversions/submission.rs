//! A job's submission, validated on the way in: what needs nothing but the request; the
//! limits of the server and the jobs it runs after are checked by the daemon.

use pointfarm_proto::v1 as pb;

use super::super::request::{build_unseen, render_request};
use super::invalid;
use crate::capabilities::WorkerRequirements;
use crate::error::DaemonError;
use crate::job_control::{check_labels, check_name, check_priority};
use crate::model::JobSpec;

/// Validates a submission; limits that depend on the server are checked by the daemon.
impl TryFrom<&pb::SubmitJobRequest> for JobSpec {
    type Error = DaemonError;

    fn try_from(r: &pb::SubmitJobRequest) -> Result<Self, DaemonError> {
        if r.dataset_id.is_empty() {
            return Err(invalid("dataset_id", "is required"));
        }
        check_priority("priority", r.priority)?;
        check_name("name", &r.name)?;
        let labels = r.labels.clone().into_iter().collect();
        check_labels("labels", &labels)?;
        Ok(JobSpec {
            request_id: r.request_id.clone(),
            dataset_id: r.dataset_id.clone(),
            request: render_request(r.width, r.height, r.camera_path.as_ref(), r.render.as_ref())?,
            priority: r.priority,
            requirements: r
                .requirements
                .as_ref()
                .map(WorkerRequirements::try_from)
                .transpose()?
                .unwrap_or_default(),
            preview: r.preview,
            // Checked by the daemon, which knows the jobs.
            after: r.after_job_ids.clone(),
            name: r.name.clone(),
            labels,
            video: super::super::video::video_settings(r.video.as_ref())?,
            output_url: crate::output_queue::check_output_url("output_url", &r.output_url)?,
            build_unseen: build_unseen(r.build_unseen)?,
        })
    }
}

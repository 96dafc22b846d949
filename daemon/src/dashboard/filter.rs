//! The jobs list's filter, for the jobs page and `/api/jobs` alike: a state
//! (`state=running`), labels (`label=shot=010`, each one more that a job must have, as
//! `ListJobsRequest.labels` asks) and a part of the job's name (`name=night`, any case).
//! Read from the URL's query, so that a link shares a filter; what it holds is checked as a
//! submission's labels and name are (`job_control`), and refused as a 400 that names the
//! field.

use std::collections::BTreeMap;

use pointfarm_proto::v1 as pb;
use tonic::Status;

use super::failure::Failure;
use crate::job_control::{check_labels, check_name};
use crate::model::{Job, JobState};
use crate::state::JobFilter;

/// Which jobs a list shows.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct JobQuery {
    /// What the state database filters: the state and the labels.
    pub stored: JobFilter,
    /// A part of the name users see (`pages::job_name`), lowercased; empty matches all.
    pub name: String,
}

impl JobQuery {
    /// The filter in a URL's query (`state`, every `label`, `name`); other fields are left
    /// to their readers. An empty `label` or `name` is no filter, as a form leaves them.
    pub fn parse(query: &[u8]) -> Result<Self, Failure> {
        let mut state = None;
        let mut labels = BTreeMap::new();
        let mut name = String::new();
        for (key, value) in form_urlencoded::parse(query) {
            match key.as_ref() {
                "state" => state = parse_state(&value)?,
                "label" => {
                    let Some((key, wanted)) = label(&value)? else {
                        continue;
                    };
                    if labels.get(&key).is_some_and(|other| *other != wanted) {
                        return Err(invalid(format!(
                            "label: '{key}' is asked to be both '{}' and '{wanted}'; no job \
                             has two values of one label",
                            labels[&key]
                        )));
                    }
                    labels.insert(key, wanted);
                }
                "name" => {
                    check_name("name", &value)?;
                    name = value.trim().to_lowercase();
                }
                _ => {}
            }
        }
        check_labels("label", &labels)?;
        Ok(Self {
            stored: JobFilter { state, labels },
            name,
        })
    }

    pub fn state(&self) -> Option<JobState> {
        self.stored.state
    }

    pub fn labels(&self) -> &BTreeMap<String, String> {
        &self.stored.labels
    }

    /// The part of the filter the state database does not apply (`stored` is the rest):
    /// whether `job`'s name holds the part asked for.
    pub fn matches_name(&self, job: &Job) -> bool {
        self.name.is_empty() || job_name(job).to_lowercase().contains(&self.name)
    }

    /// Whether the list is filtered at all.
    pub fn is_empty(&self) -> bool {
        self.stored.state.is_none() && self.stored.labels.is_empty() && self.name.is_empty()
    }

    /// This filter as a URL's query (without `?`), with `state` instead of its own and
    /// `extra` label added: what a link to a narrower or other list says.
    pub fn query_with(&self, state: Option<JobState>, extra: Option<(&str, &str)>) -> String {
        let mut query = form_urlencoded::Serializer::new(String::new());
        if let Some(state) = state {
            query.append_pair("state", state.name());
        }
        let extra = extra.filter(|(key, _)| !self.stored.labels.contains_key(*key));
        let current = self.stored.labels.iter();
        for (key, value) in current.map(|(k, v)| (k.as_str(), v.as_str())).chain(extra) {
            query.append_pair("label", &format!("{key}={value}"));
        }
        if !self.name.is_empty() {
            query.append_pair("name", &self.name);
        }
        query.finish()
    }

    /// This filter's own query.
    pub fn query(&self) -> String {
        self.query_with(self.stored.state, None)
    }

    /// This filter without label `key`: the link that drops it.
    pub fn without_label(&self, key: &str) -> Self {
        let mut narrower = self.clone();
        narrower.stored.labels.remove(key);
        narrower
    }
}

/// `key=value` of a `label` field; None when the field is empty.
fn label(field: &str) -> Result<Option<(String, String)>, Failure> {
    if field.trim().is_empty() {
        return Ok(None);
    }
    match field.split_once('=') {
        Some((key, value)) => Ok(Some((key.trim().to_string(), value.to_string()))),
        None => Err(invalid(format!(
            "label: '{field}' is not key=value (label=shot=010)"
        ))),
    }
}

fn invalid(message: String) -> Failure {
    Failure(Status::invalid_argument(message))
}

/// `jobs` less those whose name the filter does not take: a page of `/api/jobs`.
pub fn jobs_message(
    query: &JobQuery,
    jobs: &[Job],
    next_page_token: String,
) -> pb::ListJobsResponse {
    pb::ListJobsResponse {
        jobs: jobs
            .iter()
            .filter(|job| query.matches_name(job))
            .map(pb::Job::from)
            .collect(),
        next_page_token,
    }
}

/// A job state by its name in either spelling: `running` or `JOB_STATE_RUNNING`.
pub fn parse_state(name: &str) -> Result<Option<JobState>, Failure> {
    let lower = name.trim().to_ascii_lowercase();
    let short = lower.strip_prefix("job_state_").unwrap_or(&lower);
    Ok(Some(match short {
        "" | "all" | "unspecified" => return Ok(None),
        "queued" => JobState::Queued,
        "running" => JobState::Running,
        "succeeded" => JobState::Succeeded,
        "failed" => JobState::Failed,
        "cancelled" => JobState::Cancelled,
        "paused" => JobState::Paused,
        _ => {
            return Err(Failure(Status::invalid_argument(format!(
                "state: '{name}' is none of queued, running, paused, succeeded, failed, \
                 cancelled"
            ))))
        }
    }))
}

/// What users call a job: its name, else the request id its client chose.
pub(super) fn job_name(job: &Job) -> &str {
    if job.spec.name.is_empty() {
        &job.spec.request_id
    } else {
        &job.spec.name
    }
}

#[cfg(test)]
mod tests {
    use axum::http::StatusCode;

    use super::*;

    fn parse(query: &str) -> Result<JobQuery, Failure> {
        JobQuery::parse(query.as_bytes())
    }

    #[test]
    fn states_are_read_in_either_spelling() {
        assert_eq!(parse_state("running").ok(), Some(Some(JobState::Running)));
        assert_eq!(
            parse_state("JOB_STATE_CANCELLED").ok(),
            Some(Some(JobState::Cancelled))
        );
        assert_eq!(parse_state("").ok(), Some(None));
        assert_eq!(parse_state("paused").ok(), Some(Some(JobState::Paused)));
        let refused = parse_state("stalled").expect_err("refused");
        assert_eq!(refused.http_status(), StatusCode::BAD_REQUEST);
        assert!(
            refused.message().contains("'stalled'"),
            "{}",
            refused.message()
        );
    }

    #[test]
    fn a_query_reads_a_state_labels_and_a_name() {
        let query = parse("state=running&label=shot%3D010&label=team=fx%3Da&name=Night&limit=5")
            .expect("a filter");
        assert_eq!(query.state(), Some(JobState::Running));
        let labels: Vec<_> = query.labels().iter().collect();
        assert_eq!(
            labels,
            [
                (&"shot".to_string(), &"010".to_string()),
                (&"team".to_string(), &"fx=a".to_string())
            ]
        );
        assert_eq!(query.name, "night");
        assert_eq!(
            query.query(),
            "state=running&label=shot%3D010&label=team%3Dfx%3Da&name=night"
        );
        assert_eq!(parse(&query.query()).expect("read back"), query);
        assert_eq!(
            query
                .without_label("shot")
                .query_with(None, Some(("seq", "1"))),
            "label=team%3Dfx%3Da&label=seq%3D1&name=night"
        );
        let empty = parse("label=&name=&state=").expect("no filter");
        assert!(empty.is_empty(), "{empty:?}");
        assert_eq!(empty.query(), "");
    }

    #[test]
    fn a_bad_filter_is_a_400_naming_its_field() {
        for (query, says) in [
            ("label=shot", "not key=value"),
            ("label=Shot%20A=1", "key"),
            ("label=shot=1&label=shot=2", "both"),
            ("state=stalled", "'stalled'"),
            ("name=a%07b", "control character"),
            (&format!("label=shot={}", "v".repeat(300)), "bytes"),
        ] {
            let refused = parse(query).expect_err(query);
            assert_eq!(refused.http_status(), StatusCode::BAD_REQUEST, "{query}");
            assert!(
                refused.message().contains(says),
                "{query}: {}",
                refused.message()
            );
        }
    }
}

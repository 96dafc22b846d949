//! The outputs on their way to object storage, kept in the `outputs` tree until each is
//! uploaded or its failure is recorded in its job, so that a daemon stopped (even by
//! `kill -9`) resumes them. A record's key is taken from sled's increasing id, so records
//! are resumed in the order they were queued; the job's pending count changes in the same
//! transaction as its record.
//!
//! Neither queuing nor finishing an output flushes the database itself: a frame's output is
//! queued before the frame is marked done, whose flush makes both durable before the frame's
//! completion is answered, and the upload thread flushes the outputs it finished once per
//! batch. A finished output whose removal a crash lost is sent again, to the same URL with
//! the same bytes, and counted once, as its job's count was lost with it.

use std::ops::Bound;

use sled::transaction::{TransactionalTree, UnabortableTransactionError};
use sled::Transactional;

use super::records::Records;
use super::{decode, encode, transaction_error, StateDb};
use crate::error::StateError;
use crate::model::Job;
use crate::output_queue::PendingOutput;

impl Records {
    /// Stores `job` changed by `change` and applies `record` to the outputs tree, as one
    /// transaction; None (and nothing applied but `record`) if there is no such job.
    fn change_job_with_output(
        &self,
        job_id: &str,
        change: impl FnOnce(&mut Job),
        record: impl Fn(&TransactionalTree) -> Result<(), UnabortableTransactionError>,
    ) -> Result<Option<Job>, StateError> {
        let changed = self.changed_job(job_id, change)?;
        let encoded = changed.as_ref().map(encode).transpose()?;
        (&self.trees.jobs, &self.trees.outputs)
            .transaction(|(jobs, outputs)| {
                if let Some(encoded) = &encoded {
                    jobs.insert(job_id.as_bytes(), encoded.as_slice())?;
                }
                record(outputs)?;
                Ok(())
            })
            .map_err(transaction_error)?;
        Ok(changed)
    }
}

/// An output record's key: big-endian, so that keys sort in the order they were taken.
fn output_key(key: u64) -> [u8; 8] {
    key.to_be_bytes()
}

impl StateDb {
    /// Records `output` as pending and counts it in its job; None, and nothing recorded,
    /// if the job is gone. Returns the job as changed; durable with the next flush.
    pub fn queue_output(&self, output: &PendingOutput) -> Result<Option<Job>, StateError> {
        self.with(|records| {
            if records.job(&output.job_id)?.is_none() {
                return Ok(None);
            }
            let key = output_key(records.db.generate_id()?);
            let encoded = encode(output)?;
            records.change_job_with_output(
                &output.job_id,
                |job| job.outputs.pending += 1,
                |outputs| {
                    outputs.insert(&key, encoded.as_slice())?;
                    Ok(())
                },
            )
        })
    }

    /// Removes the pending output `key` of job `job_id` and records how it went in the job
    /// (uploaded, or why not); the job is None if it is gone. Durable with the next flush.
    pub fn finish_output(
        &self,
        key: u64,
        job_id: &str,
        outcome: Result<(), String>,
    ) -> Result<Option<Job>, StateError> {
        self.with(|records| {
            records.change_job_with_output(
                job_id,
                |job| job.outputs.record(outcome),
                |outputs| {
                    outputs.remove(&output_key(key))?;
                    Ok(())
                },
            )
        })
    }

    /// The first pending output queued after `after` (from the first when None), with its key.
    /// A record that cannot be read is removed and logged, so that it cannot hold up the
    /// outputs queued after it.
    pub fn pending_output_after(
        &self,
        after: Option<u64>,
    ) -> Result<Option<(u64, PendingOutput)>, StateError> {
        self.with(|records| {
            let outputs = &records.trees.outputs;
            let start = match after {
                None => Bound::Unbounded,
                Some(after) => Bound::Excluded(output_key(after)),
            };
            let entries = outputs.range::<[u8; 8], _>((start, Bound::Unbounded));
            for entry in entries {
                let (key, value) = entry?;
                match read_output(&key, &value) {
                    Ok(found) => return Ok(Some(found)),
                    Err(error) => {
                        tracing::warn!(
                            %error,
                            "removed a pending output record that cannot be read; its upload is lost"
                        );
                        outputs.remove(&key)?;
                    }
                }
            }
            Ok(None)
        })
    }
}

/// A pending output record's key and value, read.
fn read_output(key: &[u8], value: &[u8]) -> Result<(u64, PendingOutput), StateError> {
    let key: [u8; 8] = key.try_into().map_err(|_| {
        StateError::Damaged(format!(
            "an output record's key is {} bytes, not 8",
            key.len()
        ))
    })?;
    Ok((u64::from_be_bytes(key), decode(value)?))
}

#[cfg(test)]
mod tests {
    use pointfarm_render::request::RenderRequest;

    use super::*;
    use crate::model::JobSpec;

    fn open(dir: &std::path::Path) -> StateDb {
        StateDb::open(&dir.join("state.sled"), false)
            .expect("open")
            .0
    }

    fn output(job_id: &str, index: u32) -> PendingOutput {
        PendingOutput {
            job_id: job_id.into(),
            name: format!("frame_{index:05}.png"),
            file: format!("/data/frames/{job_id}/{index}.png").into(),
            url: format!("s3://renders/farm/frame_{index:05}.png"),
        }
    }

    fn submit(state: &StateDb) -> Job {
        let request = RenderRequest::turntable(8, 8, 3);
        let spec = JobSpec::new("a".into(), "ds-1".into(), request);
        state.submit_job(spec).expect("submit").0
    }

    /// Every pending output from the first, in order.
    fn pending(state: &StateDb) -> Vec<(u64, PendingOutput)> {
        let mut found = Vec::new();
        while let Some(next) = state
            .pending_output_after(found.last().map(|(key, _)| *key))
            .expect("pending")
        {
            found.push(next);
        }
        found
    }

    #[test]
    fn a_pending_output_is_counted_in_its_job_until_it_is_finished() {
        let dir = tempfile::tempdir().expect("dir");
        let state = open(dir.path());
        let job = submit(&state);
        let queued = state.queue_output(&output(&job.id, 0)).expect("queue");
        assert_eq!(queued.expect("job").outputs.pending, 1);
        state.queue_output(&output(&job.id, 1)).expect("queue");
        let [(first, stored), (second, _)] = pending(&state).try_into().expect("two");
        assert_eq!(stored, output(&job.id, 0));

        let finished = state.finish_output(first, &job.id, Ok(())).expect("finish");
        let outputs = finished.expect("job").outputs;
        assert_eq!((outputs.uploaded, outputs.pending), (1, 1));
        let failed = state
            .finish_output(second, &job.id, Err("refused".into()))
            .expect("finish");
        let outputs = failed.expect("job").outputs;
        assert_eq!((outputs.uploaded, outputs.pending), (1, 0));
        assert_eq!(outputs.errors, ["refused"]);
        assert!(pending(&state).is_empty());
    }

    #[test]
    fn pending_outputs_survive_a_reopening_in_the_order_they_were_queued() {
        let dir = tempfile::tempdir().expect("dir");
        let state = open(dir.path());
        let job = submit(&state);
        for index in [2, 0, 1] {
            state.queue_output(&output(&job.id, index)).expect("queue");
        }
        state.flush().expect("flush");
        drop(state);

        let state = open(dir.path());
        let names: Vec<String> = pending(&state).into_iter().map(|(_, o)| o.name).collect();
        assert_eq!(
            names,
            ["frame_00002.png", "frame_00000.png", "frame_00001.png"]
        );
        let job = state.job(&job.id).expect("read").expect("job");
        assert_eq!(job.outputs.pending, 3);
        // Taken after the reopening, a record still comes after every earlier one.
        state.queue_output(&output(&job.id, 7)).expect("queue");
        assert_eq!(pending(&state).last().expect("last").1, output(&job.id, 7));
    }

    #[test]
    fn a_pending_output_record_that_cannot_be_read_is_removed_and_the_next_one_comes() {
        let dir = tempfile::tempdir().expect("dir");
        let state = open(dir.path());
        let job = submit(&state);
        state.queue_output(&output(&job.id, 0)).expect("queue");
        state.queue_output(&output(&job.id, 1)).expect("queue");
        let [(first, _), _] = pending(&state).try_into().expect("two");
        state
            .with(|records| {
                records
                    .trees
                    .outputs
                    .insert(output_key(first), &b"not a record"[..])?;
                Ok(())
            })
            .expect("damage");

        let found = pending(&state);
        assert_eq!(found.len(), 1, "the damaged record is passed over");
        assert_eq!(found[0].1, output(&job.id, 1));
        let left = state
            .with(|records| Ok(records.trees.outputs.len()))
            .expect("count");
        assert_eq!(left, 1, "the damaged record is removed");
    }

    #[test]
    fn an_output_of_a_job_gone_is_not_recorded_and_one_finished_after_is_removed() {
        let dir = tempfile::tempdir().expect("dir");
        let state = open(dir.path());
        assert_eq!(
            state
                .queue_output(&output("no-such-job", 0))
                .expect("queue"),
            None
        );
        assert!(pending(&state).is_empty());
        let job = submit(&state);
        state.queue_output(&output(&job.id, 0)).expect("queue");
        let (key, _) = pending(&state).remove(0);
        assert_eq!(
            state.finish_output(key, "another", Ok(())).expect("finish"),
            None
        );
        assert!(pending(&state).is_empty());
    }
}

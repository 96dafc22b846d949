//! The parts of datasets whose stores the daemon builds first for jobs (camera first), kept
//! by their dataset ids so that a restart knows them without a job asking
//! (`stores::camera_first`). Each change is flushed at once: parts are few and made rarely.

use super::{decode, encode, StateDb};
use crate::error::StateError;
use crate::model::CameraFirstPart;

impl StateDb {
    /// Records `part`, replacing what was recorded of it.
    pub fn put_camera_first_part(&self, part: &CameraFirstPart) -> Result<(), StateError> {
        let encoded = encode(part)?;
        self.with(|records| {
            records
                .trees
                .parts
                .insert(part.part.id.as_bytes(), encoded)?;
            records.flush()
        })
    }

    /// Forgets the part whose dataset id is `id`.
    pub fn remove_camera_first_part(&self, id: &str) -> Result<(), StateError> {
        self.with(|records| {
            records.trees.parts.remove(id.as_bytes())?;
            records.flush()
        })
    }

    /// Every part recorded.
    pub fn camera_first_parts(&self) -> Result<Vec<CameraFirstPart>, StateError> {
        self.with(|records| {
            records
                .trees
                .parts
                .iter()
                .map(|entry| decode(&entry?.1))
                .collect()
        })
    }
}

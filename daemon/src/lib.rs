//! The pointfarm daemon. It will own datasets, jobs and their state (sled) and hand frame
//! tasks to workers; it arrives with the render service. Rendering itself lives in
//! `pointfarm-worker` and never depends on this crate.

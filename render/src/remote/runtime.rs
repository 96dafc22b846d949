//! The blocking face over object_store's async clients: a small tokio runtime of this module's
//! own, answering through a channel.

use std::future::Future;
use std::sync::mpsc;

use super::error::RemoteError;

/// Worker threads of the runtime: requests are I/O-bound, so two threads keep many in flight.
const RUNTIME_THREADS: usize = 2;

/// Owns the runtime the remote layer's requests run on.
pub(crate) struct RemoteRuntime {
    runtime: Option<tokio::runtime::Runtime>,
}

impl RemoteRuntime {
    pub(crate) fn new() -> Result<Self, RemoteError> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(RUNTIME_THREADS)
            .thread_name("pointfarm-remote")
            .enable_io()
            .enable_time()
            .build()
            .map_err(|error| RemoteError::Runtime {
                message: error.to_string(),
            })?;
        Ok(Self {
            runtime: Some(runtime),
        })
    }

    /// Runs a future on the runtime and waits for its answer; spawning and waiting on a std
    /// channel, rather than `Runtime::block_on`, works from any thread, an async one included,
    /// where `block_on` would panic.
    pub(crate) fn run<F>(&self, future: F) -> Result<F::Output, RemoteError>
    where
        F: Future + Send + 'static,
        F::Output: Send + 'static,
    {
        let runtime = self.runtime.as_ref().ok_or_else(|| RemoteError::Runtime {
            message: "it was shut down".to_owned(),
        })?;
        let (sender, receiver) = mpsc::sync_channel(1);
        runtime.spawn(async move {
            // The receiver is gone only when the caller's thread unwound; nobody needs the answer.
            let _ = sender.send(future.await);
        });
        receiver.recv().map_err(|_| RemoteError::Runtime {
            message: "a request's task ended without an answer".to_owned(),
        })
    }
}

impl Drop for RemoteRuntime {
    fn drop(&mut self) {
        // Dropping a runtime blocks, which panics on an async thread; this never blocks.
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}

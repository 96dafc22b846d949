//! Containment of what the pre-parse cannot foresee: a panic inside the `las`/`laz` decoders
//! (rayon hands a worker's panic to the caller) becomes an [`IngestError`] naming the file,
//! so a corrupt chunk never takes the process down.

use std::panic::{self, AssertUnwindSafe};
use std::path::Path;

use super::IngestError;

/// Runs `decode`, turning a panic into [`IngestError::DecoderPanicked`].
pub(crate) fn contain_panics<T>(
    path: &Path,
    decode: impl FnOnce() -> Result<T, IngestError>,
) -> Result<T, IngestError> {
    // The decoder's state is dropped with the closure; nothing of it is observed afterwards.
    panic::catch_unwind(AssertUnwindSafe(decode)).unwrap_or_else(|payload| {
        let message = payload
            .downcast_ref::<&str>()
            .map(|message| (*message).to_owned())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "panic without a message".to_owned());
        tracing::warn!(file = %path.display(), %message, "contained a decoder panic");
        Err(IngestError::DecoderPanicked {
            path: path.to_owned(),
            message,
        })
    })
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;

    #[test]
    fn a_panic_becomes_an_error_naming_the_file() {
        let path = Path::new("/data/broken.laz");
        let error = contain_panics::<()>(path, || panic!("index out of bounds"))
            .expect_err("a panic is an error");
        assert!(
            matches!(&error, IngestError::DecoderPanicked { message, .. } if message == "index out of bounds")
        );
        assert!(
            error.to_string().starts_with("/data/broken.laz: "),
            "{error}"
        );
        let formatted =
            contain_panics::<()>(path, || panic!("{} chunks", 3)).expect_err("a panic is an error");
        assert!(formatted.to_string().ends_with("3 chunks"), "{formatted}");
        assert_eq!(contain_panics(path, || Ok(7)).ok(), Some(7));
    }
}

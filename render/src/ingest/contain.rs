//! Containment of what the pre-parse cannot foresee: a panic inside the `las`/`laz` decoders
//! (rayon hands a worker's panic to the caller) becomes an [`IngestError`] naming the file,
//! so a corrupt chunk never takes the process down. While a containment runs, the panic hook
//! stays quiet about panics raised inside those two crates: the error says it once.

use std::panic::{self, AssertUnwindSafe};
use std::path::{Component, Path};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Once;

use super::IngestError;

/// How many containments run now, on any thread (rayon decodes on threads of its own).
static CONTAINING: AtomicUsize = AtomicUsize::new(0);
static QUIET_HOOK: Once = Once::new();

/// Runs `decode`, turning a panic into [`IngestError::DecoderPanicked`].
pub(crate) fn contain_panics<T>(
    path: &Path,
    decode: impl FnOnce() -> Result<T, IngestError>,
) -> Result<T, IngestError> {
    install_quiet_hook();
    CONTAINING.fetch_add(1, Ordering::SeqCst);
    // The decoder's state is dropped with the closure; nothing of it is observed afterwards.
    let result = panic::catch_unwind(AssertUnwindSafe(decode));
    CONTAINING.fetch_sub(1, Ordering::SeqCst);
    result.unwrap_or_else(|payload| {
        let message = payload
            .downcast_ref::<&str>()
            .map(|message| (*message).to_owned())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "panic without a message".to_owned());
        tracing::debug!(file = %path.display(), %message, "contained a decoder panic");
        Err(IngestError::DecoderPanicked {
            path: path.to_owned(),
            message,
        })
    })
}

/// Wraps the process's panic hook once, so that a contained decoder panic prints no
/// "panicked at" report and backtrace; every other panic reports as before.
fn install_quiet_hook() {
    QUIET_HOOK.call_once(|| {
        let previous = panic::take_hook();
        panic::set_hook(Box::new(move |info| {
            let in_decoder = info
                .location()
                .is_some_and(|location| is_decoder_source(Path::new(location.file())));
            if !(in_decoder && CONTAINING.load(Ordering::SeqCst) > 0) {
                previous(info);
            }
        }));
    });
}

/// Whether a source file belongs to the `las` or `laz` crate (`…/laz-0.13.0/src/…`).
fn is_decoder_source(file: &Path) -> bool {
    file.components().any(|component| match component {
        Component::Normal(name) => name.to_str().is_some_and(|name| {
            ["las-", "laz-"].iter().any(|prefix| {
                name.strip_prefix(prefix)
                    .is_some_and(|version| version.starts_with(|c: char| c.is_ascii_digit()))
            })
        }),
        _ => false,
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

    #[test]
    fn decoder_sources_are_told_from_others() {
        let registry = "/root/.cargo/registry/src/index.crates.io-1949cf8c6b5b557f";
        assert!(is_decoder_source(Path::new(&format!(
            "{registry}/laz-0.13.0/src/decoders.rs"
        ))));
        assert!(is_decoder_source(Path::new(&format!(
            "{registry}/las-0.9.2/src/reader.rs"
        ))));
        assert!(!is_decoder_source(Path::new(&format!(
            "{registry}/lasso-1.0.0/src/lib.rs"
        ))));
        assert!(!is_decoder_source(Path::new("render/src/ingest/read.rs")));
    }
}

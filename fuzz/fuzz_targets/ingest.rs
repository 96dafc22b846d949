//! Arbitrary bytes through LAS/LAZ ingest: the header, VLR, EVLR, LASzip VLR and chunk table
//! pre-parse and the decoders behind it. Any outcome but a panic or an abort is fine; the
//! input is written to a file because ingest reads files (and checks against their size).
//! Inputs starting with `LASF` are the interesting ones: seed the corpus with real files.

#![no_main]

use std::io::Write;
use std::sync::Once;

use libfuzzer_sys::fuzz_target;

static SILENT_PANICS: Once = Once::new();

fuzz_target!(|bytes: &[u8]| {
    // libfuzzer-sys's hook aborts on every panic, even one ingest contains (the `laz` coder's
    // debug assertions fire on corrupt data); a panic that escapes ingest still aborts, since
    // libfuzzer-sys catches it around this closure.
    SILENT_PANICS.call_once(|| std::panic::set_hook(Box::new(|_| {})));
    let mut file = tempfile_in_memory();
    file.write_all(bytes).expect("write the input");
    file.flush().expect("flush the input");
    let _ = pointfarm_render::ingest::load_point_cloud(file.path());
});

/// A named temporary file, in memory where the system has a tmpfs.
fn tempfile_in_memory() -> tempfile::NamedTempFile {
    let dir = std::path::Path::new("/dev/shm");
    if dir.is_dir() {
        tempfile::NamedTempFile::new_in(dir).expect("temp file")
    } else {
        tempfile::NamedTempFile::new().expect("temp file")
    }
}

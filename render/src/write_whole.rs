//! Small files beside a store (its file lists, its finished marker) replaced whole or not at
//! all, so a reader never sees half a list after a crash.

use std::io::Write;
use std::path::Path;

/// Writes `bytes` to `path` through `PATH.partial`, synced, then renamed over it, and the
/// rename synced: without the first sync a power cut may leave the new name on an empty file
/// (file systems may commit the rename before the data), without the second the old file.
pub fn write_whole(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut partial = path.as_os_str().to_owned();
    partial.push(".partial");
    let mut file = std::fs::File::create(&partial)?;
    file.write_all(bytes)?;
    file.sync_all()?;
    drop(file);
    std::fs::rename(&partial, path)?;
    let folder = path.parent().filter(|p| !p.as_os_str().is_empty());
    std::fs::File::open(folder.unwrap_or(Path::new(".")))?.sync_all()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_is_replaced_whole_and_no_partial_is_left() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("list.txt");
        write_whole(&path, b"one\n").expect("first");
        write_whole(&path, b"two\n").expect("second");
        assert_eq!(std::fs::read(&path).expect("read"), b"two\n");
        assert!(!dir.path().join("list.txt.partial").exists());
    }
}

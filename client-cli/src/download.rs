//! Files a server sends, written beside their place under a `.part` name and renamed into it
//! once whole, so that a cut download never leaves a partial file under the name asked for.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

/// A download to `out`, written to the partial file beside it until it is whole.
pub struct PartialFile {
    partial: PathBuf,
    out: PathBuf,
}

impl PartialFile {
    /// The partial file of `out`: its name with `.part` appended, in its folder.
    pub fn of(out: &Path) -> Self {
        let mut name = out.file_name().unwrap_or_default().to_os_string();
        name.push(".part");
        Self {
            partial: out.with_file_name(name),
            out: out.to_path_buf(),
        }
    }

    /// Where the download is written until it is whole.
    pub fn path(&self) -> &Path {
        &self.partial
    }

    /// Renames the partial file into place once `written` says it is whole; removes it when
    /// the download or the rename failed.
    pub fn finish<T>(self, written: Result<T>) -> Result<T> {
        let placed = written.and_then(|value| {
            std::fs::rename(&self.partial, &self.out)
                .with_context(|| format!("writing {}", self.out.display()))
                .map(|()| value)
        });
        if placed.is_err() {
            let _ = std::fs::remove_file(&self.partial);
        }
        placed
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_whole_download_takes_its_place_and_a_failed_one_leaves_nothing() {
        let dir = tempfile::tempdir().expect("tempdir");
        let out = dir.path().join("spin.mp4");
        let partial = PartialFile::of(&out);
        assert_eq!(partial.path(), dir.path().join("spin.mp4.part"));
        std::fs::write(partial.path(), b"whole").expect("write");
        assert_eq!(partial.finish(Ok(5)).expect("placed"), 5);
        assert_eq!(std::fs::read(&out).expect("read"), b"whole");

        let again = PartialFile::of(&dir.path().join("cut.mp4"));
        std::fs::write(again.path(), b"cu").expect("write");
        let part = again.path().to_path_buf();
        let error = again.finish::<u64>(Err(anyhow::anyhow!("the stream ended")));
        assert!(error.is_err());
        assert!(!part.exists() && !dir.path().join("cut.mp4").exists());
    }
}

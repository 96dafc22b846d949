//! The bytes store folders take on disk, by the one rule every count of them follows: a file
//! is counted once however many names it has (a grown store's layers are hard links to the
//! payload files of the stores it was grown from, `layers.rs`), known by its identity, its
//! device and inode; and removing folders frees a file only when every name it has lies in
//! them, so a store whose payload another store still links as a layer frees only the files
//! no other store holds. Where files have no identity to read (not Unix), each name is a file
//! of its own, freed with its folder.
//!
//! A walk keeps a few numbers per file with more than one name it finds, and a sum of the
//! others, so counting a folder of many files takes little memory.

use std::collections::HashMap;
use std::path::Path;

/// A file's identity: its device and inode.
type FileId = (u64, u64);

/// What a walk found of one file with more than one name.
#[derive(Debug, Clone, Copy)]
struct Found {
    bytes: u64,
    /// Names the file has on its file system.
    names: u64,
    /// Of these, the names the walk came across.
    names_seen: u64,
}

/// The files under one or more folders, each counted once.
#[derive(Debug, Default)]
pub struct DiskUsage {
    /// Files with more than one name, which another name may have counted already.
    linked: HashMap<FileId, Found>,
    /// Bytes of the files with one name.
    single_bytes: u64,
}

impl DiskUsage {
    /// The files under `path` (a folder, or a file).
    pub fn of(path: &Path) -> Self {
        let mut usage = Self::default();
        usage.add(path);
        usage
    }

    /// Adds the files under `path`, links not followed; what vanishes meanwhile counts
    /// nothing.
    pub fn add(&mut self, path: &Path) {
        let Ok(meta) = std::fs::symlink_metadata(path) else {
            return;
        };
        if meta.is_dir() {
            let Ok(entries) = std::fs::read_dir(path) else {
                return;
            };
            for entry in entries.flatten() {
                self.add(&entry.path());
            }
            return;
        }
        match identity(&meta) {
            Some((id, names)) if names > 1 => {
                let found = self.linked.entry(id).or_insert(Found {
                    bytes: meta.len(),
                    names,
                    names_seen: 0,
                });
                found.names_seen += 1;
            }
            _ => self.single_bytes = self.single_bytes.saturating_add(meta.len()),
        }
    }

    /// Bytes of the files found, each once.
    pub fn bytes(&self) -> u64 {
        let linked: u64 = self.linked.values().map(|f| f.bytes).sum();
        self.single_bytes.saturating_add(linked)
    }

    /// Bytes removing the folders added would free: of the files every name of which was
    /// found.
    pub fn freed_bytes(&self) -> u64 {
        let linked: u64 = self
            .linked
            .values()
            .filter(|f| f.names_seen >= f.names)
            .map(|f| f.bytes)
            .sum();
        self.single_bytes.saturating_add(linked)
    }
}

/// Bytes of the files under `path`, each counted once ([`DiskUsage::bytes`]).
pub fn folder_bytes(path: &Path) -> u64 {
    DiskUsage::of(path).bytes()
}

#[cfg(unix)]
fn identity(meta: &std::fs::Metadata) -> Option<(FileId, u64)> {
    use std::os::unix::fs::MetadataExt;
    Some(((meta.dev(), meta.ino()), meta.nlink()))
}

#[cfg(not(unix))]
fn identity(_: &std::fs::Metadata) -> Option<(FileId, u64)> {
    None
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    /// A store folder with its own payload of `own` bytes and, where given, the payload of
    /// `below` linked as its layer, as a growth links it.
    fn store(root: &Path, name: &str, own: usize, below: Option<&Path>) -> std::path::PathBuf {
        let folder = root.join(name);
        std::fs::create_dir_all(folder.join("index")).expect("folder");
        std::fs::write(folder.join("nodes.bin"), vec![1u8; own]).expect("payload");
        std::fs::write(folder.join("index").join("db"), [2u8; 10]).expect("index");
        if let Some(below) = below {
            std::fs::hard_link(below.join("nodes.bin"), folder.join("nodes.bin.0")).expect("link");
        }
        folder
    }

    #[test]
    fn a_layer_two_stores_share_is_counted_once_and_freed_with_the_last_of_them() {
        let dir = tempfile::tempdir().expect("tempdir");
        let first = store(dir.path(), "first", 1000, None);
        let grown = store(dir.path(), "grown", 300, Some(&first));
        assert_eq!(folder_bytes(&first), 1010);
        // Each folder alone holds the layer; together they hold it once.
        assert_eq!(folder_bytes(&grown), 1310);
        assert_eq!(folder_bytes(dir.path()), 1320);
        let mut both = DiskUsage::of(&first);
        both.add(&grown);
        assert_eq!((both.bytes(), both.freed_bytes()), (1320, 1320));

        // Either store removed alone frees only the files the other does not link.
        assert_eq!(DiskUsage::of(&first).freed_bytes(), 10);
        assert_eq!(DiskUsage::of(&grown).freed_bytes(), 310);
        std::fs::remove_dir_all(&first).expect("the first store removed");
        assert_eq!(folder_bytes(dir.path()), 1310, "the layer stays");
        assert_eq!(DiskUsage::of(&grown).freed_bytes(), 1310);
        assert_eq!(folder_bytes(&dir.path().join("missing")), 0);
    }
}

//! Datasets of several files against a real state database: folders registered, uploads
//! composed, shared files kept until their last dataset goes.

use std::path::Path;
use std::sync::Arc;

use crate::service::{hash_file, Daemon, DaemonConfig};

fn open(dir: &Path) -> Arc<Daemon> {
    let mut config = DaemonConfig::new(dir.join("data"));
    config.data_roots = vec![dir.join("roots")];
    Daemon::open(config).expect("open")
}

/// Writes `bytes` as `name` under the data root.
fn root_file(dir: &Path, name: &str, bytes: &[u8]) {
    let path = dir.join("roots").join(name);
    std::fs::create_dir_all(path.parent().expect("parent")).expect("folders");
    std::fs::write(path, bytes).expect("file");
}

/// An upload of `bytes` named `name`, as the gRPC layer finishes one.
fn upload(daemon: &Daemon, name: &str, bytes: &[u8]) -> crate::model::Dataset {
    let temp = daemon.upload_path();
    std::fs::create_dir_all(temp.parent().expect("parent")).expect("uploads");
    std::fs::write(&temp, bytes).expect("write");
    let (sha256, size) = hash_file(&temp).expect("hash");
    daemon
        .finish_upload(&temp, name, sha256, size)
        .expect("finish")
}

#[test]
fn a_folder_registers_as_one_dataset_of_its_files_in_order() {
    let folder = tempfile::tempdir().expect("tempdir");
    let dir = folder.path();
    root_file(dir, "campaign/b.laz", b"tile b");
    root_file(dir, "campaign/a.las", b"tile a");
    root_file(dir, "campaign/sub/c.las", b"tile c");
    root_file(dir, "campaign/readme.txt", b"not a tile");
    root_file(dir, "single.las", b"tile a");
    let daemon = open(dir);
    let dataset = daemon
        .register_dataset(&["campaign".into()], "")
        .expect("register");
    let names: Vec<String> = dataset.files().into_iter().map(|f| f.name).collect();
    assert_eq!(names, ["a.las", "b.laz", "c.las"]);
    assert_eq!(dataset.size_bytes, 18);
    assert_eq!(dataset.name, "campaign");
    // The same content is the same dataset; one file keeps its own hash as the id.
    let again = daemon
        .register_dataset(&["campaign".into()], "other name")
        .expect("again");
    assert_eq!(again.id, dataset.id);
    let single = daemon
        .register_dataset(&["single.las".into()], "")
        .expect("single");
    assert_eq!(single.files().len(), 1);
    assert_eq!(single.sha256, single.files()[0].sha256);
    assert_ne!(single.id, dataset.id);
    // Several paths, a file among folders.
    let mixed = daemon
        .register_dataset(&["single.las".into(), "campaign/sub".into()], "")
        .expect("mixed");
    assert_eq!(mixed.files().len(), 2);
    // Outside the roots, empty folders and missing paths are refused.
    std::fs::create_dir_all(dir.join("roots/empty")).expect("empty");
    for bad in ["/etc", "empty", "missing"] {
        assert!(daemon.register_dataset(&[bad.into()], "").is_err(), "{bad}");
    }
}

#[test]
fn uploads_compose_and_share_their_files_until_the_last_dataset_goes() {
    let folder = tempfile::tempdir().expect("tempdir");
    let daemon = open(folder.path());
    let a = upload(&daemon, "a.laz", b"LASF tile a");
    let b = upload(&daemon, "b.las", b"LASF tile b");
    let both = daemon
        .compose_dataset(&[a.id.clone(), b.id.clone(), a.id.clone()], "")
        .expect("compose");
    assert_eq!(both.files().len(), 2, "each file once");
    assert_eq!(both.size_bytes, a.size_bytes + b.size_bytes);
    assert_eq!(
        daemon
            .state
            .uploaded_bytes(&daemon.config.uploads_dir())
            .expect("bytes"),
        a.size_bytes + b.size_bytes,
        "a shared file counts once against the quota"
    );
    assert!(daemon.compose_dataset(&["ds-missing".into()], "").is_err());
    assert!(daemon.compose_dataset(&[], "").is_err());

    // Deleting a keeps its file for `both`; deleting `both` then removes it.
    daemon.delete_dataset(&a.id).expect("delete a");
    assert!(a.path.is_file(), "still a file of another dataset");
    daemon.delete_dataset(&both.id).expect("delete both");
    assert!(!a.path.exists(), "no dataset has it any more");
    assert!(b.path.is_file(), "b is still its own dataset");
}

/// Files hashed together come back in their order, each as hashed alone, a missing one as
/// an error in its place, and every size counted once.
#[test]
fn files_hashed_together_are_each_hashed_as_alone() {
    use std::sync::atomic::{AtomicU64, Ordering};
    let folder = tempfile::tempdir().expect("tempdir");
    let mut paths: Vec<_> = (0..7u8)
        .map(|i| {
            let path = folder.path().join(format!("f{i}"));
            std::fs::write(&path, vec![i; 1000 + usize::from(i) * 4099]).expect("file");
            path
        })
        .collect();
    paths.insert(3, folder.path().join("missing"));
    let counted = AtomicU64::new(0);
    let together = crate::service::hash_files(&paths, &|size| {
        counted.fetch_add(size, Ordering::Relaxed);
    });
    assert_eq!(together.len(), paths.len());
    let mut total = 0;
    for (path, hashed) in paths.iter().zip(&together) {
        match (hash_file(path), hashed) {
            (Ok(alone), Ok(hashed)) => {
                assert_eq!(&alone, hashed, "{}", path.display());
                total += alone.1;
            }
            (Err(_), Err(_)) => {}
            (alone, hashed) => panic!("{}: {alone:?} alone, {hashed:?} together", path.display()),
        }
    }
    assert_eq!(counted.load(Ordering::Relaxed), total);
}

//! The files of a dataset as a user names them: LAS/LAZ files and folders of them, found
//! anywhere (the CLI) or only inside given folders (a server's data roots); and the one way a
//! dataset's file is opened.

use std::collections::HashSet;
use std::fs::File;
use std::io;
use std::path::{Path, PathBuf};

use super::IngestError;

/// Where a dataset's files may lie.
#[derive(Debug, Clone, Copy)]
pub enum FileScope<'a> {
    /// Anywhere, through any symbolic link: the files a user names on their own machine. Paths
    /// are kept as named.
    Anywhere,
    /// Only inside these folders (a server's data roots): every file and folder reached, through
    /// symbolic links too, must resolve to a path inside one of them. Paths are kept resolved
    /// (canonical, without symbolic links), so a file is later opened without following any.
    Within(&'a [PathBuf]),
}

/// Whether a path that leads to a dataset's file may be a symbolic link when it is opened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Symlinks {
    /// Followed: a path a user named.
    Follow,
    /// Refused (`O_NOFOLLOW`): a resolved path a server stored, which a symbolic link put in
    /// its place since must not redirect.
    Refuse,
}

/// Opens a dataset's file for reading, refusing anything but a regular file. The open itself
/// is non-blocking (`O_NONBLOCK`), because opening a FIFO waits for a writer forever and
/// opening a device can block or act on the device; the opened file's own metadata then decides,
/// so a file swapped for a special one after any earlier check is refused all the same. On a
/// regular file `O_NONBLOCK` changes nothing about reads.
pub fn open_dataset_file(path: &Path, symlinks: Symlinks) -> io::Result<File> {
    // Checked before opening too, so that a device or a FIFO is never opened at all.
    let before = match symlinks {
        Symlinks::Follow => std::fs::metadata(path)?,
        Symlinks::Refuse => std::fs::symlink_metadata(path)?,
    };
    regular_file(&before.file_type())?;
    let file = open_without_blocking(path, symlinks)?;
    regular_file(&file.metadata()?.file_type())?;
    Ok(file)
}

#[cfg(unix)]
fn open_without_blocking(path: &Path, symlinks: Symlinks) -> io::Result<File> {
    use rustix::fs::{Mode, OFlags};
    let mut flags = OFlags::RDONLY | OFlags::NONBLOCK | OFlags::CLOEXEC;
    if symlinks == Symlinks::Refuse {
        flags |= OFlags::NOFOLLOW;
    }
    match rustix::fs::open(path, flags, Mode::empty()) {
        Ok(fd) => Ok(File::from(fd)),
        Err(rustix::io::Errno::LOOP) if symlinks == Symlinks::Refuse => Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            "is a symbolic link, not the regular file it was",
        )),
        Err(errno) => Err(errno.into()),
    }
}

#[cfg(not(unix))]
fn open_without_blocking(path: &Path, _: Symlinks) -> io::Result<File> {
    File::open(path)
}

/// An error unless `file_type` is a regular file's, saying what it is instead.
fn regular_file(file_type: &std::fs::FileType) -> io::Result<()> {
    if file_type.is_file() {
        return Ok(());
    }
    Err(io::Error::new(
        io::ErrorKind::InvalidInput,
        format!("is not a regular file ({})", kind_of(file_type)),
    ))
}

/// What a file that is not a regular one is, in words.
fn kind_of(file_type: &std::fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if file_type.is_fifo() {
            return "a FIFO";
        }
        if file_type.is_socket() {
            return "a socket";
        }
        if file_type.is_block_device() || file_type.is_char_device() {
            return "a device";
        }
    }
    if file_type.is_dir() {
        "a folder"
    } else if file_type.is_symlink() {
        "a symbolic link"
    } else {
        "a special file"
    }
}

/// The LAS/LAZ files `inputs` name, anywhere ([`FileScope::Anywhere`]); see
/// [`dataset_files_in`].
pub fn dataset_files(inputs: &[PathBuf]) -> Result<Vec<PathBuf>, IngestError> {
    dataset_files_in(inputs, FileScope::Anywhere)
}

/// The LAS/LAZ files `inputs` name: each file as it is, each folder's `.las` and `.laz` files
/// (in its subfolders too, hidden ones left out), sorted by name within a folder and without
/// repeats.
///
/// Symbolic links are resolved: a folder reached twice (a link back to a folder above it, or
/// two links to one folder) is walked once, so a loop ends. Only regular files are taken: a
/// `.las`/`.laz` name that is a FIFO, a socket or a device is an error naming it, and it is
/// never opened. With [`FileScope::Within`], a file or folder that resolves outside the scope's
/// folders (through a symbolic link) is an error naming the link, never followed further.
/// A folder without any file is an error naming it.
pub fn dataset_files_in(
    inputs: &[PathBuf],
    scope: FileScope<'_>,
) -> Result<Vec<PathBuf>, IngestError> {
    let roots: Option<Vec<PathBuf>> = match scope {
        FileScope::Anywhere => None,
        FileScope::Within(roots) => Some(
            roots
                .iter()
                .filter_map(|root| std::fs::canonicalize(root).ok())
                .collect(),
        ),
    };
    let mut walk = Walk {
        roots,
        files: Vec::new(),
        folders_walked: HashSet::new(),
    };
    for input in inputs {
        let resolved = walk.resolve(input)?;
        let metadata = std::fs::metadata(&resolved).map_err(|error| IngestError::Io {
            path: input.clone(),
            error,
        })?;
        if metadata.is_dir() {
            let before = walk.files.len();
            walk.folder(input, &resolved)?;
            if walk.files.len() == before {
                return Err(IngestError::NoFilesInFolder {
                    path: input.clone(),
                });
            }
        } else if metadata.is_file() {
            walk.take(input, resolved);
        } else {
            return Err(not_regular(input, &metadata.file_type()));
        }
    }
    let mut seen = HashSet::new();
    walk.files
        .retain(|file| seen.insert(std::fs::canonicalize(file).unwrap_or_else(|_| file.clone())));
    Ok(walk.files)
}

fn not_regular(path: &Path, file_type: &std::fs::FileType) -> IngestError {
    IngestError::NotRegularFile {
        path: path.to_owned(),
        kind: kind_of(file_type),
    }
}

fn is_point_file(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("las") || e.eq_ignore_ascii_case("laz"))
}

/// One walk over a dataset's inputs.
struct Walk {
    /// The canonical folders everything must resolve into; None: anywhere.
    roots: Option<Vec<PathBuf>>,
    files: Vec<PathBuf>,
    /// Canonical folders already walked.
    folders_walked: HashSet<PathBuf>,
}

impl Walk {
    /// Where `named` leads, every symbolic link resolved; an error when that is outside the
    /// roots.
    fn resolve(&self, named: &Path) -> Result<PathBuf, IngestError> {
        let resolved = std::fs::canonicalize(named).map_err(|error| IngestError::Io {
            path: named.to_owned(),
            error,
        })?;
        match &self.roots {
            Some(roots) if !roots.iter().any(|root| resolved.starts_with(root)) => {
                tracing::warn!(
                    path = %named.display(),
                    target = %resolved.display(),
                    "refused: a symbolic link leads outside the data roots"
                );
                Err(IngestError::OutsideRoots {
                    path: named.to_owned(),
                })
            }
            _ => Ok(resolved),
        }
    }

    /// Takes a regular file: as named, or resolved within roots.
    fn take(&mut self, named: &Path, resolved: PathBuf) {
        self.files.push(match self.roots {
            None => named.to_owned(),
            Some(_) => resolved,
        });
    }

    /// Takes the point files of the folder `named`, which resolves to `resolved`, and of its
    /// subfolders.
    fn folder(&mut self, named: &Path, resolved: &Path) -> Result<(), IngestError> {
        if !self.folders_walked.insert(resolved.to_owned()) {
            tracing::debug!(folder = %named.display(), "already walked (a symbolic link loop or a second link)");
            return Ok(());
        }
        let io_error = |error| IngestError::Io {
            path: named.to_owned(),
            error,
        };
        let mut entries = std::fs::read_dir(resolved)
            .map_err(io_error)?
            .map(|entry| entry.map(|e| (e.file_name(), e.file_type())))
            .collect::<Result<Vec<_>, _>>()
            .map_err(io_error)?;
        entries.sort_by(|(a, _), (b, _)| a.cmp(b));
        for (name, file_type) in entries {
            if name.to_str().is_some_and(|n| n.starts_with('.')) {
                continue;
            }
            let entry = named.join(&name);
            let file_type = file_type.map_err(|error| IngestError::Io {
                path: entry.clone(),
                error,
            })?;
            let (file_type, entry_resolved) = if file_type.is_symlink() {
                let target = match self.resolve(&entry) {
                    Ok(target) => target,
                    // A broken link that is not named as a point file may have been anything:
                    // it adds nothing.
                    Err(IngestError::Io { .. }) if !is_point_file(&entry) => continue,
                    Err(error) => return Err(error),
                };
                let metadata = std::fs::metadata(&target).map_err(|error| IngestError::Io {
                    path: entry.clone(),
                    error,
                })?;
                (metadata.file_type(), target)
            } else {
                (file_type, resolved.join(&name))
            };
            if file_type.is_dir() {
                self.folder(&entry, &entry_resolved)?;
            } else if is_point_file(&entry) {
                if !file_type.is_file() {
                    return Err(not_regular(&entry, &file_type));
                }
                self.take(&entry, entry_resolved);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(files: &[PathBuf], root: &Path) -> Vec<String> {
        files
            .iter()
            .map(|f| f.strip_prefix(root).expect("inside").display().to_string())
            .collect()
    }

    #[test]
    fn folders_give_their_point_files_sorted_and_once() {
        let dir = tempfile::tempdir().expect("tempdir");
        let root = dir.path();
        std::fs::create_dir_all(root.join("b/deeper")).expect("dirs");
        std::fs::create_dir_all(root.join(".hidden")).expect("dirs");
        for name in [
            "b/deeper/t3.LAZ",
            "a.las",
            "b/t2.laz",
            "notes.txt",
            ".hidden/x.las",
        ] {
            std::fs::write(root.join(name), b"x").expect("file");
        }
        let files = dataset_files(&[root.to_path_buf(), root.join("a.las")]).expect("files");
        assert_eq!(
            names(&files, root),
            ["a.las", "b/deeper/t3.LAZ", "b/t2.laz"]
        );

        std::fs::create_dir_all(root.join("empty")).expect("dir");
        let error = dataset_files(&[root.join("empty")]).expect_err("empty folder");
        assert!(
            error.to_string().contains("no .las or .laz file"),
            "{error}"
        );
    }

    #[cfg(unix)]
    fn mkfifo(path: &Path) {
        rustix::fs::mknodat(
            rustix::fs::CWD,
            path,
            rustix::fs::FileType::Fifo,
            rustix::fs::Mode::from_raw_mode(0o600),
            0,
        )
        .expect("mkfifo");
    }

    /// A data root with a file, and a folder beside it (outside the root) with another.
    #[cfg(unix)]
    fn root_and_outside() -> (tempfile::TempDir, PathBuf, PathBuf) {
        let dir = tempfile::tempdir().expect("tempdir");
        let base = std::fs::canonicalize(dir.path()).expect("canonical");
        let (root, outside) = (base.join("root"), base.join("outside"));
        std::fs::create_dir_all(root.join("tiles")).expect("dirs");
        std::fs::create_dir_all(&outside).expect("dirs");
        std::fs::write(root.join("tiles/a.las"), b"x").expect("file");
        std::fs::write(outside.join("secret.las"), b"secret").expect("file");
        (dir, root, outside)
    }

    #[cfg(unix)]
    #[test]
    fn symbolic_links_out_of_the_roots_are_refused_naming_the_link() {
        use std::os::unix::fs::symlink;
        let (_dir, root, outside) = root_and_outside();
        let roots = [root.clone()];
        symlink(outside.join("secret.las"), root.join("tiles/b.las")).expect("file link");
        let error = dataset_files_in(&[root.join("tiles")], FileScope::Within(&roots))
            .expect_err("a file link out of the roots");
        assert!(matches!(error, IngestError::OutsideRoots { .. }), "{error}");
        assert!(error.to_string().contains("tiles/b.las"), "{error}");
        assert!(
            !error.to_string().contains("secret"),
            "the target is never named: {error}"
        );
        std::fs::remove_file(root.join("tiles/b.las")).expect("remove");

        symlink(&outside, root.join("tiles/more")).expect("folder link");
        let error = dataset_files_in(std::slice::from_ref(&root), FileScope::Within(&roots))
            .expect_err("a folder link out of the roots");
        assert!(error.to_string().contains("tiles/more"), "{error}");
        // Named directly, a link out of the roots is refused too.
        let error = dataset_files_in(
            &[root.join("tiles/more/secret.las")],
            FileScope::Within(&roots),
        )
        .expect_err("named directly");
        assert!(matches!(error, IngestError::OutsideRoots { .. }), "{error}");

        // The CLI follows the same links wherever they lead, keeping the names it was given.
        let files = dataset_files(std::slice::from_ref(&root)).expect("anywhere");
        assert_eq!(
            names(&files, &root),
            ["tiles/a.las", "tiles/more/secret.las"]
        );
    }

    #[cfg(unix)]
    #[test]
    fn links_inside_the_roots_are_taken_resolved_and_loops_end() {
        use std::os::unix::fs::symlink;
        let (_dir, root, _outside) = root_and_outside();
        let roots = [root.clone()];
        std::fs::create_dir_all(root.join("other")).expect("dir");
        std::fs::write(root.join("other/c.laz"), b"x").expect("file");
        symlink(root.join("other/c.laz"), root.join("tiles/link.laz")).expect("file link");
        symlink(&root, root.join("tiles/loop")).expect("a link to a folder above");
        symlink("self", root.join("tiles/self")).expect("a link to itself");
        let files = dataset_files_in(&[root.join("tiles")], FileScope::Within(&roots))
            .expect("inside the roots");
        // Resolved paths, each file once, the loop walked once.
        assert_eq!(names(&files, &root), ["tiles/a.las", "other/c.laz"]);
        let anywhere = dataset_files(&[root.join("tiles")]).expect("anywhere");
        assert_eq!(names(&anywhere, &root), ["tiles/a.las", "tiles/link.laz"]);
    }

    #[cfg(unix)]
    #[test]
    fn special_files_are_refused_without_being_opened() {
        let (_dir, root, _outside) = root_and_outside();
        let roots = [root.clone()];
        mkfifo(&root.join("tiles/x.las"));
        // A FIFO opened for reading would wait for a writer: these return at once.
        let error =
            dataset_files_in(&[root.join("tiles")], FileScope::Within(&roots)).expect_err("a FIFO");
        assert!(
            error
                .to_string()
                .ends_with("x.las: not a regular file (a FIFO)"),
            "{error}"
        );
        let error = dataset_files(&[root.join("tiles/x.las")]).expect_err("named directly");
        assert!(
            matches!(error, IngestError::NotRegularFile { .. }),
            "{error}"
        );
        let error = open_dataset_file(&root.join("tiles/x.las"), Symlinks::Follow)
            .expect_err("never opened");
        assert!(error.to_string().contains("a FIFO"), "{error}");
        // Another FIFO not named as a point file is no part of a dataset.
        std::fs::remove_file(root.join("tiles/x.las")).expect("remove");
        mkfifo(&root.join("tiles/pipe"));
        let files = dataset_files_in(&[root.join("tiles")], FileScope::Within(&roots))
            .expect("the FIFO is not a point file");
        assert_eq!(names(&files, &root), ["tiles/a.las"]);
    }

    #[cfg(unix)]
    #[test]
    fn a_stored_path_replaced_by_a_link_is_not_followed() {
        use std::os::unix::fs::symlink;
        let (_dir, root, outside) = root_and_outside();
        let path = root.join("tiles/a.las");
        let file = open_dataset_file(&path, Symlinks::Refuse).expect("a regular file");
        assert_eq!(file.metadata().expect("metadata").len(), 1);
        std::fs::remove_file(&path).expect("remove");
        symlink(outside.join("secret.las"), &path).expect("link");
        let error = open_dataset_file(&path, Symlinks::Refuse).expect_err("a link");
        assert!(error.to_string().contains("symbolic link"), "{error}");
        assert!(open_dataset_file(&path, Symlinks::Follow).is_ok());
        let error = open_dataset_file(&root, Symlinks::Follow).expect_err("a folder");
        assert!(error.to_string().contains("a folder"), "{error}");
    }
}

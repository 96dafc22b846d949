//! The files of a dataset as a user names them: LAS/LAZ files and folders of them.

use std::path::{Path, PathBuf};

use super::IngestError;

/// The LAS/LAZ files `inputs` name: each file as it is, each folder's `.las` and `.laz` files
/// (in its subfolders too, hidden ones left out), sorted by path within a folder and without
/// repeats. A folder without any is an error naming it.
pub fn dataset_files(inputs: &[PathBuf]) -> Result<Vec<PathBuf>, IngestError> {
    let mut files = Vec::new();
    for input in inputs {
        if input.is_dir() {
            let before = files.len();
            collect_folder(input, &mut files)?;
            if files.len() == before {
                return Err(IngestError::NoFilesInFolder {
                    path: input.clone(),
                });
            }
        } else {
            files.push(input.clone());
        }
    }
    let mut seen = std::collections::HashSet::new();
    files.retain(|file| seen.insert(std::fs::canonicalize(file).unwrap_or_else(|_| file.clone())));
    Ok(files)
}

fn is_point_file(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("las") || e.eq_ignore_ascii_case("laz"))
}

fn collect_folder(folder: &Path, files: &mut Vec<PathBuf>) -> Result<(), IngestError> {
    let io_error = |error| IngestError::Io {
        path: folder.to_owned(),
        error,
    };
    let mut entries = std::fs::read_dir(folder)
        .map_err(io_error)?
        .map(|entry| entry.map(|e| e.path()))
        .collect::<Result<Vec<_>, _>>()
        .map_err(io_error)?;
    entries.sort();
    for path in entries {
        let hidden = path
            .file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| n.starts_with('.'));
        if hidden {
            continue;
        }
        if path.is_dir() {
            collect_folder(&path, files)?;
        } else if is_point_file(&path) {
            files.push(path);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let names: Vec<String> = files
            .iter()
            .map(|f| f.strip_prefix(root).expect("inside").display().to_string())
            .collect();
        assert_eq!(names, ["a.las", "b/deeper/t3.LAZ", "b/t2.laz"]);

        std::fs::create_dir_all(root.join("empty")).expect("dir");
        let error = dataset_files(&[root.join("empty")]).expect_err("empty folder");
        assert!(
            error.to_string().contains("no .las or .laz file"),
            "{error}"
        );
    }
}

//! The source paths the documents name exist: every file path in a code span of
//! ARCHITECTURE.md, README.md, BENCHMARKS.md, the design notes, the guide's pages and the
//! performance notes' index (`lod/layers.rs`, `render/src/source/camera_first.rs`,
//! `deploy/test.sh`) is a file of the repository, named from its root or by its tail, and every
//! folder named from one of the repository's top-level folders (`render/src/lod/`) is one of its
//! folders; their relative links lead to files and headings that exist. A measured finding in
//! docs/perf names files as they were when measured, so only its index is held here.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use super::{code_of, pages, workspace};

/// How a file a document names ends: the languages of the repository's sources and scripts.
const SOURCE_EXTENSIONS: [&str; 7] = [".rs", ".wgsl", ".proto", ".sh", ".toml", ".py", ".js"];

/// The documents whose paths are held to the tree.
fn documents() -> Vec<(PathBuf, String)> {
    pages(
        &[
            "ARCHITECTURE.md",
            "README.md",
            "BENCHMARKS.md",
            "docs/perf/README.md",
        ],
        &["docs/design", "docs/guide"],
    )
}

/// The files and folders of a tree, relative to its root with `/` between names; folders end
/// in `/`.
struct Tree {
    files: BTreeSet<String>,
    folders: BTreeSet<String>,
}

impl Tree {
    /// The tree under `root` without `.git` and what the root's `.gitignore` anchors to the
    /// root (`/target`, `/frames`): build outputs that a clean checkout lacks.
    fn walk(root: &Path) -> Self {
        let ignored: BTreeSet<String> = std::fs::read_to_string(root.join(".gitignore"))
            .unwrap_or_default()
            .lines()
            .filter_map(|line| line.trim().strip_prefix('/'))
            .map(|path| path.trim_end_matches('/').to_owned())
            .collect();
        let mut tree = Self {
            files: BTreeSet::new(),
            folders: BTreeSet::new(),
        };
        let mut pending = vec![String::new()];
        while let Some(folder) = pending.pop() {
            let entries = std::fs::read_dir(root.join(&folder))
                .unwrap_or_else(|e| panic!("{}: {e}", root.join(&folder).display()));
            for entry in entries {
                let entry = entry.expect("a folder's entry");
                let path = format!("{folder}{}", entry.file_name().to_string_lossy());
                if path == ".git" || ignored.contains(&path) {
                    continue;
                }
                if entry.file_type().expect("an entry's type").is_dir() {
                    tree.folders.insert(format!("{path}/"));
                    pending.push(format!("{path}/"));
                } else {
                    tree.files.insert(path);
                }
            }
        }
        tree
    }

    /// Whether `folder` (ending in `/`) starts at one of the tree's top-level folders: only
    /// those are the repository's; `frames/` or `tiles/` alone are folders the product writes.
    fn starts_at_top(&self, folder: &str) -> bool {
        let top = folder.split('/').next().unwrap_or_default();
        !top.is_empty() && self.folders.contains(&format!("{top}/"))
    }

    /// Whether `path` names a file of the tree from its root or as the tail of one.
    fn has_file(&self, path: &str) -> bool {
        let tail = format!("/{path}");
        self.files.contains(path) || self.files.iter().any(|file| file.ends_with(&tail))
    }
}

/// The word of a code span as a path the check holds to the tree, or `None` where it is no
/// such path: no source extension or trailing `/`, a URL, a path outside the repository
/// (`/etc/...`, `~/...`, `../...`), a glob or placeholder (`gallery*.sh`, `<name>.toml`,
/// `DATA/lod/`, `JOB_ID.toml`), or a word that is not a path at all (`--config=x.toml`).
fn checked_path(word: &str) -> Option<&str> {
    let word = word.trim_matches(|c| matches!(c, '"' | '\'' | '(' | ')' | ',' | ';' | ':'));
    let word = word.strip_prefix("./").unwrap_or(word);
    let looks_like_a_path = !word.is_empty()
        && word
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.' | '/'));
    let outside = word.starts_with('/') || word.starts_with("..");
    let named = word.ends_with('/') || SOURCE_EXTENSIONS.iter().any(|e| word.ends_with(e));
    let placeholder = word.split('/').any(|name| {
        let stem = name.split('.').next().unwrap_or_default();
        stem.chars().filter(|c| c.is_ascii_alphabetic()).count() >= 2
            && !stem.chars().any(|c| c.is_ascii_lowercase())
    });
    (looks_like_a_path && named && !outside && !placeholder).then_some(word)
}

/// The code spans of a page's prose (its blocks hold commands and files the user writes), each
/// with the line it starts on.
fn spans_with_lines(text: &str) -> Vec<(usize, String)> {
    let prose = code_of(text).prose;
    let mut spans = Vec::new();
    let mut line = 1;
    for (i, piece) in prose.split('`').enumerate() {
        if i % 2 == 1 {
            spans.push((line, piece.replace('\n', " ")));
        }
        line += piece.matches('\n').count();
    }
    spans
}

/// What the check found: how many paths it held to the tree, and each one missing as
/// `document:line: path`.
struct Findings {
    checked: usize,
    problems: Vec<String>,
}

/// Every path of `documents` held to `tree`; a folder only where it starts at one of the
/// tree's top-level folders, and then from the root.
fn path_findings(documents: &[(PathBuf, String)], root: &Path, tree: &Tree) -> Findings {
    let mut findings = Findings {
        checked: 0,
        problems: Vec::new(),
    };
    for (page, text) in documents {
        let shown = page.strip_prefix(root).unwrap_or(page).display();
        for (line, span) in spans_with_lines(text) {
            for path in span.split_whitespace().filter_map(checked_path) {
                let found = match path.ends_with('/') {
                    true if !tree.starts_at_top(path) => continue,
                    true => tree.folders.contains(path),
                    false => tree.has_file(path),
                };
                findings.checked += 1;
                if !found {
                    findings
                        .problems
                        .push(format!("{shown}:{line}: `{path}` is not in the repository"));
                }
            }
        }
    }
    findings
}

#[test]
fn every_source_path_the_documents_name_exists() {
    let root = workspace();
    let findings = path_findings(&documents(), &root, &Tree::walk(&root));
    assert!(
        findings.checked > 100,
        "the documents name hundreds of source files; {} found",
        findings.checked
    );
    assert!(
        findings.problems.is_empty(),
        "{} path(s) the documents name that the repository lacks (give the file's current \
         path, or drop the mention):\n{}",
        findings.problems.len(),
        findings.problems.join("\n")
    );
}

#[test]
fn a_missing_path_is_named_with_its_line() {
    let dir = tempfile::tempdir().expect("a scratch folder");
    let root = dir.path();
    std::fs::create_dir_all(root.join("render/src/lod")).expect("make the folders");
    std::fs::create_dir_all(root.join("frames/shot")).expect("make an ignored folder");
    std::fs::write(root.join("render/src/lod/layers.rs"), "").expect("write a source");
    std::fs::write(root.join("frames/shot/kept.rs"), "").expect("write an ignored file");
    std::fs::write(root.join(".gitignore"), "/frames\n").expect("write the ignore file");
    let text = "# A design\n\n\
        `lod/layers.rs` and `render/src/lod/` exist; `render/src/lod/gone.rs` does not.\n\
        ```sh\n\
        pointfarm render --camera-path missing.toml `in/a/block.rs`\n\
        ```\n\
        Skipped: `s3://bucket/x.toml`, `/etc/pointfarm/config.toml`, `DATA/lod/`,\n\
        `gallery*.sh`, `frames/`, `tiles/`, `--config=x.toml`, `CACHE-DIR/ranges/`.\n\
        Missing: `render/src/raster/`, (`shot/kept.rs`) and `point.wgsl`\n\
        `render/src/lod/layers.rs` (`lod/layers.rs`) and\n\
        a span `split over\n\
        two lines/gone.proto`.\n";
    let page = root.join("docs/design.md");
    let findings = path_findings(&[(page, text.to_owned())], root, &Tree::walk(root));
    let expected = [
        "docs/design.md:3: `render/src/lod/gone.rs` is not in the repository",
        "docs/design.md:9: `render/src/raster/` is not in the repository",
        "docs/design.md:9: `shot/kept.rs` is not in the repository",
        "docs/design.md:9: `point.wgsl` is not in the repository",
        "docs/design.md:11: `lines/gone.proto` is not in the repository",
    ];
    assert_eq!(findings.problems, expected);
    assert_eq!(findings.checked, 9, "{:#?}", findings.problems);
}

#[test]
fn every_link_of_the_documents_leads_somewhere() {
    let problems = super::link_problems(&documents());
    assert!(
        problems.is_empty(),
        "{} broken link(s):\n{}",
        problems.len(),
        problems.join("\n")
    );
}

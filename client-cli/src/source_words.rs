//! What a local render's frame source tells, in words: a line for each step, and a spinner
//! while the dataset is read or its levels of detail are built.

use std::cell::RefCell;

use indicatif::ProgressBar;
use pointfarm_render::source::{LevelsFrom, SourceEvent};

use crate::output::Reporter;

/// Says a frame source's events about one input (its label before every line).
pub struct SourceWords {
    reporter: Reporter,
    label: String,
    /// The spinner of the step under way, cleared by the next event.
    spinner: RefCell<Option<ProgressBar>>,
}

impl SourceWords {
    /// Lines about `label` (the inputs), on stderr with `--json`.
    pub fn new(json: bool, label: String) -> Self {
        Self {
            reporter: Reporter::new(json),
            label,
            spinner: RefCell::new(None),
        }
    }

    /// Says `line` about the input.
    pub fn say(&self, line: &str) {
        self.clear();
        self.reporter.say(format_args!("{}: {line}", self.label));
    }

    /// Tells `event`.
    pub fn tell(&self, event: SourceEvent<'_>) {
        match event {
            SourceEvent::Reading { files } => self.spin(match files {
                [one] => format!("reading {}", one.display()),
                many => format!("reading {} files", many.len()),
            }),
            SourceEvent::Read {
                points,
                files,
                colors,
                ms,
                ..
            } => self.say(&format!(
                "{points} points in {files} file{}, {colors}, read in {ms:.0} ms",
                plural(files)
            )),
            SourceEvent::Preview {
                points,
                points_in_files,
                stored_nodes,
                stored_points,
                colors,
            } => {
                let what = match stored_nodes {
                    0 => "chunk starts".to_string(),
                    nodes => format!(
                        "{} chunk starts and {stored_points} points of {nodes} stored nodes",
                        points.saturating_sub(stored_points)
                    ),
                };
                self.say(&format!(
                    "preview: {points} of the {points_in_files} points ({what}), {colors}"
                ));
            }
            SourceEvent::Filtered { kept: 0, points } => self.say(&format!(
                "the filter keeps none of the {points} points: the frames show only the \
                 background"
            )),
            SourceEvent::Filtered { kept, points } => self.say(&format!(
                "the filter keeps {kept} of {points} points ({:.1}%)",
                kept as f64 * 100.0 / points.max(1) as f64
            )),
            SourceEvent::BuildingFirst { stage, files } => self.say(&format!(
                "camera first: building {} ({} file{}: {})",
                stage.describe(),
                files.len(),
                if files.len() == 1 { "" } else { "s" },
                names(files)
            )),
            SourceEvent::Building { points, folder } => self.spin(format!(
                "building levels of detail of {points} points (once; kept in {})",
                folder.display()
            )),
            SourceEvent::Built {
                nodes,
                points,
                seconds,
            } => self.say(&format!(
                "levels of detail: {nodes} nodes built in {seconds:.1} s, {:.2} M points/s",
                points as f64 / seconds / 1e6
            )),
            SourceEvent::Updated {
                files_added,
                files_removed,
                files_changed,
                regions_rebuilt,
                points_added,
                points_removed,
                seconds,
            } => self.say(&format!(
                "store updated: {files_added} added, {files_removed} removed, {files_changed} \
                 changed file(s): {points_added} points in, {points_removed} out, \
                 {regions_rebuilt} regions built again in {seconds:.1} s"
            )),
            SourceEvent::Rebuilding { folder, damage } => self.say(&format!(
                "levels of detail: the store in {} failed its checks ({damage}); rebuilding it",
                folder.display()
            )),
            SourceEvent::Levels {
                points,
                from,
                host_cache_bytes,
                gpu_cache_bytes,
                lod_error,
            } => {
                let from = match from {
                    LevelsFrom::Store { folder, files } => format!(
                        "{points} points in {files} file{}, levels of detail from {}",
                        plural(files),
                        folder.display()
                    ),
                    LevelsFrom::Copc {
                        nodes,
                        pages,
                        unread_pages,
                        sample_nodes,
                    } => {
                        let unread = match unread_pages {
                            0 => String::new(),
                            n => format!(", {n} more page{} read as frames reach them", plural(n)),
                        };
                        format!(
                            "{points} points, COPC: reading its hierarchy node by node ({nodes} \
                             nodes in the {pages} page{} read{unread}; {sample_nodes} nodes read \
                             for the color ranges)",
                            plural(pages)
                        )
                    }
                    LevelsFrom::Served => format!("{points} points, levels of detail served"),
                };
                self.say(&format!(
                    "{from}; node caches: host {} MiB, GPU {} MiB; pixel error {lod_error}",
                    host_cache_bytes >> 20,
                    gpu_cache_bytes >> 20,
                ));
            }
        }
    }

    fn spin(&self, message: String) {
        self.clear();
        *self.spinner.borrow_mut() = Some(crate::progress::spinner(message));
    }

    fn clear(&self) {
        if let Some(spinner) = self.spinner.borrow_mut().take() {
            spinner.finish_and_clear();
        }
    }
}

impl Drop for SourceWords {
    fn drop(&mut self) {
        self.clear();
    }
}

/// The plural ending of a count's noun: "" for one, "s" for any other count.
pub(crate) fn plural(count: usize) -> &'static str {
    if count == 1 {
        ""
    } else {
        "s"
    }
}

/// The file names of `files`, the first few of them.
pub(crate) fn names(files: &[std::path::PathBuf]) -> String {
    const SHOWN: usize = 8;
    let mut names: Vec<String> = (files.iter().take(SHOWN))
        .map(|f| {
            f.file_name()
                .map_or(f.display().to_string(), |n| n.to_string_lossy().into())
        })
        .collect();
    if files.len() > SHOWN {
        names.push(format!("and {} more", files.len() - SHOWN));
    }
    names.join(", ")
}

//! The pages a user reads held to the binary (README.md, the user guide docs/guide/*.md, the
//! operator's deploy/README.md, the gallery and the Python example's README): every
//! `pointfarm` command they show exists and takes each flag shown with it (checked against
//! the command's `--help`), and every relative link leads to a file, and a heading, that
//! exist. A user copies these commands; a renamed or removed flag fails here, listed with its
//! page. The source paths the design and reference documents name are held to the tree in
//! `paths`.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use pointfarm_tests::pointfarm_bin;

// The crate root is this file, so its module lies in a folder of its name only by saying so.
#[path = "docs_commands/paths.rs"]
mod paths;

/// The workspace's root, where README.md lies.
fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the tests crate lies in the workspace")
        .to_path_buf()
}

/// The user's pages, each with its text.
fn documents() -> Vec<(PathBuf, String)> {
    pages(
        &[
            "README.md",
            "deploy/README.md",
            "docs/gallery.md",
            "examples/python/README.md",
        ],
        &["docs/guide"],
    )
}

/// The workspace's `files` and the Markdown pages of its `folders`, each with its text.
fn pages(files: &[&str], folders: &[&str]) -> Vec<(PathBuf, String)> {
    let root = workspace();
    let mut paths: Vec<PathBuf> = files.iter().map(|page| root.join(page)).collect();
    for folder in folders {
        let mut found: Vec<PathBuf> = std::fs::read_dir(root.join(folder))
            .unwrap_or_else(|e| panic!("{folder}: {e}"))
            .map(|entry| entry.expect("a folder's entry").path())
            .filter(|path| path.extension().is_some_and(|e| e == "md"))
            .collect();
        found.sort();
        paths.extend(found);
    }
    paths
        .into_iter()
        .map(|path| {
            let text = std::fs::read_to_string(&path)
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            (path, text)
        })
        .collect()
}

/// What a page says in code: the lines of its shell blocks (a line ending in `\` joined with
/// the next) and its inline code spans, and its prose with the blocks' lines left empty (so
/// that its lines are the page's).
struct Code {
    shell_lines: Vec<String>,
    spans: Vec<String>,
    prose: String,
}

fn code_of(text: &str) -> Code {
    let mut shell_lines = Vec::new();
    let mut prose = String::new();
    // None outside a block; Some(true) in a shell block, Some(false) in another language's.
    let mut block: Option<bool> = None;
    let mut continued = String::new();
    for line in text.lines() {
        if let Some(info) = line.trim_start().strip_prefix("```") {
            block = match block {
                None => Some(matches!(info.trim(), "" | "sh" | "bash" | "console")),
                Some(_) => None,
            };
            prose.push('\n');
            continue;
        }
        if block.is_some() {
            prose.push('\n');
        }
        match block {
            Some(true) => match line.strip_suffix('\\') {
                Some(start) => {
                    continued.push_str(start);
                    continued.push(' ');
                }
                None => {
                    continued.push_str(line);
                    shell_lines.push(std::mem::take(&mut continued));
                }
            },
            Some(false) => {}
            None => {
                prose.push_str(line);
                prose.push('\n');
            }
        }
    }
    // Spans may wrap across lines of the prose.
    let flat = prose.replace('\n', " ");
    let spans = flat
        .split('`')
        .enumerate()
        .filter(|(i, _)| i % 2 == 1)
        .map(|(_, span)| span.to_owned())
        .collect();
    Code {
        shell_lines,
        spans,
        prose,
    }
}

/// The pieces of a shell line that each run one command: split at pipes, `;`, `&&` and
/// command substitutions, without the comment.
fn commands_of_line(line: &str) -> Vec<String> {
    let line = match line.find(" #") {
        Some(at) => &line[..at],
        None => line,
    };
    line.replace("$(", "|")
        .replace("&&", "|")
        .replace(';', "|")
        .split('|')
        .map(|piece| piece.trim().to_owned())
        .filter(|piece| !piece.is_empty())
        .collect()
}

/// The words of a command, quotes and brackets around them taken off.
fn words(command: &str) -> Vec<String> {
    command
        .split_whitespace()
        .map(|word| {
            word.trim_matches(|c| matches!(c, '"' | '\'' | '[' | ']' | '(' | ')' | ','))
                .to_owned()
        })
        .filter(|word| !word.is_empty())
        .collect()
}

/// A flag named by `word`: `--name` (without `=value`) or a one-letter `-x`.
fn flag_of(word: &str) -> Option<&str> {
    let name = word.split('=').next().unwrap_or(word);
    let long = name.strip_prefix("--").is_some_and(|rest| {
        rest.starts_with(|c: char| c.is_ascii_lowercase())
            && rest
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-')
    });
    let short = name.len() == 2
        && name.starts_with('-')
        && name[1..].chars().all(|c| c.is_ascii_alphabetic());
    (long || short).then_some(name)
}

/// The `--help` of each command asked about, run once.
struct Helps {
    texts: HashMap<Vec<String>, Option<String>>,
}

impl Helps {
    fn new() -> Self {
        Self {
            texts: HashMap::new(),
        }
    }

    /// The help of `pointfarm PATH...`, or `None` where there is no such command.
    fn of(&mut self, path: &[String]) -> Option<&str> {
        self.texts
            .entry(path.to_vec())
            .or_insert_with(|| {
                let output = Command::new(pointfarm_bin())
                    .args(path)
                    .arg("--help")
                    .output()
                    .expect("run pointfarm --help");
                output
                    .status
                    .success()
                    .then(|| String::from_utf8_lossy(&output.stdout).into_owned())
            })
            .as_deref()
    }

    /// The subcommands `pointfarm PATH...` lists, with their aliases.
    fn subcommands(&mut self, path: &[String]) -> Vec<String> {
        let Some(help) = self.of(path) else {
            return Vec::new();
        };
        let mut names = Vec::new();
        let mut listing = false;
        for line in help.lines() {
            if line.trim_end() == "Commands:" {
                listing = true;
                continue;
            }
            if !listing {
                continue;
            }
            if !line.starts_with("  ") {
                break;
            }
            let mut parts = line.split_whitespace();
            if let Some(name) = parts.next() {
                names.push(name.to_owned());
            }
            if let Some(at) = line.find("[alias: ") {
                let aliases = &line[at + "[alias: ".len()..];
                let aliases = aliases.split(']').next().unwrap_or_default();
                names.extend(aliases.split(',').map(|a| a.trim().to_owned()));
            }
        }
        names.retain(|name| name != "help");
        names
    }
}

/// Whether `help` lists `flag` as an option.
fn help_has(help: &str, flag: &str) -> bool {
    if flag.starts_with("--") {
        help.match_indices(flag).any(|(at, _)| {
            let after = help[at + flag.len()..].chars().next();
            !after.is_some_and(|c| c.is_ascii_alphanumeric() || c == '-')
        })
    } else {
        help.contains(&format!(" {flag}, --"))
    }
}

/// What is wrong with one command as a page shows it: `words` start at the command (after
/// `pointfarm`, or a span's first word). An empty list where the binary takes it.
fn check_command(helps: &mut Helps, words: &[String]) -> Vec<String> {
    let mut problems = Vec::new();
    let top = helps.subcommands(&[]);
    // Global options may come before the command (`pointfarm -v --log-format json serve`).
    let Some(start) = words.iter().position(|w| top.contains(w)) else {
        return problems;
    };
    let mut path = vec![words[start].clone()];
    let nested = helps.subcommands(&path);
    let mut rest = start + 1;
    if !nested.is_empty() {
        match words.get(rest) {
            Some(word) if nested.contains(word) => {
                path.push(word.clone());
                rest += 1;
            }
            Some(word) if flag_of(word).is_none() => {
                problems.push(format!("`pointfarm {}` has no command `{word}`", path[0]));
                return problems;
            }
            _ => {}
        }
    }
    let mut checks: Vec<(Vec<String>, &String)> = Vec::new();
    for word in &words[..start] {
        checks.push((Vec::new(), word));
    }
    for word in &words[rest..] {
        checks.push((path.clone(), word));
    }
    for (path, word) in checks {
        let Some(flag) = flag_of(word) else { continue };
        let Some(help) = helps.of(&path) else {
            problems.push(format!("no command `pointfarm {}`", path.join(" ")));
            break;
        };
        if !help_has(help, flag) {
            let command = match path.is_empty() {
                true => "pointfarm".to_owned(),
                false => format!("pointfarm {}", path.join(" ")),
            };
            problems.push(format!("`{command}` has no option {flag}"));
        }
    }
    problems
}

/// The commands a page shows, each as its words from the command on: the shell lines'
/// `pointfarm ...` commands and the inline spans that start with `pointfarm` or with a
/// command's name (`serve --metrics-listen`, `jobs show`).
fn commands_of(helps: &mut Helps, text: &str) -> Vec<Vec<String>> {
    let code = code_of(text);
    let mut commands = Vec::new();
    for line in &code.shell_lines {
        for command in commands_of_line(line) {
            let words = words(&command);
            if let Some(at) = binary_at(&words) {
                commands.push(words[at + 1..].to_vec());
            }
        }
    }
    commands.extend(span_commands(helps, &code.spans));
    commands
}

/// Where a command's words name the binary: `pointfarm`, or a path to it
/// (`target/release/pointfarm`), after environment assignments and prefixes such as
/// `timeout 60`, but not as an option's value (`docker run --name pointfarm`).
fn binary_at(words: &[String]) -> Option<usize> {
    (0..words.len()).find(|&at| {
        let word = &words[at];
        let names_it = word == "pointfarm" || word.ends_with("/pointfarm");
        names_it && (at == 0 || !words[at - 1].starts_with('-'))
    })
}

/// The commands among inline code spans: those that start with `pointfarm` or with the name
/// of one of its commands.
fn span_commands(helps: &mut Helps, spans: &[String]) -> Vec<Vec<String>> {
    let top = helps.subcommands(&[]);
    let mut commands = Vec::new();
    for span in spans {
        for command in commands_of_line(span) {
            let words = words(&command);
            match binary_at(&words) {
                Some(at) => commands.push(words[at + 1..].to_vec()),
                None if words.first().is_some_and(|w| top.contains(w)) => commands.push(words),
                None => {}
            }
        }
    }
    commands
}

/// Every command path of the binary: each command, and each of its subcommands.
fn command_paths(helps: &mut Helps) -> Vec<Vec<String>> {
    let mut paths = vec![Vec::new()];
    for command in helps.subcommands(&[]) {
        let path = vec![command];
        for nested in helps.subcommands(&path) {
            paths.push(vec![path[0].clone(), nested]);
        }
        paths.push(path);
    }
    paths
}

/// Every problem of every command in `documents`, each naming its page.
fn command_problems(documents: &[(PathBuf, String)]) -> Vec<String> {
    let mut helps = Helps::new();
    let mut problems = Vec::new();
    for (path, text) in documents {
        for command in commands_of(&mut helps, text) {
            for problem in check_command(&mut helps, &command) {
                problems.push(format!(
                    "{}: {problem} (in `{}`)",
                    path.display(),
                    command.join(" ")
                ));
            }
        }
    }
    problems.dedup();
    problems
}

/// The anchors of a Markdown file's headings, as GitHub makes them: lower case, spaces as
/// hyphens, every other character but letters, digits, `-` and `_` dropped.
fn anchors(text: &str) -> Vec<String> {
    code_of(text)
        .prose
        .lines()
        .filter_map(|line| {
            let heading = line.trim_start_matches('#');
            (heading.len() < line.len() && heading.starts_with(' ')).then(|| {
                heading
                    .trim()
                    .to_lowercase()
                    .chars()
                    .filter(|c| c.is_alphanumeric() || matches!(c, ' ' | '-' | '_'))
                    .map(|c| if c == ' ' { '-' } else { c })
                    .collect()
            })
        })
        .collect()
}

/// Every relative link of `documents` whose file or heading does not exist.
fn link_problems(documents: &[(PathBuf, String)]) -> Vec<String> {
    let mut problems = Vec::new();
    for (path, text) in documents {
        let prose = code_of(text).prose;
        for (at, _) in prose.match_indices("](") {
            let target = &prose[at + 2..];
            let Some(end) = target.find(')') else {
                continue;
            };
            let link = &target[..end];
            if link.contains("://") || link.starts_with("mailto:") || link.contains(' ') {
                continue;
            }
            let (file, anchor) = match link.split_once('#') {
                Some((file, anchor)) => (file, Some(anchor)),
                None => (link, None),
            };
            let file_path = match file {
                "" => path.clone(),
                file => path.parent().expect("a page's folder").join(file),
            };
            let Ok(target_text) = std::fs::read_to_string(&file_path) else {
                if !file_path.exists() {
                    problems.push(format!("{}: ({link}) leads nowhere", path.display()));
                }
                continue;
            };
            if let Some(anchor) = anchor {
                let is_markdown = file_path.extension().is_some_and(|e| e == "md");
                if is_markdown && !anchors(&target_text).iter().any(|a| a == anchor) {
                    problems.push(format!(
                        "{}: ({link}) names a heading {} lacks",
                        path.display(),
                        file_path.display()
                    ));
                }
            }
        }
    }
    problems
}

#[test]
fn every_command_the_pages_show_takes_the_flags_shown() {
    let documents = documents();
    assert!(
        documents.len() > 8,
        "the READMEs, the gallery and the guide's pages"
    );
    let problems = command_problems(&documents);
    assert!(
        problems.is_empty(),
        "{} command(s) of the pages that the binary refuses:\n{}",
        problems.len(),
        problems.join("\n")
    );
}

#[test]
fn every_command_a_help_text_names_takes_the_flags_named() {
    let mut helps = Helps::new();
    let mut problems = Vec::new();
    for path in command_paths(&mut helps) {
        let help = helps.of(&path).unwrap_or_default().replace('\n', " ");
        let spans: Vec<String> = help
            .split('`')
            .enumerate()
            .filter(|(i, _)| i % 2 == 1)
            .map(|(_, span)| span.to_owned())
            .collect();
        for command in span_commands(&mut helps, &spans) {
            for problem in check_command(&mut helps, &command) {
                problems.push(format!(
                    "pointfarm {} --help: {problem} (in `{}`)",
                    path.join(" "),
                    command.join(" ")
                ));
            }
        }
    }
    assert!(
        problems.is_empty(),
        "{} command(s) named in --help that the binary refuses:\n{}",
        problems.len(),
        problems.join("\n")
    );
}

#[test]
fn every_link_of_the_pages_leads_somewhere() {
    let problems = link_problems(&documents());
    assert!(
        problems.is_empty(),
        "{} broken link(s):\n{}",
        problems.len(),
        problems.join("\n")
    );
}

#[test]
fn an_unknown_flag_command_or_link_is_named() {
    let dir = tempfile::tempdir().expect("a scratch folder");
    let page = dir.path().join("page.md");
    let text = "# A page\n\n\
        ```sh\n\
        pointfarm render scan.laz --out x.png --no-such-flag \\\n    --supersample 2\n\
        pointfarm -v --no-such-global serve --listen 127.0.0.1:0\n\
        pointfarm jobs frobnicate JOB\n\
        docker run --name pointfarm -p 8080:8080 image serve --stop-timeout 9\n\
        timeout 60 target/release/pointfarm demo --no-such-demo-flag\n\
        ```\n\n\
        Set `worker --cache-gib` and `serve --no-such-setting`; see [here](#a-page),\n\
        [there](#no-heading) and [elsewhere](missing.md).\n";
    std::fs::write(&page, text).expect("write the page");
    let documents = vec![(page, text.to_owned())];
    let commands = command_problems(&documents);
    let expected = [
        "`pointfarm render` has no option --no-such-flag",
        "`pointfarm` has no option --no-such-global",
        "`pointfarm jobs` has no command `frobnicate`",
        "`pointfarm demo` has no option --no-such-demo-flag",
        "`pointfarm serve` has no option --no-such-setting",
    ];
    assert_eq!(commands.len(), expected.len(), "{commands:#?}");
    for (problem, expected) in commands.iter().zip(expected) {
        assert!(
            problem.contains(expected),
            "{problem} should say {expected}"
        );
    }
    let links = link_problems(&documents);
    assert_eq!(links.len(), 2, "{links:#?}");
    assert!(links[0].contains("(#no-heading)"), "{links:#?}");
    assert!(
        links[1].contains("(missing.md) leads nowhere"),
        "{links:#?}"
    );
}

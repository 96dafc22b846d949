//! The command line of a bench program: `--flag value` pairs read in order, and the exit
//! status with the error printed under the program's name.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// One flag's value, read as the flag needs it.
pub struct FlagValue<'a> {
    flag: &'a str,
    value: &'a str,
}

impl FlagValue<'_> {
    /// The value as a count, naming the flag when it is not one.
    pub fn number(&self) -> Result<u64, String> {
        self.value
            .parse::<u64>()
            .map_err(|e| format!("{} {}: {e}", self.flag, self.value))
    }

    pub fn path(&self) -> PathBuf {
        PathBuf::from(self.value)
    }

    /// The value as counts separated by commas.
    pub fn numbers(&self) -> Result<Vec<u64>, String> {
        self.value
            .split(',')
            .map(|v| {
                v.parse::<u64>()
                    .map_err(|e| format!("{} {}: {e}", self.flag, self.value))
            })
            .collect()
    }
}

/// Reads `args` as `--flag value` pairs, handing each to `apply`, which says whether it
/// knows the flag; a flag without a value or one it does not know is an error with `usage`.
pub fn parse_flags(
    args: &[String],
    usage: &str,
    mut apply: impl FnMut(&str, FlagValue) -> Result<bool, String>,
) -> Result<(), String> {
    let mut it = args.iter();
    while let Some(flag) = it.next() {
        let value = it
            .next()
            .ok_or_else(|| format!("{flag} needs a value\n{usage}"))?;
        if !apply(flag, FlagValue { flag, value })? {
            return Err(format!("unknown flag {flag}\n{usage}"));
        }
    }
    Ok(())
}

/// The LAZ files in `dir`, sorted by name: a campaign's tiles a program is pointed at.
pub fn laz_files(dir: &Path) -> Result<Vec<PathBuf>, String> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| format!("{}: {e}", dir.display()))?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|path| path.extension().is_some_and(|ext| ext == "laz"))
        .collect();
    files.sort();
    Ok(files)
}

/// The exit status of `program`'s run, printing its error if it failed.
pub fn exit_code(program: &str, outcome: Result<(), String>) -> ExitCode {
    match outcome {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("{program}: {error}");
            ExitCode::FAILURE
        }
    }
}

/// Runs the bench program `program` on this process's arguments: read by `parse`, measured
/// by `measure`; its exit status, printing its error if it failed.
pub fn run_program<A>(
    program: &str,
    parse: impl FnOnce(&[String]) -> Result<A, String>,
    measure: impl FnOnce(&A) -> Result<(), String>,
) -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    exit_code(program, parse(&args).and_then(|parsed| measure(&parsed)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn strings(args: &[&str]) -> Vec<String> {
        args.iter().map(|a| a.to_string()).collect()
    }

    fn parse(args: &[&str]) -> Result<(u64, Option<PathBuf>), String> {
        let (mut points, mut dir) = (0, None);
        parse_flags(&strings(args), "usage: x", |flag, value| {
            match flag {
                "--points" => points = value.number()?,
                "--dir" => dir = Some(value.path()),
                _ => return Ok(false),
            }
            Ok(true)
        })?;
        Ok((points, dir))
    }

    #[test]
    fn flags_are_read_in_pairs_and_bad_ones_are_named() {
        assert_eq!(
            parse(&["--points", "7", "--dir", "/tmp/a"]),
            Ok((7, Some(PathBuf::from("/tmp/a"))))
        );
        assert_eq!(parse(&[]), Ok((0, None)));
        assert_eq!(
            parse(&["--points"]),
            Err("--points needs a value\nusage: x".into())
        );
        let not_a_number = parse(&["--points", "many"]);
        assert!(
            matches!(&not_a_number, Err(e) if e.starts_with("--points many: ")),
            "{not_a_number:?}"
        );
        assert_eq!(
            parse(&["--colors", "2"]),
            Err("unknown flag --colors\nusage: x".into())
        );
    }
}

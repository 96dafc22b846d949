//! Writing the corpus: the sources into `DIR/sources`, their mutants into `DIR/mutants` as
//! `<source>--<kind>--<detail>.<las|laz>`. The same arguments give the same files, byte for
//! byte: the written sources come from seeded clouds and the flips from seeded generators.

use std::fs;
use std::path::{Path, PathBuf};

use crate::mutations::{mutants, Kind};
use crate::sources::sources;
use crate::CorpusError;

/// What was written.
#[derive(Debug, Default)]
pub struct Generated {
    pub sources: usize,
    pub mutants: usize,
    pub bytes: u64,
}

/// Writes the corpus into `dir`: the full corpus, or with `fast` the small written sources
/// and only the headline mutants (of the real scans too, when `real_dir` has them).
pub fn generate(dir: &Path, real_dir: Option<&Path>, fast: bool) -> Result<Generated, CorpusError> {
    let sources_dir = dir.join("sources");
    let mutants_dir = dir.join("mutants");
    fs::create_dir_all(&mutants_dir).map_err(|error| CorpusError::io(&mutants_dir, error))?;
    let mut generated = Generated::default();
    for source in sources(&sources_dir, real_dir, fast)? {
        generated.sources += 1;
        generated.bytes += source.bytes.len() as u64;
        for mutant in mutants(&source, seed_of(&source.name))? {
            if fast && !mutant.headline {
                continue;
            }
            let path = mutant_path(&mutants_dir, source.stem(), mutant.kind, &mutant.detail)
                .with_extension(source.extension());
            fs::write(&path, &mutant.bytes).map_err(|error| CorpusError::io(&path, error))?;
            generated.mutants += 1;
            generated.bytes += mutant.bytes.len() as u64;
        }
    }
    Ok(generated)
}

fn mutant_path(dir: &Path, stem: &str, kind: Kind, detail: &str) -> PathBuf {
    dir.join(format!("{stem}--{}--{detail}.x", kind.label()))
}

/// The kind of a mutant from its file name; `None` for a source.
pub fn kind_of(path: &Path) -> Option<Kind> {
    let name = path.file_name()?.to_str()?;
    Kind::from_label(name.split("--").nth(1)?)
}

/// A fixed seed per source name (FNV-1a), so a source's flips do not depend on the others.
fn seed_of(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |hash, byte| {
        (hash ^ u64::from(byte)).wrapping_mul(0x0100_0000_01b3)
    })
}

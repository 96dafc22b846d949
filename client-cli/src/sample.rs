//! `pointfarm sample`: writes the generated demo scene to a LAS/LAZ file.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use pointfarm_render::ingest::{write_las, LasWriteOptions};
use pointfarm_render::sample::{sample_scene, DEFAULT_SAMPLE_POINTS};

#[derive(Args)]
pub struct SampleArgs {
    /// Output file; .laz is compressed, .las is not.
    out: PathBuf,
    /// Number of points.
    #[arg(long, default_value_t = DEFAULT_SAMPLE_POINTS)]
    points: usize,
    /// Seed of the generator (the same seed gives the same file).
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

pub fn run(args: SampleArgs) -> Result<()> {
    let cloud = sample_scene(args.points, args.seed);
    if let Some(parent) = args.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("creating {}", parent.display()))?;
    }
    write_las(&args.out, &cloud, &LasWriteOptions::default())?;
    outln!("{}: {} points", args.out.display(), cloud.len());
    Ok(())
}

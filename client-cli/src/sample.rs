//! `pointfarm sample`: writes the generated demo scene to a LAS/LAZ file, a block at a time,
//! so a scene of any size is written in a block's memory.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use pointfarm_render::ingest::{LasStreamWriter, LasWriteOptions};
use pointfarm_render::sample::{SampleScene, DEFAULT_SAMPLE_POINTS, SAMPLE_ORIGIN};

use crate::progress;

/// Points generated and written at a time (about 40 B each while generated).
const BLOCK_POINTS: usize = 1 << 20;

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
    if let Some(parent) = args.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("creating {}", parent.display()))?;
    }
    let mut scene = SampleScene::new(args.points, args.seed);
    let mut writer =
        LasStreamWriter::create(&args.out, SAMPLE_ORIGIN, &LasWriteOptions::default())?;
    let bar = progress::counter(
        args.points as u64,
        "points",
        format!("writing {}", args.out.display()),
    );
    while scene.remaining() > 0 {
        let block = scene.next_block(BLOCK_POINTS);
        writer.write(&block)?;
        bar.inc(block.len() as u64);
    }
    writer.finish()?;
    bar.finish_and_clear();
    outln!("{}: {} points", args.out.display(), args.points);
    Ok(())
}

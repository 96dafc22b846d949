//! The flags the level-of-detail store programs share (`lod-build-resume`,
//! `lod-store-update`): the campaign they write, the build's memory budget and where their
//! scratch folder is made; and that campaign written into a fresh scratch folder.

use std::path::PathBuf;

use tempfile::TempDir;

use super::{write_campaign, CampaignFiles};
use crate::cli::FlagValue;

/// The seed of the terrain the store programs write.
const CAMPAIGN_SEED: u64 = 11;

/// `--points N --files N --budget-mib N --dir DIR`.
pub struct CampaignFlags {
    pub points: u64,
    pub files: usize,
    /// The build's memory budget, in MiB.
    pub budget_mib: u64,
    /// Where the scratch folder is made (the system's temporary folder by default).
    pub dir: Option<PathBuf>,
}

/// A campaign written for one run: its LAZ tiles in `tiles`, inside `scratch` (removed when
/// dropped), where the run keeps its stores too.
pub struct ScratchCampaign {
    pub scratch: TempDir,
    pub tiles: PathBuf,
    pub written: CampaignFiles,
}

impl CampaignFlags {
    /// `points` in `files` tiles, built within 1 GiB.
    pub fn new(points: u64, files: usize) -> Self {
        Self {
            points,
            files,
            budget_mib: 1024,
            dir: None,
        }
    }

    /// Takes `flag`'s value where it is one of these flags; whether it was.
    pub fn apply(&mut self, flag: &str, value: &FlagValue) -> Result<bool, String> {
        match flag {
            "--points" => self.points = value.number()?,
            "--files" => self.files = value.number()? as usize,
            "--budget-mib" => self.budget_mib = value.number()?,
            "--dir" => self.dir = Some(value.path()),
            _ => return Ok(false),
        }
        Ok(true)
    }

    /// Refuses a campaign of too few rows of tiles to have an inner tile, one of the middle
    /// row away from the edges.
    pub fn check_inner_tile(&self) -> Result<(), String> {
        if super::grid(self.files).0 < 3 {
            return Err(format!(
                "{} files make no inner tile: give a count of at least three rows",
                self.files
            ));
        }
        Ok(())
    }

    /// The campaign written as LAZ tiles into a fresh scratch folder named after `program`.
    pub fn write(&self, program: &str) -> Result<ScratchCampaign, String> {
        let scratch = tempfile::Builder::new()
            .prefix(&format!("{program}-"))
            .tempdir_in(self.dir.clone().unwrap_or_else(std::env::temp_dir))
            .map_err(|e| e.to_string())?;
        let tiles = scratch.path().join("tiles");
        std::fs::create_dir_all(&tiles).map_err(|e| e.to_string())?;
        let written = write_campaign(&tiles, self.points, self.files, CAMPAIGN_SEED, false)
            .map_err(|e| e.to_string())?;
        Ok(ScratchCampaign {
            scratch,
            tiles,
            written,
        })
    }
}

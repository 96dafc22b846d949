//! The command line the campaign benches through a real `pointfarm serve` share
//! (`lod-camera-first-daemon`, `lod-store-growth`): the campaign's flags, `--rounds` and the
//! `pointfarm` binary to serve with, each bench adding flags of its own.

use std::path::PathBuf;

use super::CampaignFlags;
use crate::cli::{parse_flags, FlagValue};

/// `--pointfarm PATH [--rounds N]` and the campaign's flags.
pub struct ServeCampaignFlags {
    pub campaign: CampaignFlags,
    /// How many times each measurement is taken, at least once.
    pub rounds: usize,
    /// The `pointfarm` binary the daemons run.
    pub pointfarm: PathBuf,
}

impl ServeCampaignFlags {
    /// Reads `args` over `campaign`'s defaults, handing a flag of none of these to `extra`,
    /// which says whether it knows it; a campaign without an inner tile, or no `--pointfarm`,
    /// is an error (with `usage`).
    pub fn parse(
        args: &[String],
        usage: &str,
        mut campaign: CampaignFlags,
        mut extra: impl FnMut(&str, &FlagValue) -> Result<bool, String>,
    ) -> Result<Self, String> {
        let (mut rounds, mut pointfarm) = (1, None);
        parse_flags(args, usage, |flag, value| {
            match flag {
                "--rounds" => rounds = value.number()?.max(1) as usize,
                "--pointfarm" => pointfarm = Some(value.path()),
                _ => return Ok(campaign.apply(flag, &value)? || extra(flag, &value)?),
            }
            Ok(true)
        })?;
        campaign.check_inner_tile()?;
        let pointfarm = pointfarm.ok_or_else(|| format!("--pointfarm is needed\n{usage}"))?;
        Ok(Self {
            campaign,
            rounds,
            pointfarm,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<(ServeCampaignFlags, u64), String> {
        let args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
        let mut frames = 0;
        let flags = ServeCampaignFlags::parse(
            &args,
            "usage: x",
            CampaignFlags::new(1000, 9),
            |flag, value| {
                if flag != "--frames" {
                    return Ok(false);
                }
                frames = value.number()?;
                Ok(true)
            },
        )?;
        Ok((flags, frames))
    }

    #[test]
    fn the_shared_flags_the_campaigns_and_the_benchs_own_are_read() {
        let (flags, frames) = parse(&[
            "--pointfarm",
            "/bin/pf",
            "--rounds",
            "0",
            "--files",
            "12",
            "--frames",
            "4",
        ])
        .expect("flags");
        assert_eq!(flags.pointfarm, PathBuf::from("/bin/pf"));
        assert_eq!((flags.rounds, flags.campaign.files, frames), (1, 12, 4));
        assert_eq!(flags.campaign.points, 1000);
    }

    #[test]
    fn no_pointfarm_an_unknown_flag_and_no_inner_tile_are_refused() {
        let error = |args: &[&str]| parse(args).err().expect("an error");
        assert_eq!(error(&[]), "--pointfarm is needed\nusage: x");
        assert_eq!(
            error(&["--pointfarm", "p", "--colors", "2"]),
            "unknown flag --colors\nusage: x"
        );
        assert!(error(&["--pointfarm", "p", "--files", "2"]).contains("no inner tile"));
    }
}

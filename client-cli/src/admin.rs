//! `pointfarm dataset|jobs|frames`: managing a server's datasets and jobs. Human-readable
//! tables by default, `--json` for scripts (one JSON value on stdout: the API's messages in
//! their proto3 JSON mapping, or the wrappers of `admin_json.rs`). The `jobs` commands are
//! in `admin/jobs.rs`, what they print of a job in `admin/job_lines.rs`.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use pointfarm_proto::v1 as pb;

use pointfarm_render::ingest::dataset_files;

use crate::admin_json::{json_line, Deleted, ExportedDataset, FetchedFrames};
use crate::credentials::ClientCredentials;
use crate::export::exported_line;
use crate::remote::{answer, status_error, Client};

mod job_lines;
mod jobs;

pub use jobs::{jobs, parse_label, parse_priority, JobsCommand};

/// Items asked for per page of a listing.
const PAGE_SIZE: u32 = 100;

/// Every item of a paged listing: `page` fetches the page at a token and returns its items and
/// the next token, empty after the last page.
async fn every_page<T, Page>(mut page: impl FnMut(String) -> Page) -> Result<Vec<T>>
where
    Page: std::future::Future<Output = Result<(Vec<T>, String)>>,
{
    let (mut all, mut token) = (Vec::new(), String::new());
    loop {
        let (items, next) = page(token).await?;
        all.extend(items);
        if next.is_empty() {
            return Ok(all);
        }
        token = next;
    }
}

#[derive(Args, Clone)]
pub struct ServerArgs {
    /// The pointfarm server.
    #[arg(
        long,
        env = "POINTFARM_SERVER",
        default_value = "http://127.0.0.1:50051",
        global = true
    )]
    pub server: String,
    #[command(flatten)]
    pub credentials: ClientCredentials,
    /// Print JSON instead of tables: the API's messages in the proto3 JSON mapping.
    #[arg(long, global = true)]
    pub json: bool,
}

#[derive(Subcommand)]
pub enum DatasetCommand {
    /// Upload LAS/LAZ files or folders of them as one dataset (a file the server already
    /// has is not sent again).
    Add {
        /// LAS/LAZ files, or folders of them.
        #[arg(required = true, value_name = "INPUT")]
        inputs: Vec<PathBuf>,
    },
    /// Register files or folders that are already on the server, under its data roots, as
    /// one dataset; or, by URL (s3://, gs://, az://, http(s)://) under a prefix the server
    /// allows (`serve --allow-url-prefix`), one COPC object or LAS/LAZ tiles (objects, or a
    /// prefix of them), which the server never copies.
    Register {
        /// Files or folders on the server, under one of its `--data-root`s, or one URL.
        #[arg(required = true, value_name = "PATH|URL")]
        paths: Vec<String>,
    },
    /// The server's datasets.
    List,
    /// One dataset: its size, files, and URL where it is read by one; for tiles by URL, each
    /// tile's URL, size and version (the first ten, and a count; `--json` lists every one);
    /// and whether its store is published to object storage, or why not.
    Get {
        /// The dataset's id.
        id: String,
    },
    /// Write a dataset as a COPC 1.0 file, made by the server from its levels of detail
    /// (built first when it has none).
    Export {
        /// The dataset's id.
        id: String,
        #[command(flatten)]
        output: crate::export::OutputArgs,
    },
    /// Delete a dataset (files other datasets share stay).
    Rm {
        /// The dataset's id.
        id: String,
    },
}

#[derive(Subcommand)]
pub enum FramesCommand {
    /// Download a job's finished frames.
    Fetch {
        /// The job's id.
        job: String,
        /// Folder to write the frames to (frame_00000.png, ...).
        #[arg(long, short)]
        out: PathBuf,
        /// First frame index to fetch (to resume a download).
        #[arg(long, default_value_t = 0)]
        from: u32,
    },
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Runtime::new().context("starting the async runtime")
}

pub fn dataset(server: &ServerArgs, command: DatasetCommand) -> Result<()> {
    runtime()?.block_on(async {
        let mut client = Client::connect(&server.server, &server.credentials).await?;
        match command {
            DatasetCommand::Add { inputs } => {
                let files = dataset_files(&inputs)?;
                print_dataset(server, &client.ensure_dataset(&files).await?)?
            }
            DatasetCommand::Register { paths } => {
                let request = pb::RegisterDatasetRequest {
                    path: String::new(),
                    name: String::new(),
                    paths,
                };
                let dataset = answer(client.datasets.register_dataset(request).await)?;
                print_dataset(server, &dataset)?
            }
            DatasetCommand::Get { id } => {
                let request = pb::GetDatasetRequest { id };
                let dataset = answer(client.datasets.get_dataset(request).await)?;
                print_dataset(server, &dataset)?
            }
            DatasetCommand::List => {
                let all = every_page(|page_token| {
                    let mut datasets = client.datasets.clone();
                    let request = pb::ListDatasetsRequest {
                        page_size: PAGE_SIZE,
                        page_token,
                    };
                    async move {
                        answer(datasets.list_datasets(request).await)
                            .map(|p| (p.datasets, p.next_page_token))
                    }
                })
                .await?;
                if server.json {
                    // Every page in one response, as the API would return it with no limit.
                    let response = pb::ListDatasetsResponse {
                        datasets: all,
                        next_page_token: String::new(),
                    };
                    outln!("{}", json_line(&response)?);
                } else {
                    outln!("{:<20} {:>12}  name", "id", "bytes");
                    for d in &all {
                        outln!("{:<20} {:>12}  {}{}", d.id, d.size_bytes, d.name, source(d));
                    }
                }
            }
            DatasetCommand::Export { id, output } => {
                let target = output.target()?;
                let summary = client.export_dataset(&id, &target).await?;
                let file = target.name();
                if server.json {
                    outln!(
                        "{}",
                        json_line(&ExportedDataset {
                            file,
                            summary: &summary
                        })?
                    );
                } else {
                    outln!("{}", exported_line(&file, &summary, " on the server"));
                }
            }
            DatasetCommand::Rm { id } => {
                client
                    .datasets
                    .delete_dataset(pb::DeleteDatasetRequest { id: id.clone() })
                    .await
                    .map_err(status_error)?;
                if server.json {
                    outln!("{}", json_line(&Deleted { deleted: &id })?);
                } else {
                    outln!("deleted {id}");
                }
            }
        }
        Ok(())
    })
}

fn print_dataset(server: &ServerArgs, d: &pb::Dataset) -> Result<()> {
    if server.json {
        outln!("{}", json_line(d)?);
    } else {
        let tiles = tile_lines(d);
        let files = match (d.files.len(), tiles.is_empty()) {
            (n, false) => format!(", {n} tiles"),
            (0 | 1, true) => String::new(),
            (n, true) => format!(", {n} files"),
        };
        outln!(
            "{}  {} ({} bytes{files}){}",
            d.id,
            d.name,
            d.size_bytes,
            source(d)
        );
        for line in tiles {
            outln!("{line}");
        }
        if let Some(line) = d.store_publication.as_ref().map(publication_line) {
            outln!("{line}");
        }
    }
    Ok(())
}

/// How a dataset's store stands with object storage, in one line.
fn publication_line(p: &pb::StorePublication) -> String {
    use pb::store_publication::State;
    match State::try_from(p.state) {
        Ok(State::Published) => format!("  store: published under {}", p.url),
        Ok(State::Publishing) => "  store: publishing".to_owned(),
        Ok(State::Failed) => format!(
            "  store: publishing under {} failed (unix ms {}): {}",
            p.url, p.failed_unix_ms, p.reason
        ),
        Ok(State::NotPublished) => format!("  store: not published: {}", p.reason),
        _ => format!("  store: state {} unknown to this client", p.state),
    }
}

/// Tiles a dataset's human form lists one a line; the others are counted (`--json` lists every
/// one), so a campaign of thousands stays readable.
const LISTED_TILES: usize = 10;

/// The lines that list a dataset of tiles by URL: each tile's URL, size and version, the first
/// [`LISTED_TILES`] of them, then how many more there are; none for any other dataset.
fn tile_lines(d: &pb::Dataset) -> Vec<String> {
    if !d.url.is_empty() {
        return Vec::new();
    }
    let tiles: Vec<&pb::DatasetFile> = d.files.iter().filter(|f| !f.url.is_empty()).collect();
    let mut lines: Vec<String> = (tiles.iter().take(LISTED_TILES))
        .map(|tile| {
            format!(
                "  {}  {} bytes  version {}",
                tile.url, tile.size_bytes, tile.version
            )
        })
        .collect();
    if tiles.len() > LISTED_TILES {
        lines.push(format!(
            "  ... and {} more tiles (--json lists every one)",
            tiles.len() - LISTED_TILES
        ));
    }
    lines
}

/// Where a dataset by URL is read from, after its name; nothing for files on the server.
fn source(d: &pb::Dataset) -> String {
    match (d.url.as_str(), d.version.as_str()) {
        ("", _) => String::new(),
        (url, "") => format!("  {url}"),
        (url, version) => format!("  {url} (version {version})"),
    }
}

pub fn frames(server: &ServerArgs, command: FramesCommand) -> Result<()> {
    runtime()?.block_on(async {
        let mut client = Client::connect(&server.server, &server.credentials).await?;
        match command {
            FramesCommand::Fetch { job, out, from } => {
                let written = client.fetch_frames(&job, from, &out).await?;
                if server.json {
                    outln!("{}", json_line(&FetchedFrames::new(&job, &out, &written))?);
                } else {
                    outln!("{} frames in {}", written.len(), out.display());
                }
            }
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiles(count: usize) -> pb::Dataset {
        pb::Dataset {
            id: "d".into(),
            files: (1..=count)
                .map(|k| pb::DatasetFile {
                    name: format!("t{k}.laz"),
                    size_bytes: 100 + k as u64,
                    url: format!("s3://b/tiles/t{k}.laz"),
                    version: format!("\"e{k}\""),
                    ..Default::default()
                })
                .collect(),
            ..Default::default()
        }
    }

    #[test]
    fn a_store_publication_is_one_line() {
        use pb::store_publication::State;
        let failed = pb::StorePublication {
            state: State::Failed as i32,
            url: "s3://b/farm/ab/".into(),
            reason: "s3://b/farm/ab/nodes.bin: connection refused".into(),
            failed_unix_ms: 7,
        };
        assert_eq!(
            publication_line(&failed),
            "  store: publishing under s3://b/farm/ab/ failed (unix ms 7): \
             s3://b/farm/ab/nodes.bin: connection refused"
        );
        let published = pb::StorePublication {
            state: State::Published as i32,
            url: "s3://b/farm/ab/".into(),
            ..Default::default()
        };
        assert_eq!(
            publication_line(&published),
            "  store: published under s3://b/farm/ab/"
        );
    }

    #[test]
    fn a_long_list_of_tiles_is_cut_and_counted() {
        let few = tile_lines(&tiles(3));
        assert_eq!(few.len(), 3);
        assert_eq!(few[1], "  s3://b/tiles/t2.laz  102 bytes  version \"e2\"");
        let many = tile_lines(&tiles(LISTED_TILES + 7));
        assert_eq!(many.len(), LISTED_TILES + 1);
        assert!(many[LISTED_TILES - 1].contains(&format!("t{LISTED_TILES}.laz")));
        assert_eq!(
            many[LISTED_TILES],
            "  ... and 7 more tiles (--json lists every one)"
        );
        // Files on the server and one COPC object list no tiles.
        let copc = pb::Dataset {
            url: "s3://b/a.copc.laz".into(),
            ..tiles(1)
        };
        assert!(tile_lines(&copc).is_empty());
        let files = pb::Dataset {
            files: vec![pb::DatasetFile::default(); 2],
            ..Default::default()
        };
        assert!(tile_lines(&files).is_empty());
    }
}

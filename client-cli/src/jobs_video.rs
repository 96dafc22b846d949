//! A job's video, made on the server, downloaded: by `render --server --video` once the job
//! has succeeded, and by `jobs video JOB [--preview] --out FILE`. Written beside its place and renamed
//! into it once whole, so a cut download never leaves a partial video under its name.

use std::path::Path;

use anyhow::{bail, Context, Result};
use pointfarm_proto::v1 as pb;
use pointfarm_render::encode::video::VideoContainer;
use tokio::io::AsyncWriteExt;

use crate::admin_json::{json_line, FetchedVideo};
use crate::download::PartialFile;
use crate::remote::Client;

/// Downloads job `job_id`'s video to `out`; returns its size in bytes.
pub async fn download(client: &mut Client, job_id: &str, out: &Path) -> Result<u64> {
    download_of(client, job_id, false, out).await
}

/// Downloads job `job_id`'s video, or its preview video, to `out`; returns its size in bytes.
async fn download_of(client: &mut Client, job_id: &str, preview: bool, out: &Path) -> Result<u64> {
    let request = pb::FetchVideoRequest {
        job_id: job_id.to_owned(),
        preview,
    };
    let mut stream = client
        .jobs
        .fetch_video(request)
        .await
        .map_err(crate::remote::status_error)?
        .into_inner();
    let partial = PartialFile::of(out);
    let mut file = tokio::fs::File::create(partial.path())
        .await
        .with_context(|| format!("creating {}", partial.path().display()))?;
    let written = async {
        let (mut declared, mut received) = (None, 0u64);
        while let Some(chunk) = stream
            .message()
            .await
            .map_err(crate::remote::status_error)?
        {
            if declared.is_none() {
                declared = Some(chunk.size_bytes);
                check_container(&chunk.container, out)?;
            }
            received += chunk.data.len() as u64;
            file.write_all(&chunk.data)
                .await
                .with_context(|| format!("writing {}", partial.path().display()))?;
        }
        file.flush().await?;
        match declared {
            Some(size) if size == received => Ok(size),
            Some(size) => bail!("the server sent {received} of the video's {size} bytes"),
            None => bail!("the server sent no video"),
        }
    }
    .await;
    partial.finish(written)
}

/// Refuses to write a video under a name that says another container.
fn check_container(container: &str, out: &Path) -> Result<()> {
    let Ok(named) = VideoContainer::of_path(out) else {
        return Ok(());
    };
    if named.extension() != container {
        bail!(
            "the job's video is {container}, not {}: name the file .{container}",
            named.extension()
        );
    }
    Ok(())
}

/// `jobs video JOB [--preview] --out FILE [--json]`.
pub async fn run(
    client: &mut Client,
    job_id: &str,
    preview: bool,
    out: &Path,
    json: bool,
) -> Result<()> {
    let bytes = download_of(client, job_id, preview, out).await?;
    if json {
        let fetched = FetchedVideo {
            job_id: job_id.to_owned(),
            out: out.display().to_string(),
            preview,
            size_bytes: bytes.to_string(),
        };
        outln!("{}", json_line(&fetched)?);
    } else {
        let which = if preview { "preview video" } else { "video" };
        outln!("{which} of job {job_id}: {} ({bytes} bytes)", out.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_video_is_named_as_its_container() {
        assert!(check_container("mp4", Path::new("spin.mp4")).is_ok());
        assert!(check_container("mp4", Path::new("spin")).is_ok());
        let error = check_container("webm", Path::new("spin.mp4")).expect_err("another");
        assert!(error.to_string().contains("name the file .webm"), "{error}");
    }
}

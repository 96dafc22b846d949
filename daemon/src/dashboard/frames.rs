//! A job's frame images from the daemon's frame storage: the final PNG once the frame is
//! done, else its latest preview; `thumbnail` scales it down for the job's page (frames at
//! most [`THUMBNAIL_SIDE`] pixels on each side are sent as they are); and the video the farm
//! made of a job.

use std::io::Cursor;

use axum::body::{Body, Bytes};
use axum::extract::{Path, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Status;

use super::api::run;
use super::failure::Failure;
use super::Dashboard;
use crate::error::DaemonError;
use crate::grpc::streaming::read_chunk;
use crate::grpc::{blocking_within, BLOCKING_CALL_BOUND};
use crate::model::FrameState;

/// The longest side of a thumbnail, in pixels: a grid of them fits a phone two abreast.
pub const THUMBNAIL_SIDE: u32 = 240;

/// The PNG of frame `index` of job `id`: final or preview; NOT_FOUND while it has neither.
/// A frame's image and thumbnail, and a job's video.
pub(super) fn routes() -> Router<Dashboard> {
    Router::new()
        .route("/jobs/{id}/frames/{index}/image", get(image))
        .route("/jobs/{id}/frames/{index}/thumbnail", get(thumbnail))
        .route("/jobs/{id}/video", get(video))
}

async fn frame_png(dashboard: &Dashboard, id: String, index: u32) -> Result<Vec<u8>, Failure> {
    let path = run(&dashboard.daemon, move |daemon| {
        let job = daemon.job(&id)?;
        if index >= job.frames_total {
            return Err(DaemonError::NotFound(format!(
                "frame {index} of job {id}, which has {} frames",
                job.frames_total
            )));
        }
        let done = matches!(daemon.state.frame(&id, index)?, Some(FrameState::Done(_)));
        if !done && !daemon.state.has_preview(&id, index)? {
            return Err(DaemonError::NotFound(format!(
                "frame {index} of job {id} has no image yet"
            )));
        }
        Ok(daemon.config.frame_path(&id, index))
    })
    .await?;
    crate::grpc::io_within(tokio::fs::read(path))
        .await
        .map_err(|e| Failure(Status::internal(format!("frame {index}: {e}"))))
}

fn png(bytes: Vec<u8>) -> Response {
    (
        [
            (header::CONTENT_TYPE, "image/png"),
            // A preview is replaced in place; the page asks again, with a new query, when it is.
            (header::CACHE_CONTROL, "private, no-cache"),
        ],
        bytes,
    )
        .into_response()
}

pub async fn image(
    State(dashboard): State<Dashboard>,
    Path((id, index)): Path<(String, u32)>,
) -> Result<Response, Failure> {
    Ok(png(frame_png(&dashboard, id, index).await?))
}

pub async fn thumbnail(
    State(dashboard): State<Dashboard>,
    Path((id, index)): Path<(String, u32)>,
) -> Result<Response, Failure> {
    let full = frame_png(&dashboard, id, index).await?;
    let small = blocking_within(BLOCKING_CALL_BOUND, move || scaled_down(full)).await?;
    Ok(png(small.map_err(|e| {
        Failure(Status::internal(format!("frame {index}: {e}")))
    })?))
}

/// The video the farm made of job `id`, streamed from disk chunk by chunk so that a large one
/// never sits in memory; NOT_FOUND or FAILED_PRECONDITION while there is none.
pub async fn video(
    State(dashboard): State<Dashboard>,
    Path(id): Path<String>,
) -> Result<Response, Failure> {
    let (path, size, container) = run(&dashboard.daemon, move |daemon| daemon.video(&id)).await?;
    let mut file = crate::grpc::io_within(tokio::fs::File::open(path))
        .await
        .map_err(|e| Failure(Status::internal(format!("opening the video: {e}"))))?;
    let (sender, receiver) = tokio::sync::mpsc::channel(4);
    tokio::spawn(async move {
        loop {
            let chunk = match read_chunk(&mut file).await {
                Ok(Some(data)) => Ok(Bytes::from(data)),
                Ok(None) => return,
                Err(e) => Err(e),
            };
            let failed = chunk.is_err();
            if sender.send(chunk).await.is_err() || failed {
                return;
            }
        }
    });
    Ok((
        [
            (header::CONTENT_TYPE, container.media_type().to_owned()),
            (header::CONTENT_LENGTH, size.to_string()),
            (header::CACHE_CONTROL, "private, no-cache".to_owned()),
        ],
        Body::from_stream(ReceiverStream::new(receiver)),
    )
        .into_response())
}

/// `png` scaled to fit [`THUMBNAIL_SIDE`], or as it is when it already does.
fn scaled_down(png: Vec<u8>) -> Result<Vec<u8>, image::ImageError> {
    let decoder = image::codecs::png::PngDecoder::new(Cursor::new(&png))?;
    let (width, height) = image::ImageDecoder::dimensions(&decoder);
    if width <= THUMBNAIL_SIDE && height <= THUMBNAIL_SIDE {
        return Ok(png);
    }
    let frame = image::DynamicImage::from_decoder(decoder)?;
    let small = frame.thumbnail(THUMBNAIL_SIDE, THUMBNAIL_SIDE);
    let mut out = Vec::new();
    small.write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn encoded(width: u32, height: u32) -> Vec<u8> {
        let image = image::RgbaImage::from_pixel(width, height, image::Rgba([10, 20, 30, 255]));
        let mut out = Vec::new();
        image
            .write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)
            .expect("encode");
        out
    }

    #[test]
    fn large_frames_are_scaled_to_fit_and_small_ones_kept() {
        let small = encoded(64, 48);
        assert_eq!(scaled_down(small.clone()).expect("kept"), small);
        let thumbnail = scaled_down(encoded(1920, 1080)).expect("scaled");
        let decoded = image::load_from_memory(&thumbnail).expect("a PNG");
        assert_eq!((decoded.width(), decoded.height()), (240, 135));
        assert!(scaled_down(b"not a png".to_vec()).is_err());
    }
}

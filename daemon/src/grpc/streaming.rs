//! Bytes streamed in chunks over gRPC — frames, datasets and uploads alike: the one chunk
//! size, the response streams fed by a task of their own, and the hashing of received bytes
//! into a file.

use std::future::Future;
use std::path::Path;
use std::pin::Pin;

use sha2::{Digest, Sha256};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::Stream;
use tonic::{Status, Streaming};

use super::conversions::invalid;

use crate::model::hex;

/// Bytes per streamed message: well under gRPC's default 4 MiB message limit.
pub const CHUNK_BYTES: usize = 1 << 20;

/// A server-streaming answer.
pub(super) type ResponseStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

/// A response stream fed by `produce`, which runs as a task of its own and sends into a
/// channel that holds `capacity` messages; it stops when the client goes away.
pub(super) fn spawn_stream<T, F, Fut>(capacity: usize, produce: F) -> ResponseStream<T>
where
    T: Send + 'static,
    F: FnOnce(mpsc::Sender<Result<T, Status>>) -> Fut,
    Fut: Future<Output = ()> + Send + 'static,
{
    let (sender, receiver) = mpsc::channel(capacity);
    tokio::spawn(produce(sender));
    Box::pin(ReceiverStream::new(receiver))
}

/// A response stream of `messages`, made already; it stops when the client goes away.
pub(super) fn stream_each<T: Send + 'static>(messages: Vec<T>) -> ResponseStream<T> {
    spawn_stream(4, move |sender| async move {
        send_each(&sender, messages).await;
    })
}

/// Sends `messages` in order; false as soon as the client has gone away.
pub(super) async fn send_each<T>(
    sender: &mpsc::Sender<Result<T, Status>>,
    messages: impl IntoIterator<Item = T>,
) -> bool {
    for message in messages {
        if sender.send(Ok(message)).await.is_err() {
            return false;
        }
    }
    true
}

/// The first message of a client stream, which must carry the part `pick` takes from it
/// (its header): an error naming `field` otherwise.
pub(super) async fn first_part<M, P>(
    stream: &mut Streaming<M>,
    field: &str,
    pick: impl FnOnce(M) -> Option<P>,
) -> Result<P, Status> {
    match stream.message().await? {
        Some(message) => pick(message),
        None => None,
    }
    .ok_or_else(|| invalid(field, format!("the first message must be the {field}")).into())
}

/// `bytes` in chunks of [`CHUNK_BYTES`], each with whether it is the last; none for no bytes.
pub fn chunks(bytes: &[u8]) -> impl Iterator<Item = (&[u8], bool)> {
    let count = bytes.len().div_ceil(CHUNK_BYTES);
    bytes
        .chunks(CHUNK_BYTES)
        .enumerate()
        .map(move |(i, chunk)| (chunk, i + 1 == count))
}

/// The next chunk of at most [`CHUNK_BYTES`] read from `file`; None at its end.
pub async fn read_chunk(file: &mut tokio::fs::File) -> std::io::Result<Option<Vec<u8>>> {
    let mut buffer = vec![0u8; CHUNK_BYTES];
    let n = file.read(&mut buffer).await?;
    if n == 0 {
        return Ok(None);
    }
    buffer.truncate(n);
    Ok(Some(buffer))
}

/// A file written from received chunks, hashed (SHA-256) and counted as they arrive.
pub struct HashingWriter {
    file: tokio::fs::File,
    hasher: Sha256,
    received: u64,
}

impl HashingWriter {
    pub async fn create(path: &Path) -> std::io::Result<Self> {
        Ok(Self {
            file: tokio::fs::File::create(path).await?,
            hasher: Sha256::new(),
            received: 0,
        })
    }

    /// Bytes written so far.
    pub fn received(&self) -> u64 {
        self.received
    }

    pub async fn write(&mut self, data: &[u8]) -> std::io::Result<()> {
        self.received += data.len() as u64;
        self.hasher.update(data);
        self.file.write_all(data).await
    }

    /// Flushes the file and returns the SHA-256 of what was written, in lowercase hex.
    pub async fn finish(mut self) -> std::io::Result<String> {
        self.file.flush().await?;
        Ok(hex(&self.hasher.finalize()))
    }
}

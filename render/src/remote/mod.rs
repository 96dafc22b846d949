//! Datasets by URL: objects in S3 (and S3-compatible stores) and on plain HTTP(S) servers,
//! read by byte ranges, never copied whole.
//!
//! `ObjectUrl` checks an address once (`s3://`, `http(s)://`, `file://`; no credentials, query
//! or fragment, so URLs can always be logged); `AllowedPrefixes` is the operator's allow-list;
//! `RemoteClient` opens a `RemoteObject` (a HEAD for its size and version) and lists a
//! prefix's point files; a `RemoteObject` reads ranges, coalescing near ones and fetching them
//! in parallel, every request pinned to the version seen at open; an `ObjectReader` streams
//! one from start to end in large blocks, for the LAS/LAZ readers. `RemoteUpload` writes an
//! object by a multipart upload, a few parts in memory at a time, visible only once complete.
//! `RemoteSettings` states every timeout, retry and size bound with its default. An HTTP(S)
//! server's redirect is followed only within the origin asked (and, for a client made
//! `within` an allow-list, under its prefixes), and a server that ignores a range request is
//! refused at its answer's headers, before its body is read.
//!
//! The transport is the `object_store` crate, which is async. The render crate is not: its
//! readers are called from rayon threads, plain threads and, in the worker and the daemon,
//! from inside tokio runtimes. So the client owns a small tokio runtime of its own and every
//! call spawns its request there and waits on a std channel. That works from any thread,
//! where `Handle::current().block_on` would need a caller inside a runtime and
//! `Runtime::block_on` panics inside one; an async caller should still call from
//! `spawn_blocking`, since the wait blocks its thread. The runtime is shut down without
//! blocking when the last client is dropped, so dropping one on an async thread is safe too.
//!
//! Credentials come only from the environment (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`,
//! `AWS_ENDPOINT`, `AWS_ALLOW_HTTP`, ... as object_store reads them) and never appear in a
//! URL, an error or a `Debug` output. `file://` URLs are parsed here but read by the local path
//! (`ingest::files`), which keeps a server's reads inside its data roots.

mod allow;
mod client;
mod coalesce;
mod counters;
mod error;
mod list;
mod object;
mod redirect;
mod runtime;
mod settings;
mod store;
mod stream;
mod upload;
mod url;

pub use allow::AllowedPrefixes;
pub use client::RemoteClient;
pub use counters::FetchCounts;
pub use error::RemoteError;
pub use list::{is_point_file, ListedObject};
pub use object::RemoteObject;
pub use settings::RemoteSettings;
pub use stream::{BlockSource, ObjectReader, STREAM_BLOCK_BYTES};
pub use upload::RemoteUpload;
pub use url::{ObjectUrl, UrlKind, MAX_URL_LEN};

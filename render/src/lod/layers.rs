//! A store's payload as a chain of layers: the payload files of the stores it was grown from,
//! hard-linked into its folder and never written again, then its own file, to which it
//! appends. A store grown from another shares the earlier payload's blocks instead of copying
//! them, and removing the earlier store leaves the links, so its folder stays self-contained.
//!
//! Node offsets address the layers' concatenation, not a (layer, offset) pair: a hierarchy
//! keeps the one `u64` offset per piece it has always kept, an earlier store's records keep
//! their offsets in the grown one, and the concatenation is exactly the one payload object a
//! published store holds, uploaded as it is. A read that spans two layers is split between
//! them.
//!
//! The layers below a payload file `P` are `P.0`, `P.1`, … listed in `P.layers`, one line each:
//! its length, its modification time in nanoseconds and a checksum of its first and last
//! [`EDGE_BYTES`]. Each is checked when the store opens (a `stat` and two short reads a
//! layer): a layer of another length, time or edges refuses the store, which is then built
//! again like any damaged store ([`LodError::CorruptLayers`]); the checksums of the records
//! themselves catch damage within. A payload without a list is one layer, as stores were
//! always written.
//!
//! A store being grown is compacted into one file ([`needs_compaction`], `compact.rs`) when
//! it would hold more than [`MAX_LAYERS`] layers, or when most of its bytes are dead (records no node lists any
//! more): each layer is a file kept open while the store is, and dead bytes in linked layers
//! are never reclaimed until then.

use std::fs::File;
use std::io;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::time::UNIX_EPOCH;

use super::checksum::checksum64;
use super::error::LodError;

/// The most layers a store keeps below its own file: each is a file held open while the store
/// is, and checked when it opens.
pub const MAX_LAYERS: usize = 8;
/// Bytes at each end of a layer its checksum covers: enough to tell another file of the same
/// length, short enough that opening a store reads little.
const EDGE_BYTES: u64 = 64 << 10;
/// A layer list longer than this is not one this code wrote.
const MAX_LIST_BYTES: u64 = 64 << 10;

/// Whether a store being grown, whose payload has `layers` layers below its own file and
/// `payload_bytes` in all, of which `live_bytes` are listed by its nodes, is compacted into one
/// file first: when it has more than [`MAX_LAYERS`] layers, or more than half its bytes are
/// dead.
pub fn needs_compaction(layers: usize, payload_bytes: u64, live_bytes: u64) -> bool {
    let dead = payload_bytes.saturating_sub(live_bytes);
    layers > MAX_LAYERS || dead.saturating_mul(2) > payload_bytes
}

/// What a layer list records of one layer, checked before the layer is read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct LayerFacts {
    bytes: u64,
    modified_ns: u64,
    edges: u64,
}

/// A sealed layer, open for positioned reads, at `start` in the concatenation.
#[derive(Debug)]
struct Layer {
    path: PathBuf,
    file: File,
    start: u64,
    bytes: u64,
}

/// The checked, sealed layers below a payload file.
#[derive(Debug, Default)]
pub(crate) struct Layers {
    layers: Vec<Layer>,
}

/// The list of the layers below `payload`.
pub fn list_path(payload: &Path) -> PathBuf {
    suffixed(payload, "layers")
}

/// The layer at `index` below `payload`.
fn layer_path(payload: &Path, index: usize) -> PathBuf {
    suffixed(payload, &index.to_string())
}

fn suffixed(payload: &Path, suffix: &str) -> PathBuf {
    let mut name = payload.as_os_str().to_owned();
    name.push(".");
    name.push(suffix);
    PathBuf::from(name)
}

fn corrupt(payload: &Path, reason: impl std::fmt::Display) -> LodError {
    LodError::CorruptLayers(format!("{}: {reason}", list_path(payload).display()))
}

impl Layers {
    /// The layers below `payload`, each checked against its list; none where there is no list.
    pub(crate) fn open(payload: &Path) -> Result<Self, LodError> {
        let Some(listed) = read_list(payload)? else {
            return Ok(Self::default());
        };
        let mut layers = Vec::with_capacity(listed.len());
        let mut start = 0u64;
        for (index, wanted) in listed.into_iter().enumerate() {
            let path = layer_path(payload, index);
            let file =
                File::open(&path).map_err(|e| corrupt(payload, format!("layer {index}: {e}")))?;
            advise_random(&file, &path);
            let found =
                facts_of(&file).map_err(|e| corrupt(payload, format!("layer {index}: {e}")))?;
            if found != wanted {
                return Err(corrupt(
                    payload,
                    format!(
                        "layer {index} holds {} bytes modified at {} ns with edges {:016x}, the \
                         list {} bytes at {} ns with edges {:016x}",
                        found.bytes,
                        found.modified_ns,
                        found.edges,
                        wanted.bytes,
                        wanted.modified_ns,
                        wanted.edges
                    ),
                ));
            }
            layers.push(Layer {
                path,
                file,
                start,
                bytes: found.bytes,
            });
            start = start
                .checked_add(found.bytes)
                .ok_or_else(|| corrupt(payload, "too long"))?;
        }
        Ok(Self { layers })
    }

    /// Bytes of the layers together: where the payload's own file starts.
    pub(crate) fn base(&self) -> u64 {
        self.layers.last().map_or(0, |l| l.start + l.bytes)
    }

    pub(crate) fn count(&self) -> usize {
        self.layers.len()
    }

    /// Reads `buf.len()` bytes at `offset`, all below [`Layers::base`], from the layers that
    /// hold them; the error names the layer.
    pub(crate) fn read_exact_at(
        &self,
        buf: &mut [u8],
        offset: u64,
    ) -> Result<(), (PathBuf, io::Error)> {
        let mut at = offset;
        let mut buf = buf;
        let first = self.layers.partition_point(|l| l.start + l.bytes <= at);
        for layer in &self.layers[first..] {
            if buf.is_empty() {
                break;
            }
            let within = at - layer.start;
            let take = (layer.bytes - within).min(buf.len() as u64) as usize;
            let (now, rest) = buf.split_at_mut(take);
            layer
                .file
                .read_exact_at(now, within)
                .map_err(|e| (layer.path.clone(), e))?;
            buf = rest;
            at += take as u64;
        }
        match buf.is_empty() {
            true => Ok(()),
            false => Err((
                self.layers
                    .last()
                    .map_or_else(PathBuf::new, |l| l.path.clone()),
                io::Error::new(io::ErrorKind::UnexpectedEof, "past the layers' end"),
            )),
        }
    }
}

/// Reads `buf.len()` bytes at `offset` of the concatenation of `layers` and the payload's own
/// `file` (at `path`); the error names the file that failed.
pub(crate) fn read_across(
    layers: &Layers,
    file: &File,
    path: &Path,
    buf: &mut [u8],
    offset: u64,
) -> Result<(), (PathBuf, io::Error)> {
    let base = layers.base();
    let below = base.saturating_sub(offset).min(buf.len() as u64) as usize;
    let (lower, own) = buf.split_at_mut(below);
    if !lower.is_empty() {
        layers.read_exact_at(lower, offset)?;
    }
    if !own.is_empty() {
        file.read_exact_at(own, offset.max(base) - base)
            .map_err(|e| (path.to_owned(), e))?;
    }
    Ok(())
}

/// A finished store's payload read as one: its layers' concatenation with its own file, as
/// a published store's one payload object holds it.
pub struct PayloadReader {
    layers: Layers,
    file: File,
    path: PathBuf,
    len: u64,
}

impl PayloadReader {
    /// The payload file at `payload` and the layers listed beside it, checked.
    pub fn open(payload: &Path) -> Result<Self, LodError> {
        let layers = Layers::open(payload)?;
        let file = File::open(payload).map_err(|e| LodError::payload(payload, e))?;
        let own = file
            .metadata()
            .map_err(|e| LodError::payload(payload, e))?
            .len();
        Ok(Self {
            len: layers.base() + own,
            layers,
            file,
            path: payload.to_owned(),
        })
    }

    /// Bytes of the concatenation.
    pub fn len(&self) -> u64 {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Reads `buf.len()` bytes at `offset` of the concatenation.
    pub fn read_exact_at(&self, buf: &mut [u8], offset: u64) -> Result<(), LodError> {
        read_across(&self.layers, &self.file, &self.path, buf, offset)
            .map_err(|(path, error)| LodError::payload(path, error))
    }
}

/// Advises the kernel that `file` (a payload file or layer at `path`) is read at random.
/// Reads are whole runs of pieces, planned here; the kernel's read-ahead would take what
/// follows a run as well, mostly rests a coarse cut leaves out (docs/perf/payload-layout.md).
/// Advice only: a file system without it reads as asked.
pub(crate) fn advise_random(file: &File, path: &Path) {
    if let Err(error) = rustix::fs::fadvise(file, 0, None, rustix::fs::Advice::Random) {
        tracing::debug!(path = %path.display(), %error, "no read-ahead advice");
    }
}

/// The facts of `file` as a layer list records them.
fn facts_of(file: &File) -> io::Result<LayerFacts> {
    let meta = file.metadata()?;
    let bytes = meta.len();
    let modified_ns = meta
        .modified()?
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX));
    let head = bytes.min(EDGE_BYTES);
    let tail = (bytes - head).min(EDGE_BYTES);
    let mut edge = vec![0u8; (head + tail) as usize];
    let (first, last) = edge.split_at_mut(head as usize);
    file.read_exact_at(first, 0)?;
    file.read_exact_at(last, bytes - tail)?;
    Ok(LayerFacts {
        bytes,
        modified_ns,
        edges: checksum64(b"layer", &edge),
    })
}

/// The facts `payload`'s layer list records, checked for form; `None` where it has none.
fn read_list(payload: &Path) -> Result<Option<Vec<LayerFacts>>, LodError> {
    let path = list_path(payload);
    let file = match File::open(&path) {
        Ok(file) => file,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(corrupt(payload, e)),
    };
    let len = file.metadata().map_err(|e| corrupt(payload, e))?.len();
    if len > MAX_LIST_BYTES {
        return Err(corrupt(
            payload,
            format!("{len} bytes, more than a layer list holds"),
        ));
    }
    let mut text = vec![0u8; len as usize];
    file.read_exact_at(&mut text, 0)
        .map_err(|e| corrupt(payload, e))?;
    let text = String::from_utf8(text).map_err(|_| corrupt(payload, "not UTF-8"))?;
    let facts = text
        .lines()
        .enumerate()
        .map(|(i, line)| {
            let fields: Vec<&str> = line.split('\t').collect();
            let parsed = match fields[..] {
                [bytes, modified_ns, edges] => bytes
                    .parse()
                    .ok()
                    .zip(modified_ns.parse().ok())
                    .zip(u64::from_str_radix(edges, 16).ok()),
                _ => None,
            };
            let ((bytes, modified_ns), edges) =
                parsed.ok_or_else(|| corrupt(payload, format!("line {} is not a layer", i + 1)))?;
            Ok(LayerFacts {
                bytes,
                modified_ns,
                edges,
            })
        })
        .collect::<Result<Vec<_>, LodError>>()?;
    // A store being grown holds one layer more than a store keeps until it is compacted.
    if facts.len() > MAX_LAYERS + 1 {
        return Err(corrupt(
            payload,
            format!("{} layers, more than a store keeps", facts.len()),
        ));
    }
    Ok(Some(facts))
}

fn write_list(payload: &Path, facts: &[LayerFacts]) -> io::Result<()> {
    let text: String = facts
        .iter()
        .map(|f| format!("{}\t{}\t{:016x}\n", f.bytes, f.modified_ns, f.edges))
        .collect();
    crate::write_whole::write_whole(&list_path(payload), text.as_bytes())
}

/// Makes the payload `from` (a finished store's: its layers and its own file, none of which
/// is written again) the layers below `into`, which does not exist yet: each hard-linked,
/// none copied. Returns the bytes the layers hold.
pub fn link_layers(from: &Path, into: &Path) -> Result<u64, LodError> {
    let below = read_list(from)?.unwrap_or_default();
    let mut facts = Vec::with_capacity(below.len() + 1);
    for (index, listed) in below.iter().enumerate() {
        link(&layer_path(from, index), &layer_path(into, index))?;
        facts.push(*listed);
    }
    let top = layer_path(into, below.len());
    link(from, &top)?;
    let file = File::open(&top).map_err(|e| LodError::payload(&top, e))?;
    facts.push(facts_of(&file).map_err(|e| LodError::payload(&top, e))?);
    write_list(into, &facts).map_err(|e| LodError::payload(list_path(into), e))?;
    // The links are checked as any opening checks them.
    let layers = Layers::open(into)?;
    Ok(layers.base())
}

fn link(from: &Path, into: &Path) -> Result<(), LodError> {
    std::fs::hard_link(from, into).map_err(|e| LodError::payload(into, e))
}

/// Removes the layers below `payload` and their list, the list first, so that a store
/// cleared part way reads as one of a single layer, then as none.
pub(crate) fn remove_layers(payload: &Path) -> Result<(), LodError> {
    let count = match read_list(payload) {
        Ok(facts) => facts.map_or(0, |f| f.len()),
        Err(_) => MAX_LAYERS + 1,
    };
    let list = list_path(payload);
    match std::fs::remove_file(&list) {
        Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(LodError::payload(&list, e)),
        _ => {}
    }
    for index in 0..count {
        let path = layer_path(payload, index);
        match std::fs::remove_file(&path) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => {
                return Err(LodError::payload(&path, e))
            }
            _ => {}
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compaction_comes_at_the_layer_limit_or_when_most_bytes_are_dead() {
        assert!(!needs_compaction(1, 100, 100));
        assert!(!needs_compaction(MAX_LAYERS, 100, 50));
        assert!(needs_compaction(MAX_LAYERS + 1, 100, 100));
        assert!(needs_compaction(2, 100, 49));
    }

    #[test]
    fn reads_span_the_layers_and_a_changed_layer_is_refused() {
        let dir = tempfile::tempdir().expect("tempdir");
        let first = dir.path().join("a.bin");
        std::fs::write(&first, b"0123456789").expect("write");
        let second = dir.path().join("b.bin");
        link_layers(&first, &second).expect("linked");
        std::fs::write(&second, b"abc").expect("write");
        let third = dir.path().join("c.bin");
        assert_eq!(link_layers(&second, &third).expect("linked"), 13);
        std::fs::remove_file(&first).expect("the earliest removed");
        std::fs::remove_file(&second).expect("the next removed");
        let layers = Layers::open(&third).expect("open");
        assert_eq!((layers.count(), layers.base()), (2, 13));
        let mut buf = [0u8; 6];
        layers.read_exact_at(&mut buf, 7).expect("read");
        assert_eq!(&buf, b"789abc");
        let error = layers.read_exact_at(&mut buf, 9).expect_err("past the end");
        assert_eq!(error.1.kind(), io::ErrorKind::UnexpectedEof);

        // The same length written again is another time; a shorter one another length.
        std::fs::write(layer_path(&third, 1), b"abd").expect("tamper");
        let error = Layers::open(&third).expect_err("refused").to_string();
        assert!(error.contains("layer 1 holds 3 bytes"), "{error}");
        std::fs::write(layer_path(&third, 0), b"01234").expect("tamper");
        let error = Layers::open(&third).expect_err("refused").to_string();
        assert!(error.contains("layer 0 holds 5 bytes"), "{error}");
        remove_layers(&third).expect("removed");
        assert_eq!(Layers::open(&third).expect("none").count(), 0);
        assert!(!layer_path(&third, 0).exists());
    }
}

//! A level-of-detail store published to object storage, where every worker reads it: two
//! objects under `STORE_URL/SHA256/`, the payload file as built ([`PAYLOAD_OBJECT`]) and the
//! hierarchy object ([`HIERARCHY_OBJECT`]), which carries the hierarchy record with what a
//! worker needs beside it. The hierarchy object is written last, so a store whose upload
//! stopped part way has none and is never read.
//!
//! Layout of the hierarchy object, little-endian: "PFPS" | format version u32 | bounds min
//! 3 x f64, max 3 x f64 | payload bytes u64 | payload version: length u16, UTF-8 | hierarchy
//! record: length u64, bytes ("PFH7", `hierarchy.rs`, with its own checksum) | checksum u64
//! of everything before it. The payload's version (its ETag) is the one the payload object
//! had when the hierarchy was written: a payload replaced since is refused, never read with a
//! hierarchy of another build.

use glam::DVec3;

use super::checksum::checksum64;
use super::error::LodError;
use super::fields::FieldReader;
use super::hierarchy::LodHierarchy;
use crate::cloud::WorldBounds;

/// The payload object's name under the store's prefix.
pub const PAYLOAD_OBJECT: &str = "nodes.bin";
/// The hierarchy object's name under the store's prefix.
pub const HIERARCHY_OBJECT: &str = "hierarchy.pfps";
/// The most bytes of hierarchy object a reader takes: about 50 M nodes.
pub const MAX_HIERARCHY_OBJECT_BYTES: u64 = 2 << 30;

const MAGIC: &[u8; 4] = b"PFPS";
/// The layout this build writes and reads.
const FORMAT_VERSION: u32 = 1;
const CHECKSUM_SEED: &[u8] = b"published store";
/// Longest payload version kept: an ETag or a version id is far shorter.
const MAX_VERSION_BYTES: usize = 1024;

/// What the hierarchy object of a published store holds.
#[derive(Debug, Clone, PartialEq)]
pub struct PublishedHierarchy {
    /// The dataset's bounds, which a cut frames its cameras with.
    pub bounds: WorldBounds,
    /// Bytes of the payload object.
    pub payload_bytes: u64,
    /// The payload object's version (ETag or version id) when the hierarchy was written.
    pub payload_version: String,
    /// The store's hierarchy record, as the store keeps it.
    pub hierarchy_record: Vec<u8>,
}

impl PublishedHierarchy {
    pub fn encode(&self) -> Vec<u8> {
        let version = self.payload_version.as_bytes();
        let mut out = Vec::with_capacity(80 + version.len() + self.hierarchy_record.len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        for c in self
            .bounds
            .min
            .to_array()
            .into_iter()
            .chain(self.bounds.max.to_array())
        {
            out.extend_from_slice(&c.to_le_bytes());
        }
        out.extend_from_slice(&self.payload_bytes.to_le_bytes());
        out.extend_from_slice(&(version.len() as u16).to_le_bytes());
        out.extend_from_slice(version);
        out.extend_from_slice(&(self.hierarchy_record.len() as u64).to_le_bytes());
        out.extend_from_slice(&self.hierarchy_record);
        let sum = checksum64(CHECKSUM_SEED, &out);
        out.extend_from_slice(&sum.to_le_bytes());
        out
    }

    /// The object's contents, checked: its checksum, its format version, every length
    /// against the bytes there are, and the bounds.
    pub fn decode(bytes: &[u8]) -> Result<Self, LodError> {
        let corrupt = |reason: String| {
            LodError::CorruptHierarchy(format!("the published store's hierarchy object: {reason}"))
        };
        if bytes.len() < MAGIC.len() + 4 + 8 {
            return Err(corrupt("shorter than its header".into()));
        }
        let (body, sum) = bytes.split_at(bytes.len() - 8);
        let mut stored = [0; 8];
        stored.copy_from_slice(sum);
        if checksum64(CHECKSUM_SEED, body) != u64::from_le_bytes(stored) {
            return Err(corrupt("checksum mismatch".into()));
        }
        let mut r = FieldReader::new(body, "truncated");
        if r.take(4)? != MAGIC {
            return Err(corrupt("not a published store's hierarchy".into()));
        }
        let version = r.u32()?;
        if version != FORMAT_VERSION {
            return Err(corrupt(format!(
                "format version {version}, this build reads {FORMAT_VERSION}: publish the store again"
            )));
        }
        let min = DVec3::new(r.f64()?, r.f64()?, r.f64()?);
        let max = DVec3::new(r.f64()?, r.f64()?, r.f64()?);
        if !(min.is_finite() && max.is_finite() && min.cmple(max).all()) {
            return Err(corrupt("its bounds are not a box".into()));
        }
        let payload_bytes = r.u64()?;
        let version_len = usize::from(r.u16()?);
        if version_len > MAX_VERSION_BYTES {
            return Err(corrupt(format!("a payload version of {version_len} bytes")));
        }
        let payload_version = std::str::from_utf8(r.take(version_len)?)
            .map_err(|_| corrupt("its payload version is not UTF-8".into()))?
            .to_owned();
        let record_len = r.u64()?;
        let record = usize::try_from(record_len)
            .ok()
            .map(|len| r.take(len))
            .ok_or_else(|| corrupt(format!("a hierarchy record of {record_len} bytes")))??;
        if !r.at_end() {
            return Err(corrupt("bytes after the hierarchy record".into()));
        }
        Ok(Self {
            bounds: WorldBounds { min, max },
            payload_bytes,
            payload_version,
            hierarchy_record: record.to_vec(),
        })
    }

    /// The hierarchy, checked as a store's own is, and checked to lie within the payload.
    pub fn hierarchy(&self) -> Result<LodHierarchy, LodError> {
        let hierarchy = LodHierarchy::decode(&self.hierarchy_record)?;
        if let Some(node) = hierarchy.stored_nodes().find(|node| {
            node.pieces(node.byte_len)
                .any(|piece| piece.end > self.payload_bytes)
        }) {
            return Err(LodError::CorruptNode {
                key: node.key,
                reason: format!(
                    "its record lies past the end of the published payload ({} bytes)",
                    self.payload_bytes
                ),
            });
        }
        Ok(hierarchy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::{build_lod, GeneratedSource, LodBuildOptions, LodStore};

    fn published() -> (PublishedHierarchy, LodHierarchy) {
        let dir = tempfile::tempdir().expect("temp dir");
        let db = sled::open(dir.path().join("db")).expect("sled");
        let store = LodStore::open(
            db.open_tree("lod").expect("tree"),
            dir.path().join("nodes.bin"),
        )
        .expect("store");
        let mut options = LodBuildOptions::new(dir.path().join("spill"));
        options.max_leaf_points = 500;
        options.memory_budget_bytes = options.min_memory_budget_bytes();
        build_lod(&GeneratedSource::terrain(20_000, 7), &store, &options).expect("build");
        let hierarchy = store.read_hierarchy().expect("hierarchy");
        let published = PublishedHierarchy {
            bounds: WorldBounds {
                min: DVec3::new(-1.0, -2.0, -3.0),
                max: DVec3::new(4.0, 5.0, 6.0),
            },
            payload_bytes: store.payload_bytes().expect("payload"),
            payload_version: "\"etag-1\"".into(),
            hierarchy_record: hierarchy.encode(),
        };
        (published, hierarchy)
    }

    #[test]
    fn a_hierarchy_object_reads_back_as_written() {
        let (published, hierarchy) = published();
        let bytes = published.encode();
        let back = PublishedHierarchy::decode(&bytes).expect("decode");
        assert_eq!(back, published);
        assert_eq!(back.hierarchy().expect("hierarchy"), hierarchy);
    }

    #[test]
    fn a_damaged_hierarchy_object_is_refused() {
        let (published, _) = published();
        let bytes = published.encode();
        let refused = |bytes: &[u8]| {
            PublishedHierarchy::decode(bytes)
                .and_then(|p| p.hierarchy().map(drop))
                .expect_err("damage is refused")
                .to_string()
        };
        // A flipped bit anywhere fails the checksum.
        for at in [0, 5, 30, 70, bytes.len() / 2, bytes.len() - 1] {
            let mut flipped = bytes.clone();
            flipped[at] ^= 0x10;
            assert!(refused(&flipped).contains("checksum"), "byte {at}");
        }
        // Cut short, it is refused before any length inside is trusted.
        for len in [0, 10, 40, bytes.len() - 9] {
            let message = refused(&bytes[..len]);
            assert!(message.contains("published store"), "{len}: {message}");
        }
        // Another format version is named, checksum intact.
        let mut later = bytes[..bytes.len() - 8].to_vec();
        later[4..8].copy_from_slice(&2u32.to_le_bytes());
        let sum = checksum64(CHECKSUM_SEED, &later);
        later.extend_from_slice(&sum.to_le_bytes());
        assert!(refused(&later).contains("format version 2"));
        // A payload shorter than the hierarchy says is refused before any read.
        let short = PublishedHierarchy {
            payload_bytes: published.payload_bytes / 2,
            ..published.clone()
        };
        let message = refused(&short.encode());
        assert!(
            message.contains("past the end of the published payload"),
            "{message}"
        );
        // A hierarchy record damaged before it was published fails its own checksum.
        let mut record = published.hierarchy_record.clone();
        record[20] ^= 1;
        let damaged = PublishedHierarchy {
            hierarchy_record: record,
            ..published
        };
        assert!(refused(&damaged.encode()).contains("checksum"));
    }
}

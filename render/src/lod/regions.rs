//! `StoreRegions`: what a store keeps beside its hierarchy so that it can be updated instead of
//! built again (`update.rs`): its regions (the subtrees of each partition's children, or the
//! partition itself where it is a leaf; every point in exactly one region), each with its point
//! count and, for a region below the root, its subtree root as it was before the levels above
//! sampled from it (a record in the payload file, not listed in the hierarchy); the LAS grid
//! every point lies on, if one; and the files the points came from, one entry each.
//!
//! Written in the same sled batch as the hierarchy, so the two always describe the same
//! points. Layout, little-endian: "PFR1" | grid present u8, then scale 3 x f64, offset
//! 3 x f64 | regions u32, then per region: level u8, x, y, z u32, points u64, root present u8,
//! then its record's points u32, sampling grid u16, offset u64, bytes u32, attributes offset
//! u64, attributes bytes u32 | files u32, then per file: bytes u32, UTF-8 | facts present u8,
//! then facts u32 and per file: points u64, min 3 x f64, max 3 x f64, RGB min and max 6 x u16 |
//! checksum u64. A record of an earlier layout ("PFR1", without the facts part) is read as
//! one without facts: its store takes added files but is built again when one is removed.

use glam::DVec3;

use super::checksum::checksum64;
use super::error::LodError;
use super::fields::FieldReader;
use super::file_facts::{self, FileFacts};
use super::grid::PositionGrid;
use super::hierarchy::NodeInfo;
use super::key::NodeKey;

const MAGIC: &[u8; 4] = b"PFR2";
const MAGIC_WITHOUT_FACTS: &[u8; 4] = b"PFR1";
const CHECKSUM_SEED: &[u8] = b"store regions";

/// One region: the subtree of `key`, built from `points` original points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Region {
    pub key: NodeKey,
    pub points: u64,
    /// The subtree root's points before the levels above sampled from them; `None` for the
    /// octree's root, which nothing samples from.
    pub root: Option<NodeInfo>,
}

#[derive(Debug, Clone, PartialEq, Default)]
pub struct StoreRegions {
    pub grid: Option<PositionGrid>,
    pub regions: Vec<Region>,
    /// One entry per file the points came from (the store's owner says what an entry holds:
    /// a local store, each file's path, length and modification time).
    pub files: Vec<String>,
    /// Each file's facts, in the order of the source's parts the store was built from, then
    /// of the files each update added; `None` where the store does not know them.
    pub file_facts: Option<Vec<FileFacts>>,
}

impl StoreRegions {
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(64 + self.regions.len() * 64);
        out.extend_from_slice(MAGIC);
        match &self.grid {
            Some(grid) => {
                out.push(1);
                for v in grid
                    .scale()
                    .to_array()
                    .into_iter()
                    .chain(grid.offset().to_array())
                {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
            None => out.push(0),
        }
        out.extend_from_slice(&(self.regions.len() as u32).to_le_bytes());
        for region in &self.regions {
            let key = region.key;
            out.push(key.level);
            for c in [key.x, key.y, key.z] {
                out.extend_from_slice(&c.to_le_bytes());
            }
            out.extend_from_slice(&region.points.to_le_bytes());
            match &region.root {
                Some(root) => {
                    out.push(1);
                    out.extend_from_slice(&root.point_count.to_le_bytes());
                    out.extend_from_slice(&(root.sample_grid as u16).to_le_bytes());
                    out.extend_from_slice(&root.offset.to_le_bytes());
                    out.extend_from_slice(&root.byte_len.to_le_bytes());
                    out.extend_from_slice(&root.attributes_offset.to_le_bytes());
                    out.extend_from_slice(&root.attributes_len.to_le_bytes());
                }
                None => out.push(0),
            }
        }
        out.extend_from_slice(&(self.files.len() as u32).to_le_bytes());
        for file in &self.files {
            out.extend_from_slice(&(file.len() as u32).to_le_bytes());
            out.extend_from_slice(file.as_bytes());
        }
        match &self.file_facts {
            Some(facts) => {
                out.push(1);
                out.extend_from_slice(&(facts.len() as u32).to_le_bytes());
                for f in facts {
                    f.encode(&mut out);
                }
            }
            None => out.push(0),
        }
        let sum = checksum64(CHECKSUM_SEED, &out);
        out.extend_from_slice(&sum.to_le_bytes());
        out
    }

    pub fn decode(bytes: &[u8]) -> Result<Self, LodError> {
        let corrupt = |reason: &str| LodError::CorruptHierarchy(format!("store regions: {reason}"));
        if bytes.len() < MAGIC.len() + 8 {
            return Err(corrupt("shorter than the header"));
        }
        let (body, sum) = bytes.split_at(bytes.len() - 8);
        if checksum64(CHECKSUM_SEED, body).to_le_bytes() != sum {
            return Err(corrupt("checksum mismatch"));
        }
        let mut r = FieldReader::new(body, "store regions: truncated");
        let with_facts = match r.take(4)? {
            m if m == MAGIC => true,
            m if m == MAGIC_WITHOUT_FACTS => false,
            _ => return Err(corrupt("not a regions record")),
        };
        let grid = match r.u8()? {
            0 => None,
            1 => {
                let scale = DVec3::new(r.f64()?, r.f64()?, r.f64()?);
                let offset = DVec3::new(r.f64()?, r.f64()?, r.f64()?);
                Some(PositionGrid::new(scale, offset).ok_or_else(|| corrupt("an unusable grid"))?)
            }
            _ => return Err(corrupt("a grid marker other than 0 or 1")),
        };
        let count = r.u32()? as usize;
        if count > body.len() / 26 {
            return Err(corrupt("more regions than bytes"));
        }
        let mut regions = Vec::with_capacity(count);
        for _ in 0..count {
            let key = NodeKey {
                level: r.u8()?,
                x: r.u32()?,
                y: r.u32()?,
                z: r.u32()?,
            };
            let points = r.u64()?;
            let root = match r.u8()? {
                0 => None,
                1 => {
                    let point_count = r.u32()?;
                    let sample_grid = u32::from(r.u16()?);
                    let offset = r.u64()?;
                    let byte_len = r.u32()?;
                    let info = NodeInfo {
                        point_count,
                        sample_grid,
                        attributes_offset: r.u64()?,
                        attributes_len: r.u32()?,
                        ..NodeInfo::empty(key)
                    };
                    Some(info.in_one_piece(offset, byte_len))
                }
                _ => return Err(corrupt("a root marker other than 0 or 1")),
            };
            regions.push(Region { key, points, root });
        }
        let files = r.u32()? as usize;
        if files > body.len() / 4 {
            return Err(corrupt("more files than bytes"));
        }
        let mut names = Vec::with_capacity(files);
        for _ in 0..files {
            let len = r.u32()? as usize;
            let text =
                std::str::from_utf8(r.take(len)?).map_err(|_| corrupt("a file not UTF-8"))?;
            names.push(text.to_string());
        }
        let file_facts = match with_facts.then(|| r.u8()).transpose()? {
            None | Some(0) => None,
            Some(1) => {
                let count = r.u32()? as usize;
                if count > body.len() / file_facts::ENCODED_BYTES {
                    return Err(corrupt("more file facts than bytes"));
                }
                let facts: Result<Vec<FileFacts>, LodError> =
                    (0..count).map(|_| FileFacts::decode(&mut r)).collect();
                Some(facts?)
            }
            Some(_) => return Err(corrupt("a facts marker other than 0 or 1")),
        };
        if !r.at_end() {
            return Err(corrupt("trailing bytes"));
        }
        Ok(Self {
            grid,
            regions,
            files: names,
            file_facts,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::UVec3;

    #[test]
    fn regions_round_trip_and_damage_is_refused() {
        let key = NodeKey::new(3, UVec3::new(1, 2, 3));
        let root = NodeInfo {
            point_count: 7,
            sample_grid: 128,
            attributes_offset: 900,
            attributes_len: 40,
            ..NodeInfo::empty(key)
        }
        .in_one_piece(500, 120);
        let regions = StoreRegions {
            grid: PositionGrid::new(DVec3::splat(0.01), DVec3::new(1.0, 2.0, 3.0)),
            regions: vec![
                Region {
                    key,
                    points: 1_000,
                    root: Some(root),
                },
                Region {
                    key: NodeKey::ROOT,
                    points: 5,
                    root: None,
                },
            ],
            files: vec!["a.las 10 bytes".into(), "b.laz".into()],
            file_facts: Some(vec![
                FileFacts {
                    points: 9,
                    min: DVec3::new(1.0, 2.0, 3.0),
                    max: DVec3::new(4.0, 5.0, 6.0),
                    min_rgb: [1, 2, 3],
                    max_rgb: [200, 210, 220],
                },
                FileFacts::default(),
            ]),
        };
        let bytes = regions.encode();
        assert_eq!(StoreRegions::decode(&bytes).expect("decoded"), regions);
        let mut damaged = bytes.clone();
        damaged[10] ^= 1;
        assert!(StoreRegions::decode(&damaged).is_err());
        assert!(StoreRegions::decode(&bytes[..bytes.len() - 3]).is_err());
    }
}

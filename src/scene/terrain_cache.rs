//! A terrain block's height range kept in the bake cache. Decoding the
//! heights of every block is most of a large world's load once its chunks
//! come from the cache, yet a re-bake after an edit traces near a few
//! blocks: the others need only their height range (their boxes, the
//! world's bounds). The ranges of a space's blocks are kept in one entry,
//! each under the content key of its `.cdata` file's bytes and entry, so a
//! block read back is the block decoded, its samples decoded when first
//! read.

use crate::cache::codec::{Decoder, Encoder};
use crate::cache::{Cache, Key, KeyHasher, Kind};
use std::collections::BTreeMap;
use std::path::Path;

use super::terrain::HeightRange;

/// What a block read from `entry` of the file whose bytes' content key is
/// `content` was read from: the block's [`super::TerrainBlock::source`].
pub fn source_key(content: &Key, entry: &str) -> Key {
    KeyHasher::content("terrain entry")
        .key(content)
        .str(entry)
        .finish()
}

/// The key of the [`Kind::Terrain`] entry of the space in `space_dir`:
/// one entry for all its blocks (an entry per block would cost a file
/// system block each, more than the world's own height data is worth).
pub fn key(cache: &Cache, space_dir: &Path) -> Key {
    cache
        .hasher(Kind::Terrain)
        .str("height ranges")
        .str(&space_dir.to_string_lossy())
        .finish()
}

/// Blocks' height ranges by their [`source_key`].
#[derive(Debug, Default, Clone, PartialEq)]
pub struct HeightRanges(pub BTreeMap<Key, HeightRange>);

impl HeightRanges {
    pub fn get(&self, source: &Key) -> Option<HeightRange> {
        self.0.get(source).copied()
    }
}

pub fn encode(ranges: &HeightRanges) -> Vec<u8> {
    let mut out = Encoder::new();
    out.var(ranges.0.len() as u64);
    for (source, range) in &ranges.0 {
        out.bytes(&source.0).f32(range.low).f32(range.high);
    }
    out.into_bytes()
}

/// The ranges `encode` made, `None` for bytes it cannot have made.
pub fn decode(bytes: &[u8]) -> Option<HeightRanges> {
    let mut d = Decoder::new(bytes);
    let count = d.len(40).ok()?;
    let mut ranges = BTreeMap::new();
    for _ in 0..count {
        let source = Key(d.bytes().ok()?.try_into().ok()?);
        let range = HeightRange {
            low: d.f32().ok()?,
            high: d.f32().ok()?,
        };
        if !range.is_sound() {
            return None;
        }
        ranges.insert(source, range);
    }
    (d.is_done() && ranges.len() == count).then_some(HeightRanges(ranges))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_come_back_and_damaged_values_do_not() {
        let range = |low, high| HeightRange { low, high };
        let ranges = HeightRanges(BTreeMap::from([
            (Key([1; 32]), range(-3.25, 118.5)),
            (Key([2; 32]), range(0.0, 0.0)),
        ]));
        let bytes = encode(&ranges);
        assert_eq!(decode(&bytes), Some(ranges.clone()));
        assert_eq!(
            decode(&encode(&HeightRanges::default())),
            Some(HeightRanges::default())
        );
        assert_eq!(decode(&bytes[..bytes.len() - 1]), None);
        assert_eq!(decode(&[bytes.clone(), vec![0]].concat()), None);
        for bad in [
            range(2.0, 1.0),
            range(f32::NAN, 1.0),
            range(0.0, f32::INFINITY),
        ] {
            let mut damaged = ranges.clone();
            damaged.0.insert(Key([3; 32]), bad);
            assert_eq!(decode(&encode(&damaged)), None, "{bad:?}");
        }
    }

    #[test]
    fn the_source_names_the_entry_too() {
        let content = Key([7; 32]);
        assert_ne!(
            source_key(&content, "terrain2"),
            source_key(&content, "terrain")
        );
        assert_ne!(
            source_key(&content, "terrain2"),
            source_key(&Key([8; 32]), "terrain2")
        );
    }
}

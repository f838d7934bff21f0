//! A terrain block's height range kept in the bake cache. Decoding the
//! heights of every block is most of a large world's load once its chunks
//! come from the cache, yet a re-bake after an edit traces near a few
//! blocks: the others need only their height range (their boxes, the
//! world's bounds). The range is kept under the key of the `.cdata` file's
//! bytes and entry, so a block read back is the block decoded, its samples
//! decoded when first read.

use crate::cache::codec::{Decoder, Encoder};
use crate::cache::{Cache, Key, KeyHasher, Kind};

use super::terrain::HeightRange;

/// What a block read from `entry` of the file whose bytes' content key is
/// `content` was read from: the block's [`super::TerrainBlock::source`].
pub fn source_key(content: &Key, entry: &str) -> Key {
    KeyHasher::content("terrain entry")
        .key(content)
        .str(entry)
        .finish()
}

/// The key of the [`Kind::Terrain`] entry of the block `source` keys.
pub fn key(cache: &Cache, source: &Key) -> Key {
    cache.hasher(Kind::Terrain).key(source).finish()
}

pub fn encode(range: HeightRange) -> Vec<u8> {
    let mut out = Encoder::new();
    out.f32(range.low).f32(range.high);
    out.into_bytes()
}

/// The range `encode` made, `None` for bytes it cannot have made.
pub fn decode(bytes: &[u8]) -> Option<HeightRange> {
    let mut d = Decoder::new(bytes);
    let range = HeightRange {
        low: d.f32().ok()?,
        high: d.f32().ok()?,
    };
    let sound = range.low.is_finite() && range.high.is_finite() && range.low <= range.high;
    (d.is_done() && sound).then_some(range)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_range_comes_back_and_damaged_values_do_not() {
        let range = HeightRange {
            low: -3.25,
            high: 118.5,
        };
        let bytes = encode(range);
        assert_eq!(decode(&bytes), Some(range));
        assert_eq!(decode(&bytes[..7]), None);
        assert_eq!(decode(&[bytes.clone(), vec![0]].concat()), None);
        let upside_down = encode(HeightRange {
            low: 2.0,
            high: 1.0,
        });
        assert_eq!(decode(&upside_down), None);
        assert_eq!(
            decode(&encode(HeightRange {
                low: f32::NAN,
                high: 1.0
            })),
            None
        );
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

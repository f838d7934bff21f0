//! A 128-bit content hash: the fingerprint of every file a bake read and
//! the checksum of a partial result (`formats::partial`). It detects
//! accidental change (an edited chunk, a flipped bit, a truncated copy),
//! not an adversary, so a fast non-cryptographic mix is enough; it is
//! written out here because its value is stored in files and must never
//! change with a compiler or dependency version (std's `DefaultHasher` may).

use std::fmt;

/// A content hash: two independent 64-bit lanes over the bytes and length.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct Digest(pub [u8; 16]);

const K1: u64 = 0x9E37_79B9_7F4A_7C15;
const K2: u64 = 0xC2B2_AE3D_27D4_EB4F;
const K3: u64 = 0x1656_67B1_9E37_79F9;

/// SplitMix64's finaliser: every input bit reaches every output bit.
fn avalanche(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl Digest {
    /// The hash of `bytes`.
    pub fn of(bytes: &[u8]) -> Digest {
        let mut a = K1;
        let mut b = K2;
        let mut words = bytes.chunks_exact(8);
        for word in &mut words {
            let w = u64::from_le_bytes(word.try_into().unwrap_or_default());
            a = (a ^ w).wrapping_mul(K2).rotate_left(29);
            b = (b ^ w.rotate_left(17)).wrapping_mul(K3).rotate_left(31);
        }
        let mut tail = [0u8; 8];
        tail[..words.remainder().len()].copy_from_slice(words.remainder());
        let w = u64::from_le_bytes(tail);
        a = (a ^ w).wrapping_mul(K2).rotate_left(29);
        b = (b ^ w.rotate_left(17)).wrapping_mul(K3).rotate_left(31);
        let length = bytes.len() as u64;
        let hi = avalanche(a ^ length.wrapping_mul(K3) ^ b.rotate_left(13));
        let lo = avalanche(b ^ length.wrapping_mul(K1) ^ a.rotate_left(41));
        let mut out = [0u8; 16];
        out[..8].copy_from_slice(&hi.to_le_bytes());
        out[8..].copy_from_slice(&lo.to_le_bytes());
        Digest(out)
    }
}

impl fmt::Display for Digest {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for byte in self.0 {
            write!(f, "{byte:02x}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_single_bit_flip_and_truncation_changes_the_digest() {
        let bytes: Vec<u8> = (0..77u32).map(|i| (i * 37 % 251) as u8).collect();
        let base = Digest::of(&bytes);
        for i in 0..bytes.len() * 8 {
            let mut flipped = bytes.clone();
            flipped[i / 8] ^= 1 << (i % 8);
            assert_ne!(Digest::of(&flipped), base, "bit {i}");
        }
        for len in 0..bytes.len() {
            assert_ne!(Digest::of(&bytes[..len]), base, "length {len}");
        }
        // Trailing zeros are not absorbed by the zero-padded tail word.
        let mut padded = bytes.clone();
        padded.push(0);
        assert_ne!(Digest::of(&padded), base);
        assert_eq!(Digest::of(&bytes), base, "a pure function of the bytes");
    }

    #[test]
    fn the_value_is_fixed() {
        // Stored in files: a change of the function makes every partial
        // unreadable and every fingerprint different, so it is pinned (the
        // value is this function's own, recorded when it was written).
        assert_eq!(Digest::of(b"shadowcull").to_string(), PINNED);
        assert_ne!(Digest::of(b"a"), Digest::of(b"b"));
    }

    const PINNED: &str = "eedcc6f5f5a1071d77275ae0b59a625c";
}

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
        let mut digester = Digester::new();
        digester.update(bytes);
        digester.finish()
    }
}

/// [`Digest::of`] the bytes given in pieces: the same value as of their
/// concatenation, without making it (a chunk with its masks zeroed is
/// hashed as it is spliced).
#[derive(Debug, Clone)]
pub struct Digester {
    a: u64,
    b: u64,
    /// Bytes of a word not yet complete, and how many.
    pending: [u8; 8],
    pending_len: usize,
    length: u64,
}

impl Default for Digester {
    fn default() -> Digester {
        Digester::new()
    }
}

impl Digester {
    pub fn new() -> Digester {
        Digester {
            a: K1,
            b: K2,
            pending: [0; 8],
            pending_len: 0,
            length: 0,
        }
    }

    #[inline]
    fn mix(&mut self, w: u64) {
        self.a = (self.a ^ w).wrapping_mul(K2).rotate_left(29);
        self.b = (self.b ^ w.rotate_left(17))
            .wrapping_mul(K3)
            .rotate_left(31);
    }

    pub fn update(&mut self, mut bytes: &[u8]) {
        self.length += bytes.len() as u64;
        if self.pending_len > 0 {
            let take = (8 - self.pending_len).min(bytes.len());
            self.pending[self.pending_len..self.pending_len + take].copy_from_slice(&bytes[..take]);
            self.pending_len += take;
            bytes = &bytes[take..];
            if self.pending_len < 8 {
                return;
            }
            self.mix(u64::from_le_bytes(self.pending));
            self.pending_len = 0;
        }
        let mut words = bytes.chunks_exact(8);
        for word in &mut words {
            self.mix(u64::from_le_bytes(word.try_into().unwrap_or_default()));
        }
        let rest = words.remainder();
        self.pending[..rest.len()].copy_from_slice(rest);
        self.pending_len = rest.len();
    }

    /// The digest: the last word (zero-padded, mixed even when empty) and
    /// the length folded in.
    pub fn finish(mut self) -> Digest {
        let mut tail = [0u8; 8];
        tail[..self.pending_len].copy_from_slice(&self.pending[..self.pending_len]);
        self.mix(u64::from_le_bytes(tail));
        let (a, b, length) = (self.a, self.b, self.length);
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

    #[test]
    fn pieces_digest_as_their_concatenation() {
        let bytes: Vec<u8> = (0..200u32).map(|i| (i * 73 % 256) as u8).collect();
        for len in [0, 1, 7, 8, 9, 15, 16, 17, 63, 200] {
            let whole = Digest::of(&bytes[..len]);
            for cuts in [
                vec![],
                vec![0],
                vec![1],
                vec![3, 5],
                vec![7, 8, 9],
                vec![2, 11, 30, 31],
            ] {
                let mut digester = Digester::new();
                let mut at = 0;
                for cut in cuts.into_iter().filter(|&c| c <= len) {
                    digester.update(&bytes[at..cut]);
                    at = cut;
                }
                digester.update(&bytes[at..len]);
                assert_eq!(digester.finish(), whole, "{len} bytes");
            }
        }
    }

    const PINNED: &str = "eedcc6f5f5a1071d77275ae0b59a625c";
}

//! The partial result of one shard of a distributed bake (`bake --shard I/N
//! --partial FILE`), read back by `merge`.
//!
//! Binary, versioned and checksummed, so a partial copied between machines
//! is either read whole or refused by name: a truncated or bit-flipped file
//! fails the checksum, a file of another format version says so. Compact:
//! each unit's answer is a caster bitset, and the body is deflated (a shard
//! sees a small part of the world, so its bitsets are mostly zero).
//!
//! Layout (little endian):
//! ```text
//! 0   magic  "SCULLPRT"
//! 8   u32    format version (VERSION)
//! 12  u64    body length, inflated
//! 20  u64    body length, deflated (n)
//! 28  n      body, deflated
//! 28+n 16    Digest of bytes 0 .. 28+n
//! ```
//! Body: fingerprint (settings text; file count, then per file its name and
//! digest), shard index, shard count, plan digest, caster count, unit
//! count, then per unit: light, first tile, end tile, rays, seconds and
//! `ceil(casters / 64)` words of caster bits.

use crate::digest::Digest;
use crate::error::FormatError;
use std::io::{Read, Write};

pub const MAGIC: [u8; 8] = *b"SCULLPRT";
/// Bumped whenever the layout or the meaning of a field changes.
pub const VERSION: u32 = 1;
const HEADER: usize = 28;
const CHECKSUM: usize = 16;
/// The largest inflated body accepted (a bomb guard): 32 lights of a
/// world of 2^31 casters would not fit, real partials are far smaller.
const MAX_BODY: u64 = 4 << 30;

/// What the inputs of a bake were: the effective settings (as canonical
/// text) and every file the bake read with its content hash.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Fingerprint {
    pub settings: String,
    /// (name relative to its res root, hash), sorted by name.
    pub files: Vec<(String, Digest)>,
}

/// One unit of work's answer: the casters the rays of tiles
/// `start..end` of light `light` proved useful.
#[derive(Debug, Clone, PartialEq)]
pub struct PartialUnit {
    pub light: u32,
    pub start: u64,
    pub end: u64,
    pub rays: u64,
    pub seconds: f64,
    /// Caster bits, 64 per word.
    pub words: Vec<u64>,
}

/// A whole partial file.
#[derive(Debug, Clone, PartialEq)]
pub struct Partial {
    pub fingerprint: Fingerprint,
    pub shard: u32,
    pub shards: u32,
    /// The digest of the plan the shard followed.
    pub plan: Digest,
    pub casters: u64,
    pub units: Vec<PartialUnit>,
}

pub fn encode(partial: &Partial) -> Vec<u8> {
    let mut body = Vec::new();
    put_str(&mut body, &partial.fingerprint.settings);
    put_u32(&mut body, partial.fingerprint.files.len() as u32);
    for (name, digest) in &partial.fingerprint.files {
        put_str(&mut body, name);
        body.extend_from_slice(&digest.0);
    }
    put_u32(&mut body, partial.shard);
    put_u32(&mut body, partial.shards);
    body.extend_from_slice(&partial.plan.0);
    put_u64(&mut body, partial.casters);
    put_u32(&mut body, partial.units.len() as u32);
    for unit in &partial.units {
        put_u32(&mut body, unit.light);
        put_u64(&mut body, unit.start);
        put_u64(&mut body, unit.end);
        put_u64(&mut body, unit.rays);
        put_u64(&mut body, unit.seconds.to_bits());
        for word in &unit.words {
            put_u64(&mut body, *word);
        }
    }
    let mut deflater =
        flate2::write::DeflateEncoder::new(Vec::new(), flate2::Compression::default());
    // Writing into a Vec cannot fail.
    let _ = deflater.write_all(&body);
    let deflated = deflater.finish().unwrap_or_default();
    let mut out = Vec::with_capacity(HEADER + deflated.len() + CHECKSUM);
    out.extend_from_slice(&MAGIC);
    put_u32(&mut out, VERSION);
    put_u64(&mut out, body.len() as u64);
    put_u64(&mut out, deflated.len() as u64);
    out.extend_from_slice(&deflated);
    let checksum = Digest::of(&out);
    out.extend_from_slice(&checksum.0);
    out
}

pub fn decode(bytes: &[u8]) -> std::result::Result<Partial, FormatError> {
    if bytes.len() < MAGIC.len() || bytes[..MAGIC.len()] != MAGIC {
        return Err(FormatError::whole_file(
            "not a shadowcull partial result (no SCULLPRT magic); give the files written by `bake --shard I/N --partial FILE`",
        ));
    }
    if bytes.len() < HEADER + CHECKSUM {
        return Err(damaged(format!("only {} bytes", bytes.len())));
    }
    let mut header = Cursor::new(&bytes[..HEADER], 8);
    let version = header.u32()?;
    if version != VERSION {
        return Err(FormatError::at_byte(
            8,
            format!("partial format version {version}; this shadowcull reads version {VERSION}: bake the shards and merge with the same shadowcull"),
        ));
    }
    let inflated_len = header.u64()?;
    let deflated_len = header.u64()?;
    let expected = (HEADER as u64)
        .checked_add(deflated_len)
        .and_then(|n| n.checked_add(CHECKSUM as u64));
    if expected != Some(bytes.len() as u64) {
        return Err(damaged(format!(
            "{} bytes, the header promises {}",
            bytes.len(),
            expected.map_or("more than fits".to_string(), |n| n.to_string())
        )));
    }
    let end = bytes.len() - CHECKSUM;
    if Digest::of(&bytes[..end]).0[..] != bytes[end..] {
        return Err(damaged("the checksum does not match its content".into()));
    }
    if inflated_len > MAX_BODY {
        return Err(damaged(format!("an inflated body of {inflated_len} bytes")));
    }
    let mut body = Vec::with_capacity(inflated_len.min(1 << 26) as usize);
    flate2::read::DeflateDecoder::new(&bytes[HEADER..end])
        .take(inflated_len + 1)
        .read_to_end(&mut body)
        .map_err(|e| damaged(format!("its body does not inflate: {e}")))?;
    if body.len() as u64 != inflated_len {
        return Err(damaged("its body inflates to another length".into()));
    }
    decode_body(&body).map_err(|e| damaged(format!("in its body, {}", e.message)))
}

fn damaged(what: String) -> FormatError {
    FormatError::whole_file(format!(
        "damaged partial result ({what}): copy it again or re-run that shard"
    ))
}

fn decode_body(body: &[u8]) -> std::result::Result<Partial, FormatError> {
    let mut c = Cursor::new(body, 0);
    let settings = c.str()?;
    let file_count = c.u32()? as usize;
    let mut files = Vec::with_capacity(file_count.min(body.len() / 20));
    for _ in 0..file_count {
        files.push((c.str()?, c.digest()?));
    }
    let shard = c.u32()?;
    let shards = c.u32()?;
    let plan = c.digest()?;
    let casters = c.u64()?;
    let words = casters.div_ceil(64) as usize;
    let unit_count = c.u32()? as usize;
    let mut units = Vec::with_capacity(unit_count.min(body.len() / 36));
    for _ in 0..unit_count {
        let (light, start, end, rays) = (c.u32()?, c.u64()?, c.u64()?, c.u64()?);
        let seconds = f64::from_bits(c.u64()?);
        if words > c.remaining() / 8 {
            return Err(c.error("a unit's caster bits run past the end"));
        }
        let words = (0..words).map(|_| c.u64()).collect::<Result<_, _>>()?;
        units.push(PartialUnit {
            light,
            start,
            end,
            rays,
            seconds,
            words,
        });
    }
    if c.remaining() != 0 {
        return Err(c.error("bytes after the last unit"));
    }
    Ok(Partial {
        fingerprint: Fingerprint { settings, files },
        shard,
        shards,
        plan,
        casters,
        units,
    })
}

fn put_u32(out: &mut Vec<u8>, v: u32) {
    out.extend_from_slice(&v.to_le_bytes());
}

fn put_u64(out: &mut Vec<u8>, v: u64) {
    out.extend_from_slice(&v.to_le_bytes());
}

fn put_str(out: &mut Vec<u8>, s: &str) {
    put_u32(out, s.len() as u32);
    out.extend_from_slice(s.as_bytes());
}

/// Bounds-checked little-endian reads.
struct Cursor<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Cursor<'a> {
    /// Reads `bytes` from offset `start`.
    fn new(bytes: &'a [u8], start: usize) -> Self {
        Cursor {
            bytes,
            at: start.min(bytes.len()),
        }
    }

    fn remaining(&self) -> usize {
        self.bytes.len() - self.at
    }

    fn error(&self, message: &str) -> FormatError {
        FormatError::at_byte(self.at, message)
    }

    fn take(&mut self, n: usize) -> std::result::Result<&'a [u8], FormatError> {
        if n > self.remaining() {
            return Err(self.error("ends early"));
        }
        let out = &self.bytes[self.at..self.at + n];
        self.at += n;
        Ok(out)
    }

    fn u32(&mut self) -> std::result::Result<u32, FormatError> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().unwrap_or_default(),
        ))
    }

    fn u64(&mut self) -> std::result::Result<u64, FormatError> {
        Ok(u64::from_le_bytes(
            self.take(8)?.try_into().unwrap_or_default(),
        ))
    }

    fn digest(&mut self) -> std::result::Result<Digest, FormatError> {
        Ok(Digest(self.take(16)?.try_into().unwrap_or_default()))
    }

    fn str(&mut self) -> std::result::Result<String, FormatError> {
        let len = self.u32()? as usize;
        let bytes = self.take(len)?;
        String::from_utf8(bytes.to_vec()).map_err(|_| self.error("a name is not UTF-8"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Partial {
        Partial {
            fingerprint: Fingerprint {
                settings: "faceCulling = back\n".into(),
                files: vec![("spaces/a/00000000o.chunk".into(), Digest::of(b"chunk"))],
            },
            shard: 1,
            shards: 3,
            plan: Digest::of(b"plan"),
            casters: 70,
            units: vec![PartialUnit {
                light: 0,
                start: 4,
                end: 9,
                rays: 5120,
                seconds: 0.25,
                words: vec![0b1011, 1 << 5],
            }],
        }
    }

    #[test]
    fn round_trip() {
        let partial = sample();
        assert_eq!(decode(&encode(&partial)).unwrap(), partial);
    }

    #[test]
    fn every_truncation_and_bit_flip_is_refused() {
        let bytes = encode(&sample());
        for len in 0..bytes.len() {
            assert!(decode(&bytes[..len]).is_err(), "truncated to {len}");
        }
        for bit in 0..bytes.len() * 8 {
            let mut flipped = bytes.clone();
            flipped[bit / 8] ^= 1 << (bit % 8);
            let err = decode(&flipped).expect_err("a flipped bit is noticed");
            assert!(
                err.message.contains("damaged")
                    || err.message.contains("magic")
                    || err.message.contains("version"),
                "bit {bit}: {err}"
            );
        }
    }

    #[test]
    fn another_version_says_so() {
        let mut bytes = encode(&sample());
        bytes[8] = 9;
        let end = bytes.len() - CHECKSUM;
        let checksum = Digest::of(&bytes[..end]);
        bytes[end..].copy_from_slice(&checksum.0);
        let err = decode(&bytes).unwrap_err();
        assert!(err.message.contains("version 9"), "{err}");
    }
}

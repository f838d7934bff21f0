//! A compact binary encoding for cache values: little-endian fixed-width
//! numbers, LEB128 lengths, nothing else. A value is decoded only after its
//! entry's checksum held, but the decoder still checks every length against
//! the bytes left, so a value of another shape is an error, never a panic.

/// Appends values to a byte buffer.
#[derive(Debug, Default)]
pub struct Encoder {
    bytes: Vec<u8>,
}

impl Encoder {
    pub fn new() -> Encoder {
        Encoder::default()
    }

    pub fn into_bytes(self) -> Vec<u8> {
        self.bytes
    }

    pub fn u8(&mut self, v: u8) -> &mut Self {
        self.bytes.push(v);
        self
    }

    pub fn u32(&mut self, v: u32) -> &mut Self {
        self.bytes.extend_from_slice(&v.to_le_bytes());
        self
    }

    pub fn u64(&mut self, v: u64) -> &mut Self {
        self.bytes.extend_from_slice(&v.to_le_bytes());
        self
    }

    pub fn f32(&mut self, v: f32) -> &mut Self {
        self.u32(v.to_bits())
    }

    pub fn f64(&mut self, v: f64) -> &mut Self {
        self.u64(v.to_bits())
    }

    /// An unsigned number in as few bytes as it needs (LEB128).
    pub fn var(&mut self, mut v: u64) -> &mut Self {
        loop {
            let low = (v & 0x7F) as u8;
            v >>= 7;
            if v == 0 {
                self.bytes.push(low);
                return self;
            }
            self.bytes.push(low | 0x80);
        }
    }

    pub fn bytes(&mut self, v: &[u8]) -> &mut Self {
        self.var(v.len() as u64);
        self.bytes.extend_from_slice(v);
        self
    }

    pub fn str(&mut self, v: &str) -> &mut Self {
        self.bytes(v.as_bytes())
    }
}

/// Why a value could not be decoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("cache value ends early or holds a bad length at byte {at}")]
pub struct DecodeError {
    pub at: usize,
}

/// Reads values back in the order they were encoded.
#[derive(Debug)]
pub struct Decoder<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Decoder<'a> {
    pub fn new(bytes: &'a [u8]) -> Decoder<'a> {
        Decoder { bytes, at: 0 }
    }

    /// Whether every byte was read (a value with bytes to spare is of
    /// another shape).
    pub fn is_done(&self) -> bool {
        self.at == self.bytes.len()
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], DecodeError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&end| end <= self.bytes.len())
            .ok_or(DecodeError { at: self.at })?;
        let slice = &self.bytes[self.at..end];
        self.at = end;
        Ok(slice)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], DecodeError> {
        let at = self.at;
        self.take(N)?.try_into().map_err(|_| DecodeError { at })
    }

    pub fn u8(&mut self) -> Result<u8, DecodeError> {
        Ok(self.array::<1>()?[0])
    }

    pub fn u32(&mut self) -> Result<u32, DecodeError> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    pub fn u64(&mut self) -> Result<u64, DecodeError> {
        Ok(u64::from_le_bytes(self.array()?))
    }

    pub fn f32(&mut self) -> Result<f32, DecodeError> {
        Ok(f32::from_bits(self.u32()?))
    }

    pub fn f64(&mut self) -> Result<f64, DecodeError> {
        Ok(f64::from_bits(self.u64()?))
    }

    pub fn var(&mut self) -> Result<u64, DecodeError> {
        let at = self.at;
        let mut value = 0u64;
        for shift in (0..64).step_by(7) {
            let byte = self.u8()?;
            value |= u64::from(byte & 0x7F) << shift;
            if byte & 0x80 == 0 {
                return Ok(value);
            }
        }
        Err(DecodeError { at })
    }

    /// A length that must fit in the bytes left (each item at least
    /// `item_bytes` long), so a damaged length cannot ask for memory.
    pub fn len(&mut self, item_bytes: usize) -> Result<usize, DecodeError> {
        let at = self.at;
        let n = self.var()?;
        let left = (self.bytes.len() - self.at) as u64;
        if n.saturating_mul(item_bytes.max(1) as u64) > left && item_bytes > 0 {
            return Err(DecodeError { at });
        }
        usize::try_from(n).map_err(|_| DecodeError { at })
    }

    pub fn bytes(&mut self) -> Result<&'a [u8], DecodeError> {
        let n = self.len(1)?;
        self.take(n)
    }

    pub fn str(&mut self) -> Result<String, DecodeError> {
        let at = self.at;
        let bytes = self.bytes()?;
        String::from_utf8(bytes.to_vec()).map_err(|_| DecodeError { at })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_come_back_in_order_and_short_input_is_an_error() {
        let mut e = Encoder::new();
        e.u8(7).u32(0xDEAD_BEEF).u64(u64::MAX).f32(-0.5).f64(1e300);
        e.var(0)
            .var(127)
            .var(128)
            .var(u64::MAX)
            .str("é")
            .bytes(&[1, 2]);
        let bytes = e.into_bytes();
        let mut d = Decoder::new(&bytes);
        assert_eq!(d.u8().unwrap(), 7);
        assert_eq!(d.u32().unwrap(), 0xDEAD_BEEF);
        assert_eq!(d.u64().unwrap(), u64::MAX);
        assert_eq!(d.f32().unwrap(), -0.5);
        assert_eq!(d.f64().unwrap(), 1e300);
        for v in [0, 127, 128, u64::MAX] {
            assert_eq!(d.var().unwrap(), v);
        }
        assert_eq!(d.str().unwrap(), "é");
        assert_eq!(d.bytes().unwrap(), &[1, 2]);
        assert!(d.is_done());
        for cut in 0..bytes.len() {
            let mut d = Decoder::new(&bytes[..cut]);
            let all = (|| -> Result<(), DecodeError> {
                d.u8()?;
                d.u32()?;
                d.u64()?;
                d.f32()?;
                d.f64()?;
                for _ in 0..4 {
                    d.var()?;
                }
                d.str()?;
                d.bytes()?;
                Ok(())
            })();
            assert!(all.is_err(), "cut at {cut}");
        }
    }

    #[test]
    fn a_damaged_length_cannot_ask_for_more_than_the_bytes_left() {
        let mut e = Encoder::new();
        e.var(u64::MAX / 2);
        let bytes = e.into_bytes();
        assert!(Decoder::new(&bytes).len(8).is_err());
        assert!(Decoder::new(&bytes).bytes().is_err());
    }
}

//! BinSection containers (resmgr/bin_section.cpp): `.primitives`, 1.x `.cdata`.
//!
//! A BinSection is a flat archive of named binary blobs with the index at the
//! end of the file. Geometry lives in these containers, so every length in
//! the index is checked against the file before any entry is handed out:
//! a corrupt `.primitives` file must give an error with a byte offset, never
//! a panic or a slice into the wrong bytes.
//!
//! Two layouts exist. Files written by the engine since 1.x start with the
//! magic `65 4E A1 42`, every index entry carries 16 reserved bytes and names
//! are padded to 4 bytes. Older files have no magic (data starts at byte 0),
//! carry the reserved bytes only when bit 31 of the entry's data length is
//! set, and do not pad names. Data blocks are padded to 4 bytes in both.

use crate::error::FormatError;
use std::ops::Range;

pub const MAGIC: [u8; 4] = [0x65, 0x4E, 0xA1, 0x42];

/// Bytes of `{ u32 preloadLen; u32 version; u64 modified }` in an index entry.
const RESERVED_LEN: usize = 16;

/// Bit 31 of an entry's data length: in magic-less files it says the entry
/// carries the reserved bytes; it is never part of the length.
const EXTENDED_BIT: u32 = 1 << 31;

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Entry {
    pub name: String,
    /// Byte range of the entry's data in the container.
    pub data: Range<usize>,
}

#[derive(Debug, Clone)]
pub struct BinSection<'a> {
    pub bytes: &'a [u8],
    pub entries: Vec<Entry>,
}

impl<'a> BinSection<'a> {
    /// The data of the first entry called `name` (as the engine's
    /// `findChild` does) and its byte offset in the container, so that errors
    /// found while decoding the entry can be `.shifted(offset)` to point into
    /// the whole file.
    pub fn get(&self, name: &str) -> Option<(&'a [u8], usize)> {
        let entry = self.entries.iter().find(|e| e.name == name)?;
        // `parse` checked every range against `bytes`; `get` keeps this
        // panic-free even for a hand-built value.
        let data = self.bytes.get(entry.data.clone())?;
        Some((data, entry.data.start))
    }

    /// Whether the container starts with the BinSection magic.
    pub fn has_magic(&self) -> bool {
        self.bytes.starts_with(&MAGIC)
    }
}

fn pad4(len: usize) -> Option<usize> {
    len.checked_add(3).map(|l| l & !3)
}

fn read_u32(bytes: &[u8], at: usize) -> Option<u32> {
    let end = at.checked_add(4)?;
    let b: [u8; 4] = bytes.get(at..end)?.try_into().ok()?;
    Some(u32::from_le_bytes(b))
}

/// Parses the container's index. The entries' data is not looked at.
pub fn parse(bytes: &[u8]) -> Result<BinSection<'_>, FormatError> {
    let layout = Layout::of(bytes)?;
    let mut entries = Vec::new();
    let mut offset = layout.index_start;
    let mut data_offset = layout.data_start;
    while offset < layout.index_end {
        let entry_at = offset;
        let Record {
            name,
            data_len,
            next,
        } = layout.record(bytes, offset, entries.len())?;
        offset = next;
        let index_start = layout.index_start;
        let data_end = data_offset
            .checked_add(data_len)
            .filter(|&end| end <= index_start)
            .ok_or_else(|| {
                FormatError::at_byte(
                    entry_at,
                    format!(
                        "BinSection entry `{name}` claims {data_len} bytes of data at byte \
                         {data_offset}, which runs past the start of the index at byte \
                         {index_start}; the file is truncated or corrupt"
                    ),
                )
            })?;
        entries.push(Entry {
            name,
            data: data_offset..data_end,
        });
        // The padding of the last block may be missing without harm, so the
        // padded offset is only checked when the next entry uses it.
        data_offset = pad4(data_end).unwrap_or(usize::MAX);
    }
    Ok(BinSection { bytes, entries })
}

/// Where a container's parts lie: data from `data_start` (after the magic,
/// if any), the index in `index_start..index_end`, then the index length.
struct Layout {
    has_magic: bool,
    data_start: usize,
    index_start: usize,
    index_end: usize,
}

/// One index record as stored: its entry's name and data length, and where
/// the next record starts.
struct Record {
    name: String,
    data_len: usize,
    next: usize,
}

impl Layout {
    /// Finds the index from the length at the end of the file.
    fn of(bytes: &[u8]) -> Result<Layout, FormatError> {
        let len = bytes.len();
        if len < 4 {
            return Err(FormatError::at_byte(
                0,
                format!(
                    "BinSection is {len} bytes long, too short to hold its 4-byte index length; \
                     the file is truncated"
                ),
            ));
        }
        let has_magic = bytes.starts_with(&MAGIC);
        let data_start = if has_magic { 4 } else { 0 };
        let index_end = len - 4;
        let index_len_at = index_end;
        let raw_index_len = read_u32(bytes, index_len_at).unwrap_or(0) as i32;
        let index_start = usize::try_from(raw_index_len)
            .ok()
            .and_then(|l| index_end.checked_sub(l))
            .filter(|&start| start >= data_start)
            .ok_or_else(|| {
                FormatError::at_byte(
                    index_len_at,
                    format!(
                        "BinSection index length {raw_index_len} does not fit in the file \
                         ({} bytes available between the {} and the index length); \
                         the file is truncated or not a BinSection",
                        index_end.saturating_sub(data_start),
                        if has_magic { "magic" } else { "file start" }
                    ),
                )
            })?;
        Ok(Layout {
            has_magic,
            data_start,
            index_start,
            index_end,
        })
    }

    /// Reads the index record `number` starting at byte `entry_at`, every
    /// field checked against the end of the index.
    fn record(&self, bytes: &[u8], entry_at: usize, number: usize) -> Result<Record, FormatError> {
        let index_end = self.index_end;
        let truncated = |what: &str, at: usize| {
            FormatError::at_byte(
                at,
                format!(
                    "BinSection index entry {number} (starting at byte {entry_at}) is cut off: \
                     its {what} runs past the end of the index at byte {index_end}"
                ),
            )
        };
        let mut offset = entry_at;
        let raw_data_len = read_u32(bytes, offset)
            .filter(|_| offset + 4 <= index_end)
            .ok_or_else(|| truncated("data length", offset))?;
        offset += 4;
        if self.has_magic || raw_data_len & EXTENDED_BIT != 0 {
            if offset + RESERVED_LEN > index_end {
                return Err(truncated("16 reserved bytes", offset));
            }
            offset += RESERVED_LEN;
        }
        let data_len = (raw_data_len & !EXTENDED_BIT) as usize;
        let name_len_at = offset;
        let raw_name_len = read_u32(bytes, offset)
            .filter(|_| offset + 4 <= index_end)
            .ok_or_else(|| truncated("name length", offset))? as i32;
        offset += 4;
        let name_len = usize::try_from(raw_name_len)
            .ok()
            .filter(|&l| l <= index_end - offset)
            .ok_or_else(|| {
                FormatError::at_byte(
                    name_len_at,
                    format!(
                        "BinSection index entry {number} has name length {raw_name_len}, but only {} \
                         bytes of the index remain; the index is corrupt",
                        index_end - offset
                    ),
                )
            })?;
        let name_bytes = &bytes[offset..offset + name_len];
        let name = String::from_utf8_lossy(name_bytes).into_owned();
        let stored_name_len = if self.has_magic {
            pad4(name_len).unwrap_or(usize::MAX)
        } else {
            name_len
        };
        if stored_name_len > index_end - offset {
            return Err(truncated("name padding", offset + name_len));
        }
        Ok(Record {
            name,
            data_len,
            next: offset + stored_name_len,
        })
    }
}

/// Writes a container with the magic, padded data and a padded index, as
/// the engine's `BinSection::recollect` does (reserved bytes zero).
///
/// # Panics
/// If a section or name is longer than `i32::MAX` bytes, which the format
/// cannot express.
pub fn write(sections: &[(&str, &[u8])]) -> Vec<u8> {
    fn len_i32(len: usize, what: &str) -> [u8; 4] {
        let len = i32::try_from(len)
            .unwrap_or_else(|_| panic!("BinSection {what} of {len} bytes exceeds i32::MAX"));
        len.to_le_bytes()
    }
    let mut out = Vec::new();
    out.extend_from_slice(&MAGIC);
    for (_, data) in sections {
        out.extend_from_slice(data);
        out.resize(out.len() + (4 - data.len() % 4) % 4, 0);
    }
    let index_start = out.len();
    for (name, data) in sections {
        out.extend_from_slice(&len_i32(data.len(), "section"));
        out.extend_from_slice(&[0; RESERVED_LEN]);
        out.extend_from_slice(&len_i32(name.len(), "name"));
        out.extend_from_slice(name.as_bytes());
        out.resize(out.len() + (4 - name.len() % 4) % 4, 0);
    }
    let index_len = out.len() - index_start;
    out.extend_from_slice(&len_i32(index_len, "index"));
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::Location;
    use proptest::prelude::*;

    fn i32le(v: i32) -> [u8; 4] {
        v.to_le_bytes()
    }

    /// Magic layout, built by hand from the documented structure: two
    /// entries of odd lengths so both data and names need padding.
    fn magic_file() -> Vec<u8> {
        let mut f = MAGIC.to_vec();
        f.extend_from_slice(b"hello\0\0\0"); // 5 bytes + 3 padding, at 4
        f.extend_from_slice(b"xyz\0"); // 3 bytes + 1 padding, at 12
        let index_start = f.len();
        f.extend_from_slice(&i32le(5));
        f.extend_from_slice(&[7; 16]); // reserved: content ignored
        f.extend_from_slice(&i32le(8));
        f.extend_from_slice(b"vertices"); // already a multiple of 4
        f.extend_from_slice(&i32le(3));
        f.extend_from_slice(&[0; 16]);
        f.extend_from_slice(&i32le(3));
        f.extend_from_slice(b"abc\0");
        let index_len = (f.len() - index_start) as i32;
        f.extend_from_slice(&i32le(index_len));
        f
    }

    #[test]
    fn magic_layout_entries_and_offsets() {
        let f = magic_file();
        let bin = parse(&f).unwrap();
        assert!(bin.has_magic());
        assert_eq!(bin.entries.len(), 2);
        assert_eq!(bin.get("vertices"), Some((&b"hello"[..], 4)));
        assert_eq!(bin.get("abc"), Some((&b"xyz"[..], 12)));
        assert_eq!(bin.get("indices"), None);
    }

    /// Magic-less layout: data from byte 0, names unpadded, reserved bytes
    /// only on the entry whose length has bit 31 set.
    fn old_file() -> Vec<u8> {
        let mut f = Vec::new();
        f.extend_from_slice(b"abcdef\0\0"); // 6 bytes + 2 padding, at 0
        f.extend_from_slice(b"ghij"); // 4 bytes, at 8
        let index_start = f.len();
        f.extend_from_slice(&i32le(6));
        f.extend_from_slice(&i32le(1));
        f.extend_from_slice(b"a"); // no padding
        f.extend_from_slice(&((4u32 | EXTENDED_BIT).to_le_bytes()));
        f.extend_from_slice(&[9; 16]);
        f.extend_from_slice(&i32le(5));
        f.extend_from_slice(b"bcdef");
        let index_len = (f.len() - index_start) as i32;
        f.extend_from_slice(&i32le(index_len));
        f
    }

    #[test]
    fn old_layout_entries_and_offsets() {
        let f = old_file();
        let bin = parse(&f).unwrap();
        assert!(!bin.has_magic());
        assert_eq!(
            bin.entries,
            vec![
                Entry {
                    name: "a".into(),
                    data: 0..6
                },
                Entry {
                    name: "bcdef".into(),
                    data: 8..12
                },
            ]
        );
        assert_eq!(bin.get("bcdef"), Some((&b"ghij"[..], 8)));
    }

    #[test]
    fn empty_containers() {
        let mut f = MAGIC.to_vec();
        f.extend_from_slice(&i32le(0));
        assert!(parse(&f).unwrap().entries.is_empty());
        assert!(parse(&[0, 0, 0, 0]).unwrap().entries.is_empty());
    }

    #[test]
    fn first_of_duplicate_names_wins() {
        let f = write(&[("x", b"one"), ("x", b"two")]);
        assert_eq!(parse(&f).unwrap().get("x"), Some((&b"one"[..], 4)));
    }

    fn err_at(f: &[u8]) -> (u64, String) {
        match parse(f) {
            Err(FormatError {
                at: Location::Byte(b),
                message,
            }) => (b, message),
            other => panic!("expected a byte-located error, got {other:?}"),
        }
    }

    #[test]
    fn too_short() {
        let (at, msg) = err_at(&[0x65, 0x4E]);
        assert_eq!(at, 0);
        assert!(msg.contains("2 bytes"), "{msg}");
        // The magic alone: its last 4 bytes are read as an index length
        // that leaves no room after the magic.
        let (at, msg) = err_at(&MAGIC);
        assert_eq!(at, 0);
        assert!(msg.contains("index length"), "{msg}");
    }

    #[test]
    fn index_length_negative_or_too_large() {
        let mut f = magic_file();
        let n = f.len();
        f[n - 4..].copy_from_slice(&i32le(-1));
        assert_eq!(err_at(&f).0, (n - 4) as u64);
        // Larger than the space after the magic.
        f[n - 4..].copy_from_slice(&i32le((n - 8 + 1) as i32));
        let (at, msg) = err_at(&f);
        assert_eq!(at, (n - 4) as u64);
        assert!(msg.contains("index length"), "{msg}");
        // Exactly the space after the magic is a valid (empty-data) index
        // start, but then the entries' data cannot fit.
        f[n - 4..].copy_from_slice(&i32le((n - 8) as i32));
        assert!(parse(&f).is_err());
    }

    #[test]
    fn data_running_into_the_index() {
        let mut f = magic_file();
        let index_start = 16;
        f[index_start..index_start + 4].copy_from_slice(&i32le(13));
        let (at, msg) = err_at(&f);
        assert_eq!(at, index_start as u64);
        assert!(
            msg.contains("`vertices`") && msg.contains("13 bytes"),
            "{msg}"
        );
    }

    #[test]
    fn name_length_past_index() {
        let mut f = magic_file();
        let name_len_at = 16 + 4 + 16;
        f[name_len_at..name_len_at + 4].copy_from_slice(&i32le(1000));
        assert_eq!(err_at(&f).0, name_len_at as u64);
        f[name_len_at..name_len_at + 4].copy_from_slice(&i32le(-3));
        assert_eq!(err_at(&f).0, name_len_at as u64);
    }

    #[test]
    fn truncated_entries() {
        // Index holding only part of an entry: 4 bytes of data length, then
        // not the 16 reserved bytes a magic file needs.
        let mut f = MAGIC.to_vec();
        f.extend_from_slice(&i32le(0));
        f.extend_from_slice(&[0; 8]);
        f.extend_from_slice(&i32le(12));
        let (at, msg) = err_at(&f);
        assert_eq!(at, 8);
        assert!(msg.contains("reserved"), "{msg}");
        // Old layout: 2 stray bytes after a complete entry.
        let mut f = old_file();
        let n = f.len();
        let index_len = i32::from_le_bytes(f[n - 4..].try_into().unwrap());
        f.truncate(n - 4);
        f.extend_from_slice(&[0, 0]);
        f.extend_from_slice(&i32le(index_len + 2));
        let (at, msg) = err_at(&f);
        assert_eq!(at, (n - 4) as u64);
        assert!(msg.contains("data length"), "{msg}");
        // Magic layout whose last name lost its padding.
        let f = write(&[("abc", b"1234")]);
        let mut cut = f[..f.len() - 5].to_vec();
        let index_len = (cut.len() - 8) as i32;
        cut.extend_from_slice(&i32le(index_len));
        let (_, msg) = err_at(&cut);
        assert!(msg.contains("padding"), "{msg}");
    }

    #[test]
    fn write_layout_matches_hand_built_file() {
        // Same entries as `magic_file` except that one's reserved bytes.
        let mut expected = magic_file();
        expected[20..36].fill(0);
        assert_eq!(write(&[("vertices", b"hello"), ("abc", b"xyz")]), expected);
    }

    proptest! {
        #[test]
        fn write_then_parse_round_trips(
            sections in proptest::collection::vec(
                ("[a-z.]{0,12}", proptest::collection::vec(any::<u8>(), 0..40)),
                0..6,
            )
        ) {
            let refs: Vec<(&str, &[u8])> =
                sections.iter().map(|(n, d)| (n.as_str(), d.as_slice())).collect();
            let bytes = write(&refs);
            prop_assert_eq!(&bytes, &write(&refs));
            prop_assert_eq!(bytes.len() % 4, 0);
            let bin = parse(&bytes).unwrap();
            prop_assert_eq!(bin.entries.len(), sections.len());
            for (entry, (name, data)) in bin.entries.iter().zip(&sections) {
                prop_assert_eq!(&entry.name, name);
                prop_assert_eq!(&bytes[entry.data.clone()], data.as_slice());
                prop_assert_eq!(entry.data.start % 4, 0);
            }
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            let _ = parse(&bytes);
            let mut with_magic = MAGIC.to_vec();
            with_magic.extend_from_slice(&bytes);
            if let Ok(bin) = parse(&with_magic) {
                for e in &bin.entries {
                    prop_assert!(e.data.end <= with_magic.len());
                }
            }
        }
    }
}

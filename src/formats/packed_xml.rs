//! Packed binary XML (resmgr/packed_section.cpp), read into the same
//! [`Section`] tree as text XML, so every reader above works on either
//! encoding. Shipped BigWorld games run `res_packer` over their resources,
//! which turns `.model`, `.visual`, `.chunk` and settings files into this form.
//!
//! Layout (little-endian), as the engine reads it:
//! - `u32` magic `0x62a14e45`, `u8` version (the engine does not check it);
//! - a string table: NUL-terminated tag names, ended by an empty string; a
//!   child's key is an index into it;
//! - the root element, which spans the rest of the file.
//!
//! An element with children is `i16 nChildren; u32 ownEnd|type;
//! { i16 key; u32 end|type } × nChildren` followed by its data block: its own
//! value in `[0, ownEnd)`, then child `i` in `[end(i-1), end(i))` (offsets from
//! the start of the data block, low 28 bits; the top 4 bits are the type of
//! the value that *ends* there). A child of type 0 is itself such an element.
//!
//! Values become text the way the engine's `PackedSection::asString` renders
//! them, so a reader cannot tell which encoding a file used — except that a
//! 12-float value (a matrix) becomes its 12 numbers, which
//! [`Section::as_matrix`] accepts, where the engine exposes `row0..row3`
//! children instead.

use super::Section;
use crate::error::{FormatError, Location};

pub const MAGIC: [u8; 4] = [0x45, 0x4E, 0xA1, 0x62];

/// The version byte `res_packer` writes.
const VERSION: u8 = 0;

/// Low 28 bits of a data position word; the top 4 bits are the value type.
const DATA_POS_MASK: u32 = 0x0fff_ffff;

const TYPE_SECTION: u32 = 0;
const TYPE_STRING: u32 = 1;
const TYPE_INT: u32 = 2;
const TYPE_FLOAT: u32 = 3;
const TYPE_BOOL: u32 = 4;
const TYPE_BLOB: u32 = 5;
const TYPE_ENCRYPTED_BLOB: u32 = 6;

/// Key of the engine's shipped binaries (packed_section.cpp,
/// `BW_ENCRYPTION_KEY` without `HIDE_ENCRYPTION_KEY`).
const ENCRYPTION_KEY: u8 = 0xc9;

/// Name given to the root element: the file stores none (the engine names it
/// after the file), and text XML roots are arbitrary anyway.
pub const ROOT_NAME: &str = "root";

/// Deepest nesting accepted. Real resources nest a few dozen levels (bone
/// hierarchies); the bound keeps a hostile file from exhausting the stack.
pub const MAX_DEPTH: usize = 256;

/// Parses a whole packed-XML file (starting with [`MAGIC`]).
///
/// Errors name the element path and an offset relative to `bytes`.
pub fn parse(bytes: &[u8]) -> Result<Section, FormatError> {
    if !bytes.starts_with(&MAGIC) {
        return Err(FormatError::whole_file(
            "not packed binary XML: the file does not start with the magic 45 4E A1 62",
        ));
    }
    if bytes.len() < MAGIC.len() + 1 {
        return Err(FormatError::at_byte(
            MAGIC.len(),
            "packed XML truncated: the version byte after the magic is missing",
        ));
    }
    let mut strings = Vec::new();
    let mut pos = MAGIC.len() + 1;
    loop {
        let rest = bytes.get(pos..).unwrap_or(&[]);
        let Some(nul) = rest.iter().position(|&b| b == 0) else {
            return Err(FormatError::at_byte(
                pos,
                "packed XML string table is not terminated (no empty string before the end \
                 of the file); the file is truncated or not packed XML",
            ));
        };
        if nul == 0 {
            pos += 1;
            break;
        }
        strings.push(String::from_utf8_lossy(&rest[..nul]).into_owned());
        pos += nul + 1;
    }
    let reader = Reader {
        bytes,
        strings: &strings,
    };
    reader.element(
        ROOT_NAME.to_string(),
        ROOT_NAME.to_string(),
        pos,
        bytes.len(),
        0,
    )
}

struct Reader<'a> {
    bytes: &'a [u8],
    strings: &'a [String],
}

/// An element's child table, read and checked.
struct ChildTable {
    /// Where the element (its child count) starts.
    start: usize,
    count: usize,
    /// Where its data block starts, and its length.
    data_start: usize,
    data_len: usize,
    /// Where its own value ends in the data block, and the value's type.
    own_end: usize,
    own_type: u32,
}

impl Reader<'_> {
    fn error(&self, path: &str, offset: usize, message: impl Into<String>) -> FormatError {
        FormatError::new(
            Location::Element {
                path: path.to_string(),
                offset: offset as u64,
            },
            message,
        )
    }

    fn i16_at(&self, offset: usize) -> Option<i16> {
        let b = self.bytes.get(offset..offset.checked_add(2)?)?;
        Some(i16::from_le_bytes([b[0], b[1]]))
    }

    fn u32_at(&self, offset: usize) -> Option<u32> {
        let b = self.bytes.get(offset..offset.checked_add(4)?)?;
        Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// Reads an element with a child table occupying `bytes[start..end]`.
    fn element(
        &self,
        name: String,
        path: String,
        start: usize,
        end: usize,
        depth: usize,
    ) -> Result<Section, FormatError> {
        if depth > MAX_DEPTH {
            return Err(self.error(
                &path,
                start,
                format!("packed XML nests deeper than {MAX_DEPTH} levels; the file is corrupt"),
            ));
        }
        let table = self.child_table(&path, start, end)?;
        let value = self.value(
            table.own_type,
            table.data_start,
            table.data_start + table.own_end,
            &path,
        )?;
        let mut children = Vec::new();
        let mut previous = table.own_end;
        for i in 0..table.count {
            let (child, child_end) = self.child(&path, &table, i, previous, depth)?;
            children.push(child);
            previous = child_end;
        }
        Ok(Section {
            name,
            value,
            children,
            path,
            span: start..end,
        })
    }

    /// The child count and table of the element at `bytes[start..end]`,
    /// checked against its length, and where its own value ends.
    fn child_table(&self, path: &str, start: usize, end: usize) -> Result<ChildTable, FormatError> {
        let count = self
            .i16_at(start)
            .filter(|_| start + 2 <= end)
            .ok_or_else(|| {
                self.error(
                    path,
                    start,
                    format!(
                        "element data is {} bytes, too short for its child count (2 bytes)",
                        end.saturating_sub(start)
                    ),
                )
            })?;
        if count < 0 {
            return Err(self.error(
                path,
                start,
                format!("negative child count {count}; the file is corrupt"),
            ));
        }
        let count = count as usize;
        // count ≤ 32767, so this cannot overflow.
        let header_len = 2 + 4 + 6 * count;
        let data_start = start + header_len;
        if data_start > end {
            return Err(self.error(
                path,
                start,
                format!(
                    "{count} children need a {header_len}-byte table but the element has only {} bytes",
                    end - start
                ),
            ));
        }
        let data_len = end - data_start;
        let own_word = self.u32_at(start + 2).unwrap_or(0);
        let own_end = (own_word & DATA_POS_MASK) as usize;
        if own_end > data_len {
            return Err(self.error(
                path,
                start + 2,
                format!(
                    "own value ends at {own_end} but the element's data block has only {data_len} bytes"
                ),
            ));
        }
        Ok(ChildTable {
            start,
            count,
            data_start,
            data_len,
            own_end,
            own_type: own_word >> 28,
        })
    }

    /// Child `i` of an element, whose data begins where the previous one's
    /// ended (`previous`, in the data block), and where its data ends.
    fn child(
        &self,
        path: &str,
        table: &ChildTable,
        i: usize,
        previous: usize,
        depth: usize,
    ) -> Result<(Section, usize), FormatError> {
        let record = table.start + 6 + 6 * i;
        let key = self.i16_at(record).unwrap_or(-1);
        let word = self.u32_at(record + 2).unwrap_or(0);
        let child_end = (word & DATA_POS_MASK) as usize;
        let child_name = usize::try_from(key)
            .ok()
            .and_then(|k| self.strings.get(k))
            .ok_or_else(|| {
                self.error(
                    path,
                    record,
                    format!(
                        "child {i} names string {key} but the string table holds {} strings",
                        self.strings.len()
                    ),
                )
            })?;
        let child_path = format!("{path}/{child_name}");
        let data_len = table.data_len;
        if child_end < previous || child_end > data_len {
            return Err(self.error(
                &child_path,
                record + 2,
                format!(
                    "child {i} data ends at {child_end}, outside {previous}..={data_len} \
                     (the previous end and the data block length)"
                ),
            ));
        }
        let (child_start, child_stop) = (table.data_start + previous, table.data_start + child_end);
        let child = if word >> 28 == TYPE_SECTION {
            self.element(
                child_name.clone(),
                child_path,
                child_start,
                child_stop,
                depth + 1,
            )?
        } else {
            Section {
                name: child_name.clone(),
                value: self.value(word >> 28, child_start, child_stop, &child_path)?,
                children: Vec::new(),
                path: child_path,
                span: child_start..child_stop,
            }
        };
        Ok((child, child_end))
    }

    /// Renders a typed value as the engine's `asString` would.
    fn value(
        &self,
        kind: u32,
        start: usize,
        end: usize,
        path: &str,
    ) -> Result<String, FormatError> {
        let data = self.bytes.get(start..end).unwrap_or(&[]);
        match kind {
            TYPE_SECTION if data.is_empty() => Ok(String::new()),
            TYPE_SECTION => Err(self.error(
                path,
                start,
                "an element's own value is marked as a section; the file is corrupt",
            )),
            TYPE_STRING => Ok(String::from_utf8_lossy(data).trim().to_string()),
            TYPE_INT => {
                let v = match *data {
                    [] => 0,
                    [a] => i64::from(a as i8),
                    [a, b] => i64::from(i16::from_le_bytes([a, b])),
                    [a, b, c, d] => i64::from(i32::from_le_bytes([a, b, c, d])),
                    [a, b, c, d, e, f, g, h] => i64::from_le_bytes([a, b, c, d, e, f, g, h]),
                    _ => {
                        return Err(self.error(
                            path,
                            start,
                            format!(
                                "integer value of {} bytes; only 0, 1, 2, 4 or 8 are valid",
                                data.len()
                            ),
                        ))
                    }
                };
                Ok(v.to_string())
            }
            TYPE_FLOAT => {
                if !data.len().is_multiple_of(4) {
                    return Err(self.error(
                        path,
                        start,
                        format!(
                            "float value of {} bytes is not a whole number of 4-byte floats",
                            data.len()
                        ),
                    ));
                }
                let words: Vec<String> = data
                    .chunks_exact(4)
                    .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]).to_string())
                    .collect();
                Ok(words.join(" "))
            }
            TYPE_BOOL => Ok(if data.is_empty() { "false" } else { "true" }.to_string()),
            TYPE_BLOB => Ok(base64_encode(data)),
            TYPE_ENCRYPTED_BLOB => match data.split_first() {
                Some((0, rest)) => Ok(base64_encode(rest)),
                Some((1, rest)) => {
                    let plain: Vec<u8> = rest.iter().map(|b| b ^ ENCRYPTION_KEY).collect();
                    Ok(base64_encode(&plain))
                }
                Some((flag, _)) => Err(self.error(
                    path,
                    start,
                    format!("encrypted blob starts with {flag:#04x}; expected 0 or 1"),
                )),
                None => Err(self.error(path, start, "encrypted blob is empty (no flag byte)")),
            },
            other => Err(self.error(
                path,
                start,
                format!("unknown value type {other} (valid: 0 to 6)"),
            )),
        }
    }
}

const BASE64: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

/// Standard base64 with `=` padding (the engine's `Base64::encode`).
pub fn base64_encode(data: &[u8]) -> String {
    let mut out = String::with_capacity(data.len().div_ceil(3) * 4);
    for chunk in data.chunks(3) {
        let b = [
            chunk[0],
            chunk.get(1).copied().unwrap_or(0),
            chunk.get(2).copied().unwrap_or(0),
        ];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for (i, shift) in [18u32, 12, 6, 0].into_iter().enumerate() {
            if i <= chunk.len() {
                out.push(char::from(BASE64[((n >> shift) & 63) as usize]));
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// Strict decoding of [`base64_encode`]'s output; `None` for anything else.
pub fn base64_decode(text: &str) -> Option<Vec<u8>> {
    let bytes = text.as_bytes();
    if !bytes.len().is_multiple_of(4) {
        return None;
    }
    let mut out = Vec::with_capacity(bytes.len() / 4 * 3);
    let quads = bytes.len() / 4;
    for (q, quad) in bytes.chunks_exact(4).enumerate() {
        let mut n = 0u32;
        let mut pad = 0;
        for (i, &c) in quad.iter().enumerate() {
            let v = if c == b'=' {
                // Padding only in the last two places of the last quad.
                if q + 1 != quads || i < 2 {
                    return None;
                }
                pad += 1;
                0
            } else {
                if pad > 0 {
                    return None;
                }
                BASE64.iter().position(|&a| a == c)? as u32
            };
            n = (n << 6) | v;
        }
        let decoded = [(n >> 16) as u8, (n >> 8) as u8, n as u8];
        out.extend_from_slice(&decoded[..3 - pad]);
    }
    Some(out)
}

/// Encodes a tree as packed binary XML, choosing each value's type the way
/// `res_packer` does (`addBestGuess`): empty → string, `true`/`false` → bool,
/// an integer that prints back identically → the smallest int, 1–4 or 12
/// numbers that print back identically as `f32` → floats, canonical base64 →
/// blob, anything else → string. So `parse(write(s))` gives back `s`'s names,
/// trimmed values and children. Tag names are stored sorted (as the engine's
/// `std::map` does), so the output is deterministic.
///
/// Errors if the tree cannot be represented: an empty tag or one containing
/// NUL, more than 32767 distinct tags or children of one element, or more
/// than 2^28 bytes of data in one element.
pub fn write(root: &Section) -> Result<Vec<u8>, FormatError> {
    let mut names = std::collections::BTreeSet::new();
    collect_names(root, &mut names)?;
    if names.len() > i16::MAX as usize {
        return Err(root.error(format!(
            "{} distinct tag names; packed XML holds at most {}",
            names.len(),
            i16::MAX
        )));
    }
    let index: std::collections::BTreeMap<&str, i16> = names
        .iter()
        .enumerate()
        .map(|(i, n)| (n.as_str(), i as i16))
        .collect();
    let mut out = Vec::new();
    out.extend_from_slice(&MAGIC);
    out.push(VERSION);
    for name in &names {
        out.extend_from_slice(name.as_bytes());
        out.push(0);
    }
    out.push(0);
    write_element(root, &index, &mut out)?;
    Ok(out)
}

fn collect_names(
    section: &Section,
    names: &mut std::collections::BTreeSet<String>,
) -> Result<(), FormatError> {
    for child in &section.children {
        if child.name.is_empty() || child.name.contains('\0') {
            return Err(child.error(format!(
                "tag `{}` cannot be stored in packed XML (empty or containing NUL)",
                child.name.escape_debug()
            )));
        }
        names.insert(child.name.clone());
        collect_names(child, names)?;
    }
    Ok(())
}

fn data_pos(section: &Section, offset: usize, kind: u32) -> Result<u32, FormatError> {
    u32::try_from(offset)
        .ok()
        .filter(|&o| o <= DATA_POS_MASK)
        .map(|o| o | (kind << 28))
        .ok_or_else(|| section.error("element data exceeds 2^28 bytes, the packed XML limit"))
}

/// Appends an element with a child table; its type is always 0 (section).
fn write_element(
    section: &Section,
    index: &std::collections::BTreeMap<&str, i16>,
    out: &mut Vec<u8>,
) -> Result<(), FormatError> {
    let count = i16::try_from(section.children.len()).map_err(|_| {
        section.error(format!(
            "{} children; packed XML holds at most {} per element",
            section.children.len(),
            i16::MAX
        ))
    })?;
    let mut header = Vec::with_capacity(6 + 6 * section.children.len());
    header.extend_from_slice(&count.to_le_bytes());
    let (own_kind, own) = encode_value(&section.value);
    let mut data = own;
    header.extend_from_slice(&data_pos(section, data.len(), own_kind)?.to_le_bytes());
    for child in &section.children {
        let kind = if child.children.is_empty() {
            let (kind, bytes) = encode_value(&child.value);
            data.extend_from_slice(&bytes);
            kind
        } else {
            write_element(child, index, &mut data)?;
            TYPE_SECTION
        };
        let key = index.get(child.name.as_str()).copied().unwrap_or(0);
        header.extend_from_slice(&key.to_le_bytes());
        header.extend_from_slice(&data_pos(child, data.len(), kind)?.to_le_bytes());
    }
    out.extend_from_slice(&header);
    out.extend_from_slice(&data);
    Ok(())
}

/// `res_packer`'s type guess for a value, restricted to encodings that read
/// back as the same text.
fn encode_value(value: &str) -> (u32, Vec<u8>) {
    let text = value.trim();
    if text.is_empty() {
        return (TYPE_STRING, Vec::new());
    }
    if text == "true" {
        return (TYPE_BOOL, vec![1]);
    }
    if text == "false" {
        return (TYPE_BOOL, Vec::new());
    }
    if let Ok(v) = text.parse::<i64>() {
        if v.to_string() == text {
            let bytes = if v == 0 {
                Vec::new()
            } else if let Ok(v) = i8::try_from(v) {
                v.to_le_bytes().to_vec()
            } else if let Ok(v) = i16::try_from(v) {
                v.to_le_bytes().to_vec()
            } else if let Ok(v) = i32::try_from(v) {
                v.to_le_bytes().to_vec()
            } else {
                v.to_le_bytes().to_vec()
            };
            return (TYPE_INT, bytes);
        }
    }
    let words: Vec<&str> = text.split(' ').collect();
    if matches!(words.len(), 1..=4 | 12) {
        let floats: Option<Vec<f32>> = words
            .iter()
            .map(|w| w.parse::<f32>().ok().filter(|f| f.to_string() == *w))
            .collect();
        if let Some(floats) = floats {
            return (
                TYPE_FLOAT,
                floats.iter().flat_map(|f| f.to_le_bytes()).collect(),
            );
        }
    }
    if let Some(decoded) = base64_decode(text) {
        if base64_encode(&decoded) == text {
            return (TYPE_BLOB, decoded);
        }
    }
    (TYPE_STRING, text.as_bytes().to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn node(name: &str, value: &str, children: Vec<Section>) -> Section {
        Section {
            name: name.into(),
            value: value.into(),
            children,
            ..Default::default()
        }
    }

    /// Names, values and children: what a round trip must preserve.
    fn same_tree(a: &Section, b: &Section) -> bool {
        a.name == b.name
            && a.value == b.value
            && a.children.len() == b.children.len()
            && a.children
                .iter()
                .zip(&b.children)
                .all(|(x, y)| same_tree(x, y))
    }

    /// Hand-assembled file: header, strings, then the root element bytes.
    fn file(strings: &[&str], root: &[u8]) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.push(0);
        for s in strings {
            out.extend_from_slice(s.as_bytes());
            out.push(0);
        }
        out.push(0);
        out.extend_from_slice(root);
        out
    }

    /// Root element bytes with an empty own value and the given leaf children
    /// `(key, type, data)`.
    fn root_with(children: &[(i16, u32, &[u8])]) -> Vec<u8> {
        let mut header = (children.len() as i16).to_le_bytes().to_vec();
        header.extend_from_slice(&(TYPE_STRING << 28).to_le_bytes());
        let mut data = Vec::new();
        for (key, kind, bytes) in children {
            data.extend_from_slice(bytes);
            header.extend_from_slice(&key.to_le_bytes());
            header.extend_from_slice(&((data.len() as u32) | (kind << 28)).to_le_bytes());
        }
        header.extend_from_slice(&data);
        header
    }

    #[test]
    fn hand_built_file_decodes_every_type() {
        let strings = [
            "s", "i0", "i1", "i2", "i4", "i8", "f1", "m", "bt", "bf", "blob", "enc",
        ];
        let matrix: Vec<u8> = (1..=12).flat_map(|i| (i as f32).to_le_bytes()).collect();
        let mut enc = vec![1u8];
        enc.extend(b"hi!".iter().map(|b| b ^ ENCRYPTION_KEY));
        let bytes = file(
            &strings,
            &root_with(&[
                (0, TYPE_STRING, b"  hello  "),
                (1, TYPE_INT, &[]),
                (2, TYPE_INT, &[0xfe]),
                (3, TYPE_INT, &(-300i16).to_le_bytes()),
                (4, TYPE_INT, &70000i32.to_le_bytes()),
                (5, TYPE_INT, &(-5_000_000_000i64).to_le_bytes()),
                (6, TYPE_FLOAT, &0.5f32.to_le_bytes()),
                (7, TYPE_FLOAT, &matrix),
                (8, TYPE_BOOL, &[1]),
                (9, TYPE_BOOL, &[]),
                (10, TYPE_BLOB, b"hi!"),
                (11, TYPE_ENCRYPTED_BLOB, &enc),
            ]),
        );
        let root = parse(&bytes).unwrap();
        let values: Vec<(&str, &str)> = root
            .children
            .iter()
            .map(|c| (c.name.as_str(), c.value.as_str()))
            .collect();
        assert_eq!(
            values,
            [
                ("s", "hello"),
                ("i0", "0"),
                ("i1", "-2"),
                ("i2", "-300"),
                ("i4", "70000"),
                ("i8", "-5000000000"),
                ("f1", "0.5"),
                ("m", "1 2 3 4 5 6 7 8 9 10 11 12"),
                ("bt", "true"),
                ("bf", "false"),
                // "hi!" is 0x68 0x69 0x21 → 011010 000110 100100 100001.
                ("blob", "aGkh"),
                ("enc", "aGkh"),
            ]
        );
        assert_eq!(root.children[1].path, "root/i0");
        // The matrix is the 8th value: it follows 9+0+1+2+4+8+4 = 28 bytes.
        let data_start = bytes.len() - 9 - 1 - 2 - 4 - 8 - 4 - 48 - 1 - 3 - 4;
        assert_eq!(root.children[7].span, data_start + 28..data_start + 76);
        let m = root.children[7].as_matrix().unwrap();
        assert_eq!(m.w_axis.x, 10.0);
    }

    #[test]
    fn round_trip_of_varied_trees() {
        let tree = node(
            "root",
            "",
            vec![
                node("name", "Scene Root", vec![]),
                node(
                    "node",
                    "",
                    vec![
                        node("identifier", "Bone01", vec![]),
                        node("transform", "1 0 0 0 1 0 0 0 1 10.5 -2 3", vec![]),
                        node("node", "", vec![node("identifier", "leaf", vec![])]),
                    ],
                ),
                node(
                    "primitiveGroup",
                    "3",
                    vec![node(
                        "material",
                        "",
                        vec![
                            node(
                                "property",
                                "alphaTestEnable",
                                vec![node("Bool", "true", vec![])],
                            ),
                            node(
                                "property",
                                "doubleSided",
                                vec![node("Bool", "false", vec![])],
                            ),
                            node(
                                "property",
                                "x",
                                vec![node("Vector4", "0.1 0.2 0.3 1", vec![])],
                            ),
                        ],
                    )],
                ),
                node("ints", "127", vec![]),
                node("ints", "128", vec![]),
                node("ints", "-32769", vec![]),
                node("ints", "9223372036854775807", vec![]),
                node("notint", "007", vec![]),
                node("big", "18446744073709551615", vec![]),
                node("floats", "0.1 -0 1.5", vec![]),
                node("blob", "aGkh", vec![]),
                node("empty", "", vec![]),
                node("text", "sets/town/props/axe.tga", vec![]),
                node("five", "1 2 3 4 5", vec![]),
            ],
        );
        let bytes = write(&tree).unwrap();
        let back = parse(&bytes).unwrap();
        assert!(same_tree(&tree, &back), "{tree:#?}\n{back:#?}");
        // Deterministic, and a second round trip is byte-identical.
        assert_eq!(write(&tree).unwrap(), bytes);
        assert_eq!(write(&back).unwrap(), bytes);
    }

    #[test]
    fn writer_picks_the_engine_types() {
        assert_eq!(encode_value("true"), (TYPE_BOOL, vec![1]));
        assert_eq!(encode_value("0"), (TYPE_INT, vec![]));
        assert_eq!(encode_value("-128"), (TYPE_INT, vec![0x80]));
        assert_eq!(encode_value("128").1.len(), 2);
        assert_eq!(encode_value("0.5").0, TYPE_FLOAT);
        assert_eq!(encode_value("1 2 3 4 5").0, TYPE_STRING);
        assert_eq!(encode_value("01").0, TYPE_STRING);
        assert_eq!(encode_value("aGkh"), (TYPE_BLOB, b"hi!".to_vec()));
    }

    #[test]
    fn base64_round_trips_and_rejects() {
        for data in [&b""[..], b"a", b"ab", b"abc", b"abcd", &[0, 255, 128, 7, 9]] {
            assert_eq!(base64_decode(&base64_encode(data)).unwrap(), data);
        }
        assert_eq!(base64_encode(b"a"), "YQ==");
        for bad in ["YQ=", "Y===", "YQ==YQ==", "Y=Q=", "a*cd"] {
            assert!(base64_decode(bad).is_none(), "{bad}");
        }
    }

    fn err(bytes: &[u8]) -> String {
        parse(bytes).unwrap_err().to_string()
    }

    #[test]
    fn header_errors() {
        assert!(err(b"<root/>").contains("magic"));
        assert!(err(&MAGIC).contains("version"));
        let mut unterminated = MAGIC.to_vec();
        unterminated.extend_from_slice(b"\0abc");
        assert!(err(&unterminated).contains("not terminated"));
        // Table ends, but no root element follows.
        assert!(err(&file(&[], &[])).contains("too short"));
    }

    #[test]
    fn element_errors() {
        // Negative child count.
        assert!(err(&file(&[], &[0xff, 0xff, 0, 0, 0, 0])).contains("negative"));
        // Two children announced, no table.
        assert!(err(&file(&["a"], &[2, 0, 0, 0, 0, 0])).contains("table"));
        // Own value longer than the data block.
        assert!(err(&file(&[], &[0, 0, 5, 0, 0, 0x10, b'x'])).contains("own value ends"));
        // Child key outside the string table.
        let bad_key = root_with(&[(3, TYPE_STRING, b"x")]);
        assert!(err(&file(&["a"], &bad_key)).contains("string 3"));
        // Child ending past the data block.
        let mut past = root_with(&[(0, TYPE_STRING, b"x")]);
        past[8] = 9;
        let e = err(&file(&["a"], &past));
        assert!(
            e.contains("child 0 data ends at 9") && e.contains("<root/a>"),
            "{e}"
        );
        // Child ending before the previous one ends.
        let mut back = root_with(&[(0, TYPE_STRING, b"xy"), (0, TYPE_STRING, b"z")]);
        back[14] = 1;
        assert!(err(&file(&["a"], &back)).contains("child 1 data ends at 1"));
    }

    #[test]
    fn value_errors() {
        let cases: [(u32, &[u8], &str); 6] = [
            (TYPE_INT, &[1, 2, 3], "integer value of 3 bytes"),
            (TYPE_FLOAT, &[1, 2, 3], "whole number"),
            (TYPE_ENCRYPTED_BLOB, &[], "empty"),
            (TYPE_ENCRYPTED_BLOB, &[7, 1], "0x07"),
            (7, &[], "unknown value type 7"),
            (15, &[], "unknown value type 15"),
        ];
        for (kind, data, expected) in cases {
            let e = err(&file(&["a"], &root_with(&[(0, kind, data)])));
            assert!(e.contains(expected), "{e}");
            assert!(e.contains("<root/a>"), "{e}");
        }
        // An own value marked as a section.
        let e = err(&file(&[], &[0, 0, 1, 0, 0, 0, b'x']));
        assert!(e.contains("marked as a section"), "{e}");
    }

    #[test]
    fn deep_nesting_is_refused_not_overflowed() {
        // Each level: 1 child (key 0, type section) ending at the end of the
        // data block; innermost: no children.
        let levels = MAX_DEPTH + 10;
        let mut inner = vec![0u8, 0, 0, 0, 0, 0x10];
        for _ in 0..levels {
            let mut outer = vec![1u8, 0, 0, 0, 0, 0x10, 0, 0];
            outer.extend_from_slice(&(inner.len() as u32).to_le_bytes());
            outer.extend_from_slice(&inner);
            inner = outer;
        }
        let e = err(&file(&["n"], &inner));
        assert!(e.contains("deeper than"), "{e}");
    }

    #[test]
    fn writer_rejects_unrepresentable_trees() {
        let bad = node("root", "", vec![node("", "x", vec![])]);
        assert!(write(&bad).is_err());
        let nul = node("root", "", vec![node("a\0b", "x", vec![])]);
        assert!(write(&nul).is_err());
        let wide = node("root", "", vec![node("a", "", vec![]); 40000]);
        assert!(write(&wide).unwrap_err().to_string().contains("children"));
    }

    #[test]
    fn truncation_and_bit_flips_never_panic() {
        let tree = node(
            "root",
            "top",
            vec![
                node(
                    "a",
                    "1 2 3",
                    vec![node("b", "true", vec![]), node("c", "x y", vec![])],
                ),
                node("d", "-70000", vec![]),
                node("e", "aGkh", vec![node("f", "0.25", vec![])]),
            ],
        );
        let bytes = write(&tree).unwrap();
        assert!(same_tree(&tree, &parse(&bytes).unwrap()));
        for len in 0..bytes.len() {
            let _ = parse(&bytes[..len]);
        }
        for i in 0..bytes.len() {
            for bit in 0..8 {
                let mut flipped = bytes.clone();
                flipped[i] ^= 1 << bit;
                let _ = parse(&flipped);
            }
        }
    }

    mod properties {
        use super::*;
        use proptest::prelude::*;

        fn value() -> impl Strategy<Value = String> {
            prop_oneof![
                any::<i64>().prop_map(|v| v.to_string()),
                any::<f32>().prop_map(|v| v.to_string()),
                proptest::collection::vec(any::<f32>(), 1..13).prop_map(|v| v
                    .iter()
                    .map(|f| f.to_string())
                    .collect::<Vec<_>>()
                    .join(" ")),
                Just("true".to_string()),
                Just("false".to_string()),
                "[ -~é]{0,16}".prop_map(|s| s.trim().to_string()),
            ]
        }

        fn tree() -> impl Strategy<Value = Section> {
            let name = "[a-zA-Z_][a-zA-Z0-9_.]{0,8}";
            let leaf = (name, value()).prop_map(|(n, v)| node(&n, &v, vec![]));
            leaf.prop_recursive(5, 64, 6, move |inner| {
                (name, value(), proptest::collection::vec(inner, 0..6))
                    .prop_map(|(n, v, c)| node(&n, &v, c))
            })
        }

        proptest! {
            #[test]
            fn random_trees_round_trip(children in proptest::collection::vec(tree(), 0..5)) {
                let root = node("root", "", children);
                let bytes = write(&root).unwrap();
                let back = parse(&bytes).unwrap();
                prop_assert!(same_tree(&root, &back));
                prop_assert_eq!(write(&back).unwrap(), bytes);
            }

            #[test]
            fn random_bytes_never_panic(tail in proptest::collection::vec(any::<u8>(), 0..200)) {
                let mut bytes = MAGIC.to_vec();
                bytes.extend(tail);
                let _ = parse(&bytes);
            }
        }
    }
}

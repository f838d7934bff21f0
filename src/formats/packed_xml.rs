//! Packed binary XML (resmgr/packed_section.cpp), read into the same
//! [`Section`] tree as text XML, so every reader above works on either
//! encoding, and kept as a [`Document`] that writes back the bytes it was
//! read from. Shipped BigWorld games run `res_packer` over their resources,
//! which turns `.model`, `.visual`, `.chunk` and settings files into this
//! form; the bake rewrites such chunks, and a value nobody edited must keep
//! its bytes and its binary type (docs/contract.md §5).
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
//! A [`Document`] holds each value's type code and bytes as stored (an int
//! keeps its width, a float holding 250.0 stays a float, an encrypted blob
//! stays encrypted), the string table in file order and any bytes after an
//! element's last child, so `Document::parse(b)?.to_bytes()` is `b` for every
//! file it accepts. Edits ([`Document::set_child`]) encode only the new
//! element and leave every other value's bytes alone.
//!
//! Values become text the way the engine's `PackedSection::asString` renders
//! them, so a reader cannot tell which encoding a file used — except that a
//! float prints in its shortest exact form (`250`, `0.1`) where the engine
//! prints six decimals, and a 12-float value (a matrix) becomes its 12
//! numbers, which [`Section::as_matrix`] accepts, where the engine exposes
//! `row0..row3` children instead.

use super::Section;
use crate::error::{FormatError, Location};

pub const MAGIC: [u8; 4] = [0x45, 0x4E, 0xA1, 0x62];

/// The version byte `res_packer` writes.
const VERSION: u8 = 0;

/// Low 28 bits of a data position word; the top 4 bits are the value type.
const DATA_POS_MASK: u32 = 0x0fff_ffff;

/// Key of the engine's shipped binaries (packed_section.cpp,
/// `BW_ENCRYPTION_KEY` without `HIDE_ENCRYPTION_KEY`).
const ENCRYPTION_KEY: u8 = 0xc9;

/// Name given to the root element: the file stores none (the engine names it
/// after the file), and text XML roots are arbitrary anyway.
pub const ROOT_NAME: &str = "root";

/// Deepest nesting accepted. Real resources nest a few dozen levels (bone
/// hierarchies); the bound keeps a hostile file from exhausting the stack.
pub const MAX_DEPTH: usize = 256;

/// Bytes of an element's header before its child records: the child count
/// and its own value's end word.
const HEADER_LEN: usize = 2 + 4;
/// Bytes of one child record: key and end word.
const RECORD_LEN: usize = 2 + 4;

/// The type of a stored value: the top 4 bits of the word where it ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ValueType {
    /// An element with a child table (never a value of its own).
    Section,
    String,
    /// 0, 1, 2, 4 or 8 bytes, little-endian, signed.
    Int,
    /// Any number of `f32`s: 1 to 4 a vector, 12 a matrix.
    Float,
    /// No bytes is false, any bytes true.
    Bool,
    Blob,
    /// A flag byte (0 plain, 1 XOR-ed with the engine's key), then the blob.
    EncryptedBlob,
}

impl ValueType {
    const ALL: [ValueType; 7] = [
        ValueType::Section,
        ValueType::String,
        ValueType::Int,
        ValueType::Float,
        ValueType::Bool,
        ValueType::Blob,
        ValueType::EncryptedBlob,
    ];

    fn code(self) -> u32 {
        self as u32
    }

    fn from_code(code: u32) -> Option<ValueType> {
        ValueType::ALL.get(code as usize).copied()
    }
}

/// A value as stored: its type and its bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Value {
    pub kind: ValueType,
    pub data: Vec<u8>,
}

/// An element with a child table, as stored.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Element {
    /// The element's own value (first in its data block).
    pub own: Value,
    pub children: Vec<Child>,
    /// Bytes of the data block after the last child: none in files the
    /// engine writes, kept so any accepted file writes back unchanged.
    pub trailing: Vec<u8>,
}

/// One child record: the key (an index into the string table) and what it
/// holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Child {
    pub key: i16,
    pub node: Node,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Node {
    Element(Element),
    Value(Value),
}

/// A whole packed file as stored: version byte, string table in file order,
/// root element. [`Document::to_bytes`] gives back the file it was parsed
/// from, byte for byte.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Document {
    version: u8,
    /// The string table's entries as stored (names need not be UTF-8).
    strings: Vec<Vec<u8>>,
    root: Element,
}

/// Parses a whole packed-XML file (starting with [`MAGIC`]) into a tree.
///
/// Errors name the element path and an offset relative to `bytes`.
pub fn parse(bytes: &[u8]) -> Result<Section, FormatError> {
    Document::parse(bytes)?.to_section()
}

/// Encodes a tree as packed binary XML exactly as the engine's `res_packer`
/// does (see [`Document::from_section`]).
///
/// Errors if the tree cannot be represented: an empty tag or one containing
/// NUL, more than 32767 distinct tags or children of one element, or more
/// than 2^28 bytes of data in one element.
pub fn write(root: &Section) -> Result<Vec<u8>, FormatError> {
    Document::from_section(root)?.to_bytes()
}

impl Document {
    /// Reads the structure of a packed file: string table, child tables,
    /// every value's type and bytes. Values are checked when rendered
    /// ([`Document::to_section`]).
    pub fn parse(bytes: &[u8]) -> Result<Document, FormatError> {
        if !bytes.starts_with(&MAGIC) {
            return Err(FormatError::whole_file(
                "not packed binary XML: the file does not start with the magic 45 4E A1 62",
            ));
        }
        let Some(&version) = bytes.get(MAGIC.len()) else {
            return Err(FormatError::at_byte(
                MAGIC.len(),
                "packed XML truncated: the version byte after the magic is missing",
            ));
        };
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
            strings.push(rest[..nul].to_vec());
            pos += nul + 1;
        }
        let names: Vec<String> = strings
            .iter()
            .map(|s| String::from_utf8_lossy(s).into_owned())
            .collect();
        let reader = Reader {
            bytes,
            names: &names,
        };
        let root = reader.element(ROOT_NAME, pos, bytes.len(), 0)?;
        Ok(Document {
            version,
            strings,
            root,
        })
    }

    /// Packs a tree as the engine's `res_packer` does (`convertToPackedFile`):
    /// the tags sorted bytewise into the string table (a matrix's row tags
    /// left out), the root always an element, every other element without
    /// children a value, an element whose four children are `row0`..`row3`
    /// of three numbers each a 12-float value (in child order), and every
    /// value's type guessed from its text as `addBestGuess` does (see
    /// [`guess_value`]).
    pub fn from_section(root: &Section) -> Result<Document, FormatError> {
        let mut names = std::collections::BTreeSet::new();
        collect_names(root, &mut names)?;
        let mut document = Document {
            version: VERSION,
            strings: Vec::new(),
            root: Element::empty(),
        };
        for name in names {
            document.key_of(root, &name)?;
        }
        document.root = document.encode_element(root)?;
        Ok(document)
    }

    /// The file's bytes: those it was parsed from, with any edits.
    pub fn to_bytes(&self) -> Result<Vec<u8>, FormatError> {
        let mut out = MAGIC.to_vec();
        out.push(self.version);
        for name in &self.strings {
            out.extend_from_slice(name);
            out.push(0);
        }
        out.push(0);
        let mut keys = Vec::new();
        self.emit(&self.root, &mut keys, &mut out)?;
        Ok(out)
    }

    /// The tree every reader uses, with each value rendered as text; element
    /// spans are where the element's bytes are in [`Document::to_bytes`].
    ///
    /// Errors for a value its type cannot hold (an int of 3 bytes, a float
    /// of 5, an encrypted blob with a bad flag), naming element and offset.
    pub fn to_section(&self) -> Result<Section, FormatError> {
        let start = MAGIC.len() + 1 + self.strings.iter().map(|s| s.len() + 1).sum::<usize>() + 1;
        let names: Vec<String> = self
            .strings
            .iter()
            .map(|s| String::from_utf8_lossy(s).into_owned())
            .collect();
        let (section, _) = section_of(&names, &self.root, ROOT_NAME, ROOT_NAME.into(), start)?;
        Ok(section)
    }

    pub fn root(&self) -> &Element {
        &self.root
    }

    /// The string table in file order (not-UTF-8 bytes replaced).
    pub fn names(&self) -> Vec<String> {
        self.strings
            .iter()
            .map(|s| String::from_utf8_lossy(s).into_owned())
            .collect()
    }

    /// The tag a child's key names, if the table holds it.
    pub fn name_of(&self, key: i16) -> Option<&[u8]> {
        usize::try_from(key)
            .ok()
            .and_then(|k| self.strings.get(k))
            .map(Vec::as_slice)
    }

    /// The stored value at `path` (tags below the root, `/`-separated, the
    /// first child of each tag), if it is a value.
    pub fn value_at(&self, path: &str) -> Option<&Value> {
        let mut element = &self.root;
        let mut tags = path.split('/').peekable();
        while let Some(tag) = tags.next() {
            let child = element
                .children
                .iter()
                .find(|c| self.name_of(c.key) == Some(tag.as_bytes()))?;
            match (&child.node, tags.peek()) {
                (Node::Value(value), None) => return Some(value),
                (Node::Element(inner), Some(_)) => element = inner,
                _ => return None,
            }
        }
        None
    }

    /// Puts `section` into the element at `path` (child indices from the
    /// root) as its direct child, encoded as [`Document::from_section`]
    /// encodes it: in place of the first direct child of the same tag, the
    /// others of that tag removed, else appended after the last child. Tags
    /// the string table lacks are appended to it. An element stored as a
    /// value (no children) becomes an element keeping that value as its own.
    /// Nothing else changes: every other value keeps its bytes.
    ///
    /// `context` names the element in errors (the file cannot hold more
    /// tags or children).
    pub fn set_child(
        &mut self,
        path: &[usize],
        section: &Section,
        context: &Section,
    ) -> Result<(), FormatError> {
        let key = self.key_of(context, &section.name)?;
        let node = self.encode_child(section)?;
        self.put_child(path, key, node, context)
    }

    /// Appends a value, stored as given, as the last child of the element at
    /// `path`: for values no text spelling produces (an encrypted blob).
    pub fn push_value(
        &mut self,
        path: &[usize],
        name: &str,
        value: Value,
        context: &Section,
    ) -> Result<(), FormatError> {
        let key = self.key_of(context, name)?;
        let element = element_at_mut(&mut self.root, path)
            .ok_or_else(|| context.error("internal error: no element at that child path"))?;
        element.children.push(Child {
            key,
            node: Node::Value(value),
        });
        Ok(())
    }

    fn put_child(
        &mut self,
        path: &[usize],
        key: i16,
        node: Node,
        context: &Section,
    ) -> Result<(), FormatError> {
        let strings = &self.strings;
        let name = strings.get(key as usize).cloned().unwrap_or_default();
        let element = element_at_mut(&mut self.root, path)
            .ok_or_else(|| context.error("internal error: no element at that child path"))?;
        let same_tag =
            |c: &Child| usize::try_from(c.key).ok().and_then(|k| strings.get(k)) == Some(&name);
        let at = element.children.iter().position(same_tag);
        element.children.retain(|c| !same_tag(c));
        let at = at.unwrap_or(element.children.len());
        element.children.insert(at, Child { key, node });
        Ok(())
    }

    /// The key of `name`: its first entry in the string table, appended
    /// when missing.
    fn key_of(&mut self, context: &Section, name: &str) -> Result<i16, FormatError> {
        if name.is_empty() || name.contains('\0') {
            return Err(context.error(format!(
                "tag `{}` cannot be stored in packed XML (empty or containing NUL)",
                name.escape_debug()
            )));
        }
        if let Some(i) = self.strings.iter().position(|s| s == name.as_bytes()) {
            return Ok(i as i16);
        }
        let key = i16::try_from(self.strings.len()).map_err(|_| {
            context.error(format!(
                "more than {} distinct tag names; packed XML holds at most {}",
                i16::MAX,
                i16::MAX
            ))
        })?;
        self.strings.push(name.as_bytes().to_vec());
        Ok(key)
    }

    /// An element with a child table: the root, or an element with
    /// children that is not a matrix.
    fn encode_element(&mut self, section: &Section) -> Result<Element, FormatError> {
        if section.children.len() > i16::MAX as usize {
            return Err(section.error(format!(
                "{} children; packed XML holds at most {} per element",
                section.children.len(),
                i16::MAX
            )));
        }
        let mut children = Vec::with_capacity(section.children.len());
        for child in &section.children {
            children.push(Child {
                key: self.key_of(child, &child.name)?,
                node: self.encode_child(child)?,
            });
        }
        Ok(Element {
            own: guess_value(&section.value),
            children,
            trailing: Vec::new(),
        })
    }

    fn encode_child(&mut self, section: &Section) -> Result<Node, FormatError> {
        if section.children.is_empty() {
            return Ok(Node::Value(guess_value(&section.value)));
        }
        if let Some(rows) = matrix_rows(section) {
            return Ok(Node::Value(Value {
                kind: ValueType::Float,
                data: rows.iter().flat_map(|f| f.to_le_bytes()).collect(),
            }));
        }
        Ok(Node::Element(self.encode_element(section)?))
    }

    /// Appends `element` (header, then data block); `keys` is the path to
    /// it, for errors.
    fn emit(
        &self,
        element: &Element,
        keys: &mut Vec<i16>,
        out: &mut Vec<u8>,
    ) -> Result<(), FormatError> {
        let count = i16::try_from(element.children.len()).map_err(|_| {
            self.write_error(
                keys,
                format!(
                    "{} children; packed XML holds at most {} per element",
                    element.children.len(),
                    i16::MAX
                ),
            )
        })?;
        let mut header = Vec::with_capacity(HEADER_LEN + RECORD_LEN * element.children.len());
        header.extend_from_slice(&count.to_le_bytes());
        let mut data = element.own.data.clone();
        header.extend_from_slice(
            &self
                .data_pos(keys, data.len(), element.own.kind)?
                .to_le_bytes(),
        );
        for child in &element.children {
            keys.push(child.key);
            let kind = match &child.node {
                Node::Value(value) => {
                    data.extend_from_slice(&value.data);
                    value.kind
                }
                Node::Element(inner) => {
                    self.emit(inner, keys, &mut data)?;
                    ValueType::Section
                }
            };
            header.extend_from_slice(&child.key.to_le_bytes());
            header.extend_from_slice(&self.data_pos(keys, data.len(), kind)?.to_le_bytes());
            keys.pop();
        }
        data.extend_from_slice(&element.trailing);
        out.extend_from_slice(&header);
        out.extend_from_slice(&data);
        Ok(())
    }

    fn data_pos(&self, keys: &[i16], offset: usize, kind: ValueType) -> Result<u32, FormatError> {
        u32::try_from(offset)
            .ok()
            .filter(|&o| o <= DATA_POS_MASK)
            .map(|o| o | (kind.code() << 28))
            .ok_or_else(|| {
                self.write_error(
                    keys,
                    "element data exceeds 2^28 bytes, the packed XML limit",
                )
            })
    }

    fn write_error(&self, keys: &[i16], message: impl Into<String>) -> FormatError {
        let mut path = ROOT_NAME.to_string();
        for &key in keys {
            path.push('/');
            path.push_str(&String::from_utf8_lossy(self.name_of(key).unwrap_or(b"?")));
        }
        FormatError::new(Location::Element { path, offset: 0 }, message)
    }
}

impl Element {
    fn empty() -> Element {
        Element {
            own: Value {
                kind: ValueType::String,
                data: Vec::new(),
            },
            children: Vec::new(),
            trailing: Vec::new(),
        }
    }
}

/// The element at `path` (child indices from `root`); a child stored as a
/// value on the way becomes an element keeping it as its own value.
fn element_at_mut<'a>(root: &'a mut Element, path: &[usize]) -> Option<&'a mut Element> {
    let mut element = root;
    for &i in path {
        let child = element.children.get_mut(i)?;
        if let Node::Value(value) = &mut child.node {
            let own = std::mem::replace(
                value,
                Value {
                    kind: ValueType::String,
                    data: Vec::new(),
                },
            );
            child.node = Node::Element(Element {
                own,
                ..Element::empty()
            });
        }
        let Node::Element(inner) = &mut child.node else {
            return None;
        };
        element = inner;
    }
    Some(element)
}

/// Every tag below `section` that `res_packer` puts in the string table:
/// all but the root's and a matrix's row tags.
fn collect_names(
    section: &Section,
    names: &mut std::collections::BTreeSet<String>,
) -> Result<(), FormatError> {
    if matrix_rows(section).is_some() {
        return Ok(());
    }
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

struct Reader<'a> {
    bytes: &'a [u8],
    names: &'a [String],
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
    own_type: ValueType,
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

    fn value_type(&self, path: &str, offset: usize, word: u32) -> Result<ValueType, FormatError> {
        let code = word >> 28;
        ValueType::from_code(code).ok_or_else(|| {
            self.error(
                path,
                offset,
                format!("unknown value type {code} (valid: 0 to 6)"),
            )
        })
    }

    /// Reads an element with a child table occupying `bytes[start..end]`.
    fn element(
        &self,
        path: &str,
        start: usize,
        end: usize,
        depth: usize,
    ) -> Result<Element, FormatError> {
        if depth > MAX_DEPTH {
            return Err(self.error(
                path,
                start,
                format!("packed XML nests deeper than {MAX_DEPTH} levels; the file is corrupt"),
            ));
        }
        let table = self.child_table(path, start, end)?;
        let own = Value {
            kind: table.own_type,
            data: self.bytes[table.data_start..table.data_start + table.own_end].to_vec(),
        };
        let mut children = Vec::with_capacity(table.count);
        let mut previous = table.own_end;
        for i in 0..table.count {
            let (child, child_end) = self.child(path, &table, i, previous, depth)?;
            children.push(child);
            previous = child_end;
        }
        Ok(Element {
            own,
            children,
            trailing: self.bytes[table.data_start + previous..end].to_vec(),
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
        let header_len = HEADER_LEN + RECORD_LEN * count;
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
            own_type: self.value_type(path, data_start, own_word)?,
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
    ) -> Result<(Child, usize), FormatError> {
        let record = table.start + HEADER_LEN + RECORD_LEN * i;
        let key = self.i16_at(record).unwrap_or(-1);
        let word = self.u32_at(record + 2).unwrap_or(0);
        let child_end = (word & DATA_POS_MASK) as usize;
        let child_name = usize::try_from(key)
            .ok()
            .and_then(|k| self.names.get(k))
            .ok_or_else(|| {
                self.error(
                    path,
                    record,
                    format!(
                        "child {i} names string {key} but the string table holds {} strings",
                        self.names.len()
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
        let node = match self.value_type(&child_path, child_start, word)? {
            ValueType::Section => {
                Node::Element(self.element(&child_path, child_start, child_stop, depth + 1)?)
            }
            kind => Node::Value(Value {
                kind,
                data: self.bytes[child_start..child_stop].to_vec(),
            }),
        };
        Ok((Child { key, node }, child_end))
    }
}

/// The [`Section`] of `element`, stored at `start` of the file; returns
/// where it ends.
fn section_of(
    names: &[String],
    element: &Element,
    name: &str,
    path: String,
    start: usize,
) -> Result<(Section, usize), FormatError> {
    let data_start = start + HEADER_LEN + RECORD_LEN * element.children.len();
    let value = render(&element.own, data_start, &path)?;
    let mut pos = data_start + element.own.data.len();
    let mut children = Vec::with_capacity(element.children.len());
    for child in &element.children {
        let child_name = usize::try_from(child.key)
            .ok()
            .and_then(|k| names.get(k))
            .map_or("?", String::as_str);
        let child_path = format!("{path}/{child_name}");
        let (section, end) = match &child.node {
            Node::Element(inner) => section_of(names, inner, child_name, child_path, pos)?,
            Node::Value(value) => {
                let end = pos + value.data.len();
                let section = Section {
                    name: child_name.to_string(),
                    value: render(value, pos, &child_path)?,
                    children: Vec::new(),
                    path: child_path,
                    span: pos..end,
                };
                (section, end)
            }
        };
        children.push(section);
        pos = end;
    }
    let end = pos + element.trailing.len();
    let section = Section {
        name: name.to_string(),
        value,
        children,
        path,
        span: start..end,
    };
    Ok((section, end))
}

fn value_error(path: &str, offset: usize, message: impl Into<String>) -> FormatError {
    FormatError::new(
        Location::Element {
            path: path.to_string(),
            offset: offset as u64,
        },
        message,
    )
}

/// Renders a typed value stored at `offset` as the engine's `asString`
/// would (floats in their shortest exact form).
fn render(value: &Value, offset: usize, path: &str) -> Result<String, FormatError> {
    let data = value.data.as_slice();
    match value.kind {
        ValueType::Section if data.is_empty() => Ok(String::new()),
        ValueType::Section => Err(value_error(
            path,
            offset,
            "an element's own value is marked as a section; the file is corrupt",
        )),
        ValueType::String => Ok(String::from_utf8_lossy(data).trim().to_string()),
        ValueType::Int => {
            let v = match *data {
                [] => 0,
                [a] => i64::from(a as i8),
                [a, b] => i64::from(i16::from_le_bytes([a, b])),
                [a, b, c, d] => i64::from(i32::from_le_bytes([a, b, c, d])),
                [a, b, c, d, e, f, g, h] => i64::from_le_bytes([a, b, c, d, e, f, g, h]),
                _ => {
                    return Err(value_error(
                        path,
                        offset,
                        format!(
                            "integer value of {} bytes; only 0, 1, 2, 4 or 8 are valid",
                            data.len()
                        ),
                    ))
                }
            };
            Ok(v.to_string())
        }
        ValueType::Float => {
            if !data.len().is_multiple_of(4) {
                return Err(value_error(
                    path,
                    offset,
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
        ValueType::Bool => Ok(if data.is_empty() { "false" } else { "true" }.to_string()),
        ValueType::Blob => Ok(base64_encode(data)),
        ValueType::EncryptedBlob => match data.split_first() {
            Some((0, rest)) => Ok(base64_encode(rest)),
            Some((1, rest)) => {
                let plain: Vec<u8> = rest.iter().map(|b| b ^ ENCRYPTION_KEY).collect();
                Ok(base64_encode(&plain))
            }
            Some((flag, _)) => Err(value_error(
                path,
                offset,
                format!("encrypted blob starts with {flag:#04x}; expected 0 or 1"),
            )),
            None => Err(value_error(
                path,
                offset,
                "encrypted blob is empty (no flag byte)",
            )),
        },
    }
}

/// The bytes of an encrypted blob as the engine stores `plain`: flag 1, then
/// each byte XOR-ed with its key.
pub fn encrypt_blob(plain: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(plain.len() + 1);
    out.push(1);
    out.extend(plain.iter().map(|b| b ^ ENCRYPTION_KEY));
    out
}

/// The value `res_packer` stores for a text (`addBestGuess`): empty →
/// string; `true`/`false` → bool; an unsigned integer beyond `i64` that
/// prints back identically → string; an integer that prints back
/// identically → int in the fewest of 0, 1, 2, 4, 8 bytes; 1 to 4 numbers
/// that print back identically with six decimals (`250.000000`, the
/// engine's `setFloat`) → floats; canonical base64 → blob; anything else →
/// string. So `250` packs as an int and `250.000000` as a float, as in the
/// engine.
pub fn guess_value(value: &str) -> Value {
    let text = value.trim();
    let value = |kind, data| Value { kind, data };
    if text.is_empty() {
        return value(ValueType::String, Vec::new());
    }
    if text == "true" {
        return value(ValueType::Bool, vec![1]);
    }
    if text == "false" {
        return value(ValueType::Bool, Vec::new());
    }
    if let Ok(v) = text.parse::<u64>() {
        if v > i64::MAX as u64 && v.to_string() == text {
            return value(ValueType::String, text.as_bytes().to_vec());
        }
    }
    if let Ok(v) = text.parse::<i64>() {
        if v.to_string() == text {
            return value(ValueType::Int, int_bytes(v));
        }
    }
    if let Some(floats) = six_decimal_floats(text) {
        let data = floats.iter().flat_map(|f| f.to_le_bytes()).collect();
        return value(ValueType::Float, data);
    }
    if let Some(decoded) = base64_decode(text) {
        if base64_encode(&decoded) == text {
            return value(ValueType::Blob, decoded);
        }
    }
    value(ValueType::String, text.as_bytes().to_vec())
}

/// `v` in the fewest bytes the engine's int type allows.
fn int_bytes(v: i64) -> Vec<u8> {
    if v == 0 {
        Vec::new()
    } else if let Ok(v) = i8::try_from(v) {
        v.to_le_bytes().to_vec()
    } else if let Ok(v) = i16::try_from(v) {
        v.to_le_bytes().to_vec()
    } else if let Ok(v) = i32::try_from(v) {
        v.to_le_bytes().to_vec()
    } else {
        v.to_le_bytes().to_vec()
    }
}

/// A number as C++ streams read it: digits, sign, point and exponent only
/// (no `inf` or `nan`).
fn stream_f32(word: &str) -> Option<f32> {
    if word.is_empty()
        || !word
            .bytes()
            .all(|b| b.is_ascii_digit() || matches!(b, b'+' | b'-' | b'.' | b'e' | b'E'))
    {
        return None;
    }
    word.parse::<f32>().ok().filter(|f| f.is_finite())
}

/// 1 to 4 space-separated floats, when `text` is exactly how the engine's
/// `setFloat`/`setVector*` print them (fixed, six decimals).
fn six_decimal_floats(text: &str) -> Option<Vec<f32>> {
    let words: Vec<&str> = text.split(' ').collect();
    if !(1..=4).contains(&words.len()) {
        return None;
    }
    let floats: Vec<f32> = words.iter().map(|w| stream_f32(w)).collect::<Option<_>>()?;
    let printed: Vec<String> = floats.iter().map(|f| format!("{f:.6}")).collect();
    (printed.join(" ") == text).then_some(floats)
}

/// The 12 floats `res_packer` stores for a matrix (`isMatrix`): exactly four
/// children, `row0`..`row3` all present, each three numbers; rows are taken
/// in child order, as the engine's `openChild(i)` does.
fn matrix_rows(section: &Section) -> Option<Vec<f32>> {
    if section.children.len() != 4 {
        return None;
    }
    let vector3 = |s: &Section| -> Option<Vec<f32>> {
        let words: Vec<&str> = s.value.split_ascii_whitespace().collect();
        if words.len() != 3 {
            return None;
        }
        words.iter().map(|w| stream_f32(w)).collect()
    };
    for row in ["row0", "row1", "row2", "row3"] {
        vector3(section.child(row)?)?;
    }
    let mut floats = Vec::with_capacity(12);
    for child in &section.children {
        floats.extend(vector3(child)?);
    }
    Some(floats)
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

#[cfg(test)]
mod tests {
    use super::*;

    const TYPE_STRING: u32 = 1;
    const TYPE_INT: u32 = 2;
    const TYPE_FLOAT: u32 = 3;
    const TYPE_BOOL: u32 = 4;
    const TYPE_BLOB: u32 = 5;
    const TYPE_ENCRYPTED_BLOB: u32 = 6;

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
    fn writer_guesses_as_the_engine_does() {
        let guess = |text: &str| {
            let v = guess_value(text);
            (v.kind, v.data)
        };
        assert_eq!(guess("true"), (ValueType::Bool, vec![1]));
        assert_eq!(guess("false"), (ValueType::Bool, vec![]));
        assert_eq!(guess(""), (ValueType::String, vec![]));
        assert_eq!(guess("0"), (ValueType::Int, vec![]));
        assert_eq!(guess("-128"), (ValueType::Int, vec![0x80]));
        assert_eq!(
            guess("250"),
            (ValueType::Int, 250i16.to_le_bytes().to_vec())
        );
        assert_eq!(guess("-70000").1.len(), 4);
        assert_eq!(guess("5000000000").1.len(), 8);
        // The engine's setFloat prints six decimals: only that spelling is a float.
        assert_eq!(
            guess("250.000000"),
            (ValueType::Float, 250f32.to_le_bytes().to_vec())
        );
        assert_eq!(guess("-0.000000").1, (-0f32).to_le_bytes());
        assert_eq!(guess("0.007812").0, ValueType::Float);
        assert_eq!(guess("1.000000 2.000000 3.000000").1.len(), 12);
        assert_eq!(guess("1.000000 2.000000 3.000000 4.000000").1.len(), 16);
        for text in [
            "0.5",
            "250.0",
            "1.000000  2.000000",
            "1.000000 2.000000 3.000000 4.000000 5.000000",
            "inf",
            "01",
            "+5",
            "18446744073709551615",
        ] {
            assert_eq!(guess(text).0, ValueType::String, "{text}");
        }
        assert_eq!(guess("aGkh"), (ValueType::Blob, b"hi!".to_vec()));
    }

    #[test]
    fn row_matrices_pack_as_twelve_floats_in_child_order() {
        let rows = |order: [usize; 4]| {
            let texts = [
                "0.000000 0.000000 -1.000000",
                "0.000000 1.000000 0.000000",
                "1.000000 0.000000 0.000000",
                "10.500000 20.000000 30.000000",
            ];
            node(
                "transform",
                "",
                order
                    .iter()
                    .map(|&i| node(&format!("row{i}"), texts[i], vec![]))
                    .collect(),
            )
        };
        let tree = node(
            "root",
            "",
            vec![
                rows([0, 1, 2, 3]),
                rows([1, 0, 2, 3]),
                node("x", "1", vec![]),
            ],
        );
        let document = Document::from_section(&tree).unwrap();
        assert_eq!(document.names(), ["transform", "x"], "no row tags");
        let back = parse(&document.to_bytes().unwrap()).unwrap();
        let Node::Value(matrix) = &document.root().children[0].node else {
            panic!("a matrix is a value");
        };
        assert_eq!(matrix.kind, ValueType::Float);
        assert_eq!(matrix.data.len(), 48);
        assert_eq!(back.children[0].value, "0 0 -1 0 1 0 1 0 0 10.5 20 30");
        assert_eq!(
            back.children[0].as_matrix().unwrap(),
            tree.children[0].as_matrix().unwrap()
        );
        assert!(
            back.children[1].value.starts_with("0 1 0 0 0 -1 "),
            "child order"
        );
        // Three rows, or a fifth child: an element as any other.
        let mut three = rows([0, 1, 2, 3]);
        three.children.pop();
        assert!(matrix_rows(&three).is_none());
        let mut five = rows([0, 1, 2, 3]);
        five.children.push(node("row4", "1 2 3", vec![]));
        assert!(matrix_rows(&five).is_none());
    }

    /// Every value type, an unsorted string table with a duplicate and a
    /// name that is not UTF-8, bytes after the last child: all written back.
    fn odd_file() -> Vec<u8> {
        let matrix: Vec<u8> = (1..=12).flat_map(|i| (i as f32).to_le_bytes()).collect();
        let inner = root_with(&[(1, TYPE_FLOAT, &250f32.to_le_bytes()), (4, TYPE_BOOL, &[1])]);
        let mut inner_trailing = inner.clone();
        inner_trailing.extend_from_slice(b"xyz");
        let mut root = root_with(&[
            (0, TYPE_INT, &300i16.to_le_bytes()),
            (2, TYPE_FLOAT, &matrix),
            (3, TYPE_ENCRYPTED_BLOB, &encrypt_blob(b"secret")),
            (1, 0, &inner_trailing),
            (5, TYPE_BLOB, &[0, 1, 2]),
            (0, TYPE_INT, &(-5i64 << 40).to_le_bytes()),
        ]);
        root.extend_from_slice(b"tail");
        let mut bytes = file(&["z", "m", "a", "z", "b"], &root);
        bytes.truncate(MAGIC.len() + 1);
        bytes.extend_from_slice(b"z\0m\0a\0z\0b\0\xff\0\0");
        bytes.extend_from_slice(&root);
        bytes
    }

    #[test]
    fn documents_write_back_the_bytes_they_were_read_from() {
        let bytes = odd_file();
        let document = Document::parse(&bytes).unwrap();
        assert_eq!(document.to_bytes().unwrap(), bytes);
        assert_eq!(document.root().trailing, b"tail");
        let root = document.to_section().unwrap();
        assert_eq!(root.children[0].value, "300");
        assert_eq!(root.children[2].value, base64_encode(b"secret"));
        assert_eq!(root.children[3].child_text("m"), Some("250"));
        assert_eq!(root.children[5].value, (-5i64 << 40).to_string());
        // Spans are where the bytes are.
        let span = root.children[1].span.clone();
        assert_eq!(
            &bytes[span],
            (1..=12)
                .flat_map(|i| (i as f32).to_le_bytes())
                .collect::<Vec<_>>()
        );
        assert_eq!(root.span.end, bytes.len());
        // Files the writer makes, too.
        let tree = node(
            "root",
            "v",
            vec![node("a", "250.000000", vec![node("b", "-7", vec![])])],
        );
        let written = write(&tree).unwrap();
        assert_eq!(
            Document::parse(&written).unwrap().to_bytes().unwrap(),
            written
        );
    }

    fn model_with_shadow() -> Section {
        node(
            "root",
            "",
            vec![
                node(
                    "model",
                    "",
                    vec![
                        node("shadow", "1", vec![]),
                        node("resource", "a.model", vec![]),
                        node("shadow", "2", vec![]),
                        node("castsShadow", "true", vec![]),
                    ],
                ),
                node("audio", "", vec![node("maxDistance", "250.000000", vec![])]),
                node("model", "leaf", vec![]),
            ],
        )
    }

    #[test]
    fn set_child_replaces_in_place_and_keeps_every_other_byte() {
        let original = write(&model_with_shadow()).unwrap();
        let mut document = Document::parse(&original).unwrap();
        let before = document.clone();
        let shadow = node(
            "shadow",
            "3",
            vec![node(
                "RenderSet",
                "",
                vec![node("PrimitiveGroup", "3", vec![])],
            )],
        );
        let context = node("root", "", vec![]);
        document.set_child(&[0], &shadow, &context).unwrap();
        document
            .set_child(&[2], &node("shadow", "4", vec![]), &context)
            .unwrap();
        let names = document.names();
        assert_eq!(
            &names[..before.names().len()],
            before.names().as_slice(),
            "table kept"
        );
        assert_eq!(
            &names[before.names().len()..],
            ["RenderSet", "PrimitiveGroup"],
            "new tags last"
        );
        let out = document.to_bytes().unwrap();
        let root = parse(&out).unwrap();
        let tags: Vec<&str> = root.children[0]
            .children
            .iter()
            .map(|c| c.name.as_str())
            .collect();
        assert_eq!(tags, ["shadow", "resource", "castsShadow"]);
        assert_eq!(root.children[0].children[0].value, "3");
        // The audio element's bytes are the same.
        assert_eq!(document.root().children[1], before.root().children[1]);
        // A leaf model became an element keeping its own value.
        assert_eq!(root.children[2].value, "leaf");
        assert_eq!(root.children[2].child_text("shadow"), Some("4"));
        // The same edit again: the same bytes.
        let mut again = Document::parse(&out).unwrap();
        again.set_child(&[0], &shadow, &context).unwrap();
        again
            .set_child(&[2], &node("shadow", "4", vec![]), &context)
            .unwrap();
        assert_eq!(again.to_bytes().unwrap(), out);
        assert!(document.set_child(&[7], &shadow, &context).is_err());
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

        /// Texts of every kind the engine's type guess tells apart, the
        /// six-decimal floats (integral ones too) and row matrices included.
        fn value() -> impl Strategy<Value = String> {
            let six = |v: Vec<f32>| {
                v.iter()
                    .map(|f| format!("{f:.6}"))
                    .collect::<Vec<_>>()
                    .join(" ")
            };
            prop_oneof![
                any::<i64>().prop_map(|v| v.to_string()),
                any::<i8>().prop_map(|v| v.to_string()),
                any::<f32>().prop_map(|v| v.to_string()),
                (-100_000i32..100_000).prop_map(move |v| six(vec![v as f32])),
                proptest::collection::vec(-1.0e6f32..1.0e6, 1..5).prop_map(six),
                proptest::collection::vec(any::<f32>(), 1..13).prop_map(|v| v
                    .iter()
                    .map(|f| f.to_string())
                    .collect::<Vec<_>>()
                    .join(" ")),
                proptest::collection::vec(any::<u8>(), 1..20).prop_map(|b| base64_encode(&b)),
                Just("true".to_string()),
                Just("false".to_string()),
                "[ -~é]{0,16}".prop_map(|s| s.trim().to_string()),
            ]
        }

        fn matrix() -> impl Strategy<Value = Section> {
            proptest::collection::vec(-1.0e4f32..1.0e4, 12).prop_map(|v| {
                let rows = (0..4)
                    .map(|i| {
                        let text =
                            format!("{:.6} {:.6} {:.6}", v[3 * i], v[3 * i + 1], v[3 * i + 2]);
                        node(&format!("row{i}"), &text, vec![])
                    })
                    .collect();
                node("transform", "", rows)
            })
        }

        fn tree() -> impl Strategy<Value = Section> {
            let name = "[a-zA-Z_][a-zA-Z0-9_.]{0,8}";
            let leaf = prop_oneof![
                4 => (name, value()).prop_map(|(n, v)| node(&n, &v, vec![])),
                1 => matrix(),
            ];
            leaf.prop_recursive(5, 64, 6, move |inner| {
                (name, value(), proptest::collection::vec(inner, 0..6))
                    .prop_map(|(n, v, c)| node(&n, &v, c))
            })
        }

        /// The numbers of a text as the engine's floats, if all words are.
        fn floats(text: &str) -> Option<Vec<u32>> {
            text.split(' ')
                .map(|w| w.parse::<f32>().ok().map(f32::to_bits))
                .collect()
        }

        /// What a reader sees of a packed tree against the text it was
        /// packed from: tags, children, values (a float's text may print
        /// shorter), a row matrix as its twelve numbers.
        fn same_as_read(text: &Section, packed: &Section) -> bool {
            if let Some(rows) = matrix_rows(text) {
                let bits: Vec<u32> = rows.iter().map(|f| f.to_bits()).collect();
                return packed.children.is_empty() && floats(&packed.value) == Some(bits);
            }
            let value_read = text.value == packed.value
                || (guess_value(&text.value).kind == ValueType::Float
                    && floats(&text.value).is_some()
                    && floats(&text.value) == floats(&packed.value));
            value_read
                && text.children.len() == packed.children.len()
                && text
                    .children
                    .iter()
                    .zip(&packed.children)
                    .all(|(a, b)| a.name == b.name && same_as_read(a, b))
        }

        /// A stored value of `kind` with data that type can hold.
        fn stored_value() -> impl Strategy<Value = Value> {
            let bytes = |n| proptest::collection::vec(any::<u8>(), n);
            let value = |kind| move |data| Value { kind, data };
            prop_oneof![
                bytes(0..12).prop_map(value(ValueType::String)),
                prop_oneof![Just(0usize), Just(1), Just(2), Just(4), Just(8)]
                    .prop_flat_map(move |n| bytes(n..n + 1))
                    .prop_map(value(ValueType::Int)),
                (0usize..=12)
                    .prop_flat_map(move |n| bytes(4 * n..4 * n + 1))
                    .prop_map(value(ValueType::Float)),
                bytes(0..2).prop_map(value(ValueType::Bool)),
                bytes(0..12).prop_map(value(ValueType::Blob)),
                (0u8..2, bytes(0..12)).prop_map(|(flag, rest)| {
                    let mut data = vec![flag];
                    data.extend(rest);
                    Value {
                        kind: ValueType::EncryptedBlob,
                        data,
                    }
                }),
            ]
        }

        fn stored_element(names: i16) -> impl Strategy<Value = Element> {
            let leaf = stored_value().prop_map(Node::Value);
            let node = leaf.prop_recursive(4, 48, 5, move |inner| {
                (
                    stored_value(),
                    proptest::collection::vec((0..names, inner), 0..5),
                    proptest::collection::vec(any::<u8>(), 0..3),
                )
                    .prop_map(|(own, children, trailing)| {
                        Node::Element(element(own, children, trailing))
                    })
            });
            (
                stored_value(),
                proptest::collection::vec((0..names, node), 0..6),
            )
                .prop_map(|(own, children)| element(own, children, Vec::new()))
        }

        fn element(own: Value, children: Vec<(i16, Node)>, trailing: Vec<u8>) -> Element {
            Element {
                own,
                children: children
                    .into_iter()
                    .map(|(key, node)| Child { key, node })
                    .collect(),
                trailing,
            }
        }

        fn document() -> impl Strategy<Value = Document> {
            proptest::collection::vec("[a-zA-Z_]{1,6}", 1..6).prop_flat_map(|names| {
                let count = names.len() as i16;
                (any::<u8>(), stored_element(count)).prop_map(move |(version, root)| Document {
                    version,
                    strings: names.iter().map(|n| n.as_bytes().to_vec()).collect(),
                    root,
                })
            })
        }

        proptest! {
            #[test]
            fn random_trees_pack_as_read_and_write_back(children in proptest::collection::vec(tree(), 0..5)) {
                let root = node("root", "", children);
                let bytes = write(&root).unwrap();
                let back = parse(&bytes).unwrap();
                prop_assert!(same_as_read(&root, &back), "{root:#?}\n{back:#?}");
                prop_assert_eq!(Document::parse(&bytes).unwrap().to_bytes().unwrap(), bytes);
            }

            #[test]
            fn random_documents_write_back_byte_for_byte(document in document()) {
                let bytes = document.to_bytes().unwrap();
                let back = Document::parse(&bytes).unwrap();
                prop_assert_eq!(&back, &document);
                prop_assert_eq!(back.to_bytes().unwrap(), bytes);
                prop_assert!(back.to_section().is_ok());
            }

            #[test]
            fn random_bytes_never_panic(tail in proptest::collection::vec(any::<u8>(), 0..200)) {
                let mut bytes = MAGIC.to_vec();
                bytes.extend(tail);
                let _ = parse(&bytes);
                if let Ok(document) = Document::parse(&bytes) {
                    prop_assert_eq!(document.to_bytes().unwrap(), bytes);
                }
            }
        }
    }
}

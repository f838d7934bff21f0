//! Readers and writers of the BigWorld file formats (and of the crate's own
//! partial results and pictures): bytes into values and values into bytes.
//! They never touch the file system (`files` reads and writes the bytes), so
//! every decoder can be driven by any slice.

pub mod bake_settings;
pub mod binsection;
pub mod chunk;
pub mod chunk_scan;
pub mod model;
pub mod packed_xml;
pub mod partial;
pub mod png_write;
pub mod primitives;
pub mod section;
pub mod shadow_write;
pub mod space_settings;
pub mod speedtree_proxies;
pub mod terrain;
pub mod visual;
pub mod xml;

pub use section::Section;

use crate::error::{Error, FormatError, TextPosition};
use std::path::PathBuf;

/// Parses a data section in either encoding, sniffing the magic: packed
/// binary XML (`45 4E A1 62`) or text XML.
pub fn parse_data_section(bytes: &[u8]) -> Result<Section, FormatError> {
    if bytes.starts_with(&packed_xml::MAGIC) {
        packed_xml::parse(bytes)
    } else {
        xml::parse(bytes)
    }
}

/// The line and column of byte `offset` of a file's `bytes`, when they are
/// text: packed XML is not, and only the readers know its magic.
pub fn text_position(bytes: &[u8], offset: u64) -> Option<TextPosition> {
    if bytes.starts_with(&packed_xml::MAGIC) {
        return None;
    }
    TextPosition::of(bytes, offset)
}

// Beside `text_position` rather than in `error`, which knows no format.
impl FormatError {
    /// Attaches the file and, when its bytes are text, the line and column
    /// of the byte location (editors jump to `file:line:column`).
    pub fn in_source(self, path: impl Into<PathBuf>, bytes: &[u8]) -> Error {
        let position = self.at.offset().and_then(|o| text_position(bytes, o));
        Error::Format {
            path: path.into(),
            at: self.at,
            message: self.message,
            position,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_in_text_give_line_and_column_and_packed_xml_none() {
        let text = "<a>\n\t<bé>x</bé>\n</a>".as_bytes();
        let at = text.iter().position(|&b| b == b'x').unwrap() as u64;
        let err = FormatError::at_byte(at as usize, "bad").in_source("f.xml", text);
        assert_eq!(err.to_string(), format!("f.xml:2:6 at byte {at}: bad"));
        assert_eq!(
            text_position(text, at),
            Some(TextPosition { line: 2, column: 6 })
        );
        let mut packed = packed_xml::MAGIC.to_vec();
        packed.extend_from_slice(b"\n\n\n");
        assert_eq!(text_position(&packed, 6), None);
        let err = FormatError::at_byte(6, "bad").in_source("f.xml", &packed);
        assert_eq!(err.to_string(), "f.xml at byte 6: bad");
    }
}

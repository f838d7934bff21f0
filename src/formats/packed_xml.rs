//! Packed binary XML (resmgr/packed_section.cpp), read into the same
//! [`Section`] tree as text XML.

use super::Section;
use crate::error::FormatError;

pub const MAGIC: [u8; 4] = [0x45, 0x4E, 0xA1, 0x62];

/// Parses a whole packed-XML file (starting with [`MAGIC`]).
pub fn parse(bytes: &[u8]) -> Result<Section, FormatError> {
    let _ = bytes;
    Err(FormatError::whole_file(
        "packed binary XML: not implemented yet",
    ))
}

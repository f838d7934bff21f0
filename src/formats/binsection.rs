//! BinSection containers (resmgr/bin_section.cpp): `.primitives`, 1.x `.cdata`.

use crate::error::FormatError;
use std::ops::Range;

pub const MAGIC: [u8; 4] = [0x65, 0x4E, 0xA1, 0x42];

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
    pub fn get(&self, name: &str) -> Option<(&'a [u8], usize)> {
        let _ = name;
        None
    }
}

pub fn parse(bytes: &[u8]) -> Result<BinSection<'_>, FormatError> {
    let _ = bytes;
    Err(FormatError::whole_file("BinSection: not implemented yet"))
}

/// Writes a container with the magic, padded data and a padded index.
pub fn write(sections: &[(&str, &[u8])]) -> Vec<u8> {
    let _ = sections;
    Vec::new()
}

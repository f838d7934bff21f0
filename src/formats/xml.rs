//! BigWorld text XML into a [`Section`] tree.

use super::Section;
use crate::error::FormatError;

pub fn parse(bytes: &[u8]) -> Result<Section, FormatError> {
    let _ = bytes;
    Err(FormatError::whole_file("text XML: not implemented yet"))
}

//! Readers and writers of the BigWorld file formats. This is the only part of
//! the crate that touches the file system; everything below `scene/` and the
//! bake work on the values these modules return.

pub mod bake_settings;
pub mod binsection;
pub mod chunk;
pub mod model;
pub mod packed_xml;
pub mod partial;
pub mod png_write;
pub mod primitives;
pub mod resources;
pub mod section;
pub mod shadow_write;
pub mod space_settings;
pub mod terrain;
pub mod visual;
pub mod xml;

pub use section::Section;

use crate::error::FormatError;

/// Parses a data section in either encoding, sniffing the magic: packed
/// binary XML (`45 4E A1 62`) or text XML.
pub fn parse_data_section(bytes: &[u8]) -> Result<Section, FormatError> {
    if bytes.starts_with(&packed_xml::MAGIC) {
        packed_xml::parse(bytes)
    } else {
        xml::parse(bytes)
    }
}

/// Reads and validates a bake settings file; relative paths in it are taken
/// relative to the file's folder.
pub fn read_bake_settings(path: &std::path::Path) -> crate::Result<bake_settings::BakeSettings> {
    let bytes = resources::read_file(path)?;
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => std::path::Path::new("."),
    };
    let mut settings = parse_data_section(&bytes)
        .and_then(|root| bake_settings::parse(&root, dir))
        .map_err(|e| e.in_source(path, &bytes))?;
    for unknown in &mut settings.unknown {
        unknown.position = crate::error::TextPosition::of(&bytes, unknown.offset as u64);
    }
    Ok(settings)
}

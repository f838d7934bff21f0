//! The world model the bake consumes: chunks, placed instances, primitive
//! groups with their flags, terrain blocks. Built from `formats/` values;
//! does no I/O itself.

pub mod terrain;

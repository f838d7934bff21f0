//! Vertex and index sections of `.primitives` files (moo/primitive.cpp,
//! moo/vertex_formats.hpp). Only positions matter to the bake.

use crate::error::FormatError;

#[derive(Debug, Clone, PartialEq)]
pub struct Vertices {
    /// Format name as stored, up to its first NUL, lower-cased.
    pub format: String,
    pub positions: Vec<[f32; 3]>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PrimitiveGroup {
    pub start_index: u32,
    pub n_primitives: u32,
    pub start_vertex: u32,
    pub n_vertices: u32,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Indices {
    /// `list` (u16) or `list32` (u32).
    pub format: String,
    pub indices: Vec<u32>,
    pub groups: Vec<PrimitiveGroup>,
}

pub fn read_vertices(data: &[u8]) -> Result<Vertices, FormatError> {
    let _ = data;
    Err(FormatError::whole_file("vertices: not implemented yet"))
}

pub fn read_indices(data: &[u8]) -> Result<Indices, FormatError> {
    let _ = data;
    Err(FormatError::whole_file("indices: not implemented yet"))
}

/// An `xyznuv` vertex section (normals from the caller, uv zero).
pub fn write_vertices(positions: &[[f32; 3]], normals: &[[f32; 3]]) -> Vec<u8> {
    let _ = (positions, normals);
    Vec::new()
}

/// An index section, `list` when every index fits in u16, else `list32`.
pub fn write_indices(indices: &[u32], groups: &[PrimitiveGroup]) -> Vec<u8> {
    let _ = (indices, groups);
    Vec::new()
}

//! Vertex and index sections of `.primitives` files (moo/primitive.cpp,
//! moo/vertices.cpp, moo/vertex_formats.hpp, moo/primitive_file_structs.hpp).
//! Only positions matter to the bake, so vertices are decoded to positions
//! and everything else in a vertex is skipped by its format's stride.
//!
//! Every count in a section is checked against the bytes actually present
//! before anything is allocated; errors carry byte offsets relative to the
//! section (callers `.shifted()` them by the section's offset in the file).

use crate::error::FormatError;

#[derive(Debug, Clone, PartialEq)]
pub struct Vertices {
    /// Format name as stored, up to its first NUL, lower-cased. For a 14.x
    /// processed section (`BPVT` prefix) this is the on-disk format of the
    /// inner header (e.g. `set3/xyznuvtbpc`), which decides the layout.
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

/// Length of `char format[64]`, the name field of every section header.
const FORMAT_LEN: usize = 64;
/// `VertexHeader { char vertexFormat[64]; int nVertices; }`.
const VERTEX_HEADER_LEN: usize = FORMAT_LEN + 4;
/// `ProcessedVertexHeader { u32 magic; char originalVertexFormat[64]; VertexHeader; }`.
const PROCESSED_HEADER_LEN: usize = 4 + FORMAT_LEN + VERTEX_HEADER_LEN;
/// `IndexHeader { char indexFormat[64]; int nIndices; int nTriangleGroups; }`.
const INDEX_HEADER_LEN: usize = FORMAT_LEN + 8;
/// `PrimitiveGroup { int startIndex, nPrimitives, startVertex, nVertices; }`.
const GROUP_LEN: usize = 16;
/// `DECLARE_FOURCC('B','P','V','T')` as stored (little-endian).
pub const PROCESSED_VERTICES_MAGIC: [u8; 4] = *b"BPVT";

/// The source formats the engine accepts (vertices.cpp's whitelist), with
/// the size of their packed structs (vertex_formats.hpp, `#pragma pack(1)`).
const SOURCE_FORMATS: &[(&str, usize)] = &[
    ("xyznuv", 32),
    ("xyznuvtb", 32),
    ("xyznduv", 36),
    ("xyznuvi", 36),
    ("xyznuvitb", 36),
    ("xyznuv2tb", 40),
    ("xyznuviiiww", 29),
    ("xyznuviiiwwtb", 37),
];

/// GPU ("PC") formats of 14.x processed sections, named `set3/<name>` on
/// disk. The first stride is the 14.4.1 struct size with its packing set 1
/// (normals as 4 bytes, texture coordinates as two i16); the second is the
/// same layout with f32 texture coordinates, which other tool chains write
/// under the same names. A section is decoded with the stride that makes its
/// vertices fill it exactly (see `pick_stride`).
const PROCESSED_FORMATS: &[(&str, [usize; 2])] = &[
    ("xyznuvpc", [20, 24]),
    ("xyznuv2pc", [24, 32]),
    ("xyznuvipc", [24, 28]),
    ("xyznuvtbpc", [28, 32]),
    ("xyznuv2tbpc", [32, 40]),
    ("xyznuvitbpc", [32, 36]),
    ("xyznuviiiwwpc", [28, 32]),
    ("xyznuv2iiiwwpc", [30, 38]),
    ("xyznuviiiwwtbpc", [36, 40]),
];

fn read_u32(data: &[u8], at: usize) -> Option<u32> {
    let end = at.checked_add(4)?;
    let b: [u8; 4] = data.get(at..end)?.try_into().ok()?;
    Some(u32::from_le_bytes(b))
}

fn read_i32(data: &[u8], at: usize) -> Option<i32> {
    read_u32(data, at).map(|v| v as i32)
}

/// A `char[64]` name: up to the first NUL (real files hold garbage after
/// it), lower-cased as the engine does before comparing.
fn format_name(field: &[u8]) -> String {
    let end = field.iter().position(|&b| b == 0).unwrap_or(field.len());
    String::from_utf8_lossy(&field[..end]).to_ascii_lowercase()
}

/// Reads a non-negative i32 count, or says where and what is wrong.
fn read_count(data: &[u8], at: usize, what: &str) -> Result<usize, FormatError> {
    let raw = read_i32(data, at).ok_or_else(|| {
        FormatError::at_byte(
            at,
            format!(
                "section is {} bytes long, too short to hold its {what} (4 bytes at byte {at})",
                data.len()
            ),
        )
    })?;
    usize::try_from(raw).map_err(|_| {
        FormatError::at_byte(
            at,
            format!("{what} is negative ({raw}); the section is corrupt"),
        )
    })
}

fn known_vertex_formats() -> String {
    let mut names: Vec<String> = SOURCE_FORMATS.iter().map(|(n, _)| n.to_string()).collect();
    names.extend(PROCESSED_FORMATS.iter().map(|(n, _)| format!("set3/{n}")));
    names.join(", ")
}

/// The candidate strides of a format name, most likely first.
fn strides_of(format: &str) -> Option<Vec<usize>> {
    if let Some(&(_, stride)) = SOURCE_FORMATS.iter().find(|(n, _)| *n == format) {
        return Some(vec![stride]);
    }
    let bare = format.strip_prefix("set3/").unwrap_or(format);
    PROCESSED_FORMATS
        .iter()
        .find(|(n, _)| *n == bare)
        .map(|(_, s)| s.to_vec())
}

/// With several candidate strides, the one whose vertices fill the rest of
/// the section exactly; otherwise the first that fits (trailing bytes are
/// tolerated, as the engine ignores them).
fn pick_stride(candidates: &[usize], count: usize, available: usize) -> Option<usize> {
    let need = |s: usize| count.checked_mul(s);
    candidates
        .iter()
        .copied()
        .find(|&s| need(s) == Some(available))
        .or_else(|| {
            candidates
                .iter()
                .copied()
                .find(|&s| need(s).is_some_and(|n| n <= available))
        })
}

/// Decodes a vertex section: `VertexHeader` then packed vertices, optionally
/// preceded by the 14.x `BPVT` processed header. Returns positions only;
/// NaN or infinite positions are returned as stored.
pub fn read_vertices(data: &[u8]) -> Result<Vertices, FormatError> {
    let processed = data.starts_with(&PROCESSED_VERTICES_MAGIC);
    let (header_at, body_at) = if processed {
        (4 + FORMAT_LEN, PROCESSED_HEADER_LEN)
    } else {
        (0, VERTEX_HEADER_LEN)
    };
    if data.len() < body_at {
        return Err(FormatError::at_byte(
            0,
            format!(
                "vertex section is {} bytes long, too short for its {body_at}-byte {}header",
                data.len(),
                if processed { "processed (BPVT) " } else { "" }
            ),
        ));
    }
    let format = format_name(&data[header_at..header_at + FORMAT_LEN]);
    let count_at = header_at + FORMAT_LEN;
    let count = read_count(data, count_at, "vertex count")?;
    let candidates = strides_of(&format).ok_or_else(|| {
        FormatError::at_byte(
            header_at,
            format!(
                "unknown vertex format `{format}`; known formats: {}",
                known_vertex_formats()
            ),
        )
    })?;
    let available = data.len() - body_at;
    let stride = pick_stride(&candidates, count, available).ok_or_else(|| {
        let strides = candidates
            .iter()
            .map(|s| s.to_string())
            .collect::<Vec<_>>()
            .join(" or ");
        FormatError::at_byte(
            count_at,
            format!(
                "{count} vertices of format `{format}` ({strides} bytes each) do not fit in \
                 the {available} bytes after the header at byte {body_at}; \
                 the section is truncated or its count is corrupt"
            ),
        )
    })?;
    let body = &data[body_at..];
    // `pick_stride` proved count * stride <= available, so this allocation
    // is bounded by the section's size.
    let positions = body
        .chunks_exact(stride)
        .take(count)
        .map(|v| {
            let f = |i: usize| {
                let b: [u8; 4] = [v[4 * i], v[4 * i + 1], v[4 * i + 2], v[4 * i + 3]];
                f32::from_le_bytes(b)
            };
            [f(0), f(1), f(2)]
        })
        .collect();
    Ok(Vertices { format, positions })
}

/// Decodes an index section: `IndexHeader`, the indices (u16 for `list`,
/// u32 for `list32`), then the `PrimitiveGroup` table.
pub fn read_indices(data: &[u8]) -> Result<Indices, FormatError> {
    if data.len() < INDEX_HEADER_LEN {
        return Err(FormatError::at_byte(
            0,
            format!(
                "index section is {} bytes long, too short for its {INDEX_HEADER_LEN}-byte header",
                data.len()
            ),
        ));
    }
    let format = format_name(&data[..FORMAT_LEN]);
    let size = match format.as_str() {
        "list" => 2,
        "list32" => 4,
        _ => {
            return Err(FormatError::at_byte(
                0,
                format!(
                    "unknown index format `{format}`; known formats: list (16-bit), \
                     list32 (32-bit); only triangle lists are supported"
                ),
            ))
        }
    };
    let n_indices = read_count(data, FORMAT_LEN, "index count")?;
    let n_groups = read_count(data, FORMAT_LEN + 4, "primitive group count")?;
    let available = data.len() - INDEX_HEADER_LEN;
    let index_bytes = n_indices
        .checked_mul(size)
        .filter(|&n| n <= available)
        .ok_or_else(|| {
            FormatError::at_byte(
                FORMAT_LEN,
                format!(
                    "{n_indices} indices of format `{format}` ({size} bytes each) do not fit in \
                     the {available} bytes after the header; the section is truncated or its \
                     count is corrupt"
                ),
            )
        })?;
    let groups_at = INDEX_HEADER_LEN + index_bytes;
    let group_room = data.len() - groups_at;
    let group_bytes = n_groups
        .checked_mul(GROUP_LEN)
        .filter(|&n| n <= group_room)
        .ok_or_else(|| {
            FormatError::at_byte(
                FORMAT_LEN + 4,
                format!(
                    "{n_groups} primitive groups ({GROUP_LEN} bytes each) do not fit in the \
                     {group_room} bytes after the indices at byte {groups_at}; the section is \
                     truncated or its count is corrupt"
                ),
            )
        })?;
    let index_data = &data[INDEX_HEADER_LEN..groups_at];
    let indices: Vec<u32> = if size == 2 {
        index_data
            .chunks_exact(2)
            .map(|b| u32::from(u16::from_le_bytes([b[0], b[1]])))
            .collect()
    } else {
        index_data
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    };
    let group_data = &data[groups_at..groups_at + group_bytes];
    let mut groups = Vec::with_capacity(n_groups);
    for (g, record) in group_data.chunks_exact(GROUP_LEN).enumerate() {
        let record_at = groups_at + g * GROUP_LEN;
        let mut fields = [0u32; 4];
        for (k, name) in ["startIndex", "nPrimitives", "startVertex", "nVertices"]
            .iter()
            .enumerate()
        {
            let raw = read_i32(record, 4 * k).unwrap_or(0);
            fields[k] = u32::try_from(raw).map_err(|_| {
                FormatError::at_byte(
                    record_at + 4 * k,
                    format!("primitive group {g} has a negative {name} ({raw})"),
                )
            })?;
        }
        groups.push(PrimitiveGroup {
            start_index: fields[0],
            n_primitives: fields[1],
            start_vertex: fields[2],
            n_vertices: fields[3],
        });
    }
    Ok(Indices {
        format,
        indices,
        groups,
    })
}

impl Indices {
    /// Bytes per stored index: 4 for `list32`, else 2.
    fn index_size(&self) -> usize {
        if self.format == "list32" {
            4
        } else {
            2
        }
    }

    /// Byte offset of index `i` in the section this value was read from.
    fn index_offset(&self, i: usize) -> usize {
        i.saturating_mul(self.index_size())
            .saturating_add(INDEX_HEADER_LEN)
    }

    /// Byte offset of group `g`'s record in the section.
    fn group_offset(&self, g: usize) -> usize {
        self.index_offset(self.indices.len())
            .saturating_add(g.saturating_mul(GROUP_LEN))
    }
}

/// The `3 * nPrimitives` indices of primitive group `group` (a triangle
/// list; `startIndex` counts indices and indices are absolute, base vertex
/// 0), after checking that the group exists, that its range lies inside the
/// index buffer and that every index is below `vertex_count`. Error offsets
/// are relative to the index section.
pub fn group_triangles(
    indices: &Indices,
    group: usize,
    vertex_count: usize,
) -> Result<&[u32], FormatError> {
    let g = indices.groups.get(group).ok_or_else(|| {
        FormatError::at_byte(
            indices.group_offset(0),
            format!(
                "primitive group {group} is not in the index section, which has {} group(s); \
                 the .visual refers to a group the .primitives file does not have",
                indices.groups.len()
            ),
        )
    })?;
    let start = g.start_index as usize;
    let range = (g.n_primitives as usize)
        .checked_mul(3)
        .and_then(|n| start.checked_add(n).map(|end| start..end))
        .filter(|r| r.end <= indices.indices.len())
        .ok_or_else(|| {
            FormatError::at_byte(
                indices.group_offset(group),
                format!(
                    "primitive group {group} (startIndex {}, {} triangles) runs past the end of \
                     the index buffer of {} indices",
                    g.start_index,
                    g.n_primitives,
                    indices.indices.len()
                ),
            )
        })?;
    let tris = &indices.indices[range];
    if let Some((k, &bad)) = tris
        .iter()
        .enumerate()
        .find(|(_, &i)| i as usize >= vertex_count)
    {
        let pos = start + k;
        return Err(FormatError::at_byte(
            indices.index_offset(pos),
            format!(
                "primitive group {group}: index {pos} is {bad}, but the vertex section has only \
                 {vertex_count} vertices; the vertex and index sections do not belong together"
            ),
        ));
    }
    Ok(tris)
}

fn format_field(name: &str) -> [u8; FORMAT_LEN] {
    let mut field = [0u8; FORMAT_LEN];
    field[..name.len()].copy_from_slice(name.as_bytes());
    field
}

fn count_i32(n: usize, what: &str) -> [u8; 4] {
    i32::try_from(n)
        .unwrap_or_else(|_| panic!("{n} {what} exceed the format's i32 count"))
        .to_le_bytes()
}

/// An `xyznuv` vertex section (normals from the caller, uv zero).
///
/// # Panics
/// If `normals` and `positions` differ in length, or there are more than
/// `i32::MAX` vertices.
pub fn write_vertices(positions: &[[f32; 3]], normals: &[[f32; 3]]) -> Vec<u8> {
    assert_eq!(
        positions.len(),
        normals.len(),
        "write_vertices needs one normal per position"
    );
    let mut out = Vec::with_capacity(VERTEX_HEADER_LEN + 32 * positions.len());
    out.extend_from_slice(&format_field("xyznuv"));
    out.extend_from_slice(&count_i32(positions.len(), "vertices"));
    for (p, n) in positions.iter().zip(normals) {
        for v in p.iter().chain(n).chain(&[0.0, 0.0]) {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// An index section, `list` when every index fits in u16, else `list32`.
///
/// # Panics
/// If there are more than `i32::MAX` indices or groups, or a group field
/// exceeds `i32::MAX`.
pub fn write_indices(indices: &[u32], groups: &[PrimitiveGroup]) -> Vec<u8> {
    let wide = indices.iter().any(|&i| i > u32::from(u16::MAX));
    let mut out = Vec::new();
    out.extend_from_slice(&format_field(if wide { "list32" } else { "list" }));
    out.extend_from_slice(&count_i32(indices.len(), "indices"));
    out.extend_from_slice(&count_i32(groups.len(), "primitive groups"));
    for &i in indices {
        if wide {
            out.extend_from_slice(&i.to_le_bytes());
        } else {
            out.extend_from_slice(&(i as u16).to_le_bytes());
        }
    }
    for g in groups {
        for v in [g.start_index, g.n_primitives, g.start_vertex, g.n_vertices] {
            out.extend_from_slice(&count_i32(v as usize, "(primitive group field)"));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::Location;
    use proptest::prelude::*;

    fn name64(name: &[u8]) -> Vec<u8> {
        let mut f = name.to_vec();
        f.resize(FORMAT_LEN, 0);
        f
    }

    /// A vertex section of `positions` in a format of `stride` bytes, the
    /// bytes after each position filled with 0xAB so a wrong stride shows.
    fn vertex_section(format: &[u8], stride: usize, positions: &[[f32; 3]]) -> Vec<u8> {
        let mut f = name64(format);
        f.extend_from_slice(&(positions.len() as i32).to_le_bytes());
        for p in positions {
            for c in p {
                f.extend_from_slice(&c.to_le_bytes());
            }
            f.extend(std::iter::repeat_n(0xAB, stride - 12));
        }
        f
    }

    const SAMPLE: [[f32; 3]; 3] = [[1.0, 2.0, 3.0], [-4.5, 0.25, 6.0], [7.0, -8.0, 9.5]];

    fn err(r: Result<impl std::fmt::Debug, FormatError>) -> (u64, String) {
        match r {
            Err(FormatError {
                at: Location::Byte(b),
                message,
            }) => (b, message),
            other => panic!("expected a byte-located error, got {other:?}"),
        }
    }

    #[test]
    fn every_source_format_stride() {
        let expected = [
            ("xyznuv", 32),
            ("xyznuvtb", 32),
            ("xyznduv", 36),
            ("xyznuvi", 36),
            ("xyznuvitb", 36),
            ("xyznuv2tb", 40),
            ("xyznuviiiww", 29),
            ("xyznuviiiwwtb", 37),
        ];
        for (name, stride) in expected {
            let f = vertex_section(name.as_bytes(), stride, &SAMPLE);
            let v = read_vertices(&f).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(v.format, name);
            assert_eq!(v.positions, SAMPLE, "{name}");
        }
    }

    #[test]
    fn odd_stride_read_unaligned_from_an_odd_address() {
        // Slice starting at an odd address of a buffer: every f32 read is
        // unaligned, and stride 29 misaligns each following vertex again.
        let f = vertex_section(b"xyznuviiiww", 29, &SAMPLE);
        let mut shifted = vec![0u8];
        shifted.extend_from_slice(&f);
        assert_eq!(read_vertices(&shifted[1..]).unwrap().positions, SAMPLE);
    }

    #[test]
    fn name_compared_up_to_nul_and_lower_cased() {
        let mut f = vertex_section(b"XYZNuvTB\0garbage!", 32, &SAMPLE);
        f.extend_from_slice(&[1, 2, 3]); // trailing bytes are ignored
        let v = read_vertices(&f).unwrap();
        assert_eq!(v.format, "xyznuvtb");
        assert_eq!(v.positions, SAMPLE);
    }

    #[test]
    fn non_finite_positions_returned_as_stored() {
        let pts = [[f32::NAN, f32::INFINITY, f32::NEG_INFINITY]];
        let v = read_vertices(&vertex_section(b"xyznuv", 32, &pts)).unwrap();
        assert!(v.positions[0][0].is_nan());
        assert_eq!(v.positions[0][1], f32::INFINITY);
        assert_eq!(v.positions[0][2], f32::NEG_INFINITY);
    }

    fn processed_section(original: &[u8], disk: &[u8], stride: usize) -> Vec<u8> {
        let mut f = b"BPVT".to_vec();
        f.extend_from_slice(&name64(original));
        f.extend_from_slice(&vertex_section(disk, stride, &SAMPLE));
        f
    }

    #[test]
    fn processed_bpvt_prefix_both_set3_strides() {
        for stride in [28, 32] {
            let f = processed_section(b"xyznuvtb", b"set3/xyznuvtbpc", stride);
            assert_eq!(f.len(), PROCESSED_HEADER_LEN + 3 * stride);
            let v = read_vertices(&f).unwrap();
            assert_eq!(v.format, "set3/xyznuvtbpc");
            assert_eq!(v.positions, SAMPLE, "stride {stride}");
        }
        // The inner header may also name a source format.
        let f = processed_section(b"xyznuviiiwwtb", b"xyznuviiiwwtb", 37);
        assert_eq!(read_vertices(&f).unwrap().positions, SAMPLE);
    }

    #[test]
    fn processed_section_with_trailing_bytes_uses_the_engine_stride() {
        let mut f = processed_section(b"xyznuv", b"set3/xyznuvpc", 20);
        f.push(0);
        assert_eq!(read_vertices(&f).unwrap().positions, SAMPLE);
    }

    #[test]
    fn vertex_errors() {
        // Unknown format: names it and lists the known ones; at the header.
        let (at, msg) = err(read_vertices(&vertex_section(b"xyzw", 16, &SAMPLE)));
        assert_eq!(at, 0);
        assert!(
            msg.contains("`xyzw`") && msg.contains("xyznuviiiwwtb"),
            "{msg}"
        );
        let f = processed_section(b"xyznuv", b"set3/bogus", 20);
        assert_eq!(err(read_vertices(&f)).0, 68);
        // Count larger than the data: at the count field.
        let mut f = vertex_section(b"xyznuv", 32, &SAMPLE);
        f.truncate(f.len() - 1);
        let (at, msg) = err(read_vertices(&f));
        assert_eq!(at, 64);
        assert!(msg.contains("3 vertices"), "{msg}");
        f[64..68].copy_from_slice(&i32::MAX.to_le_bytes());
        assert_eq!(err(read_vertices(&f)).0, 64);
        // Negative count.
        f[64..68].copy_from_slice(&(-2i32).to_le_bytes());
        let (at, msg) = err(read_vertices(&f));
        assert_eq!(at, 64);
        assert!(msg.contains("negative"), "{msg}");
        // Truncated headers, plain and processed.
        assert_eq!(err(read_vertices(&name64(b"xyznuv"))).0, 0);
        let f = processed_section(b"xyznuv", b"set3/xyznuvpc", 20);
        let (_, msg) = err(read_vertices(&f[..100]));
        assert!(msg.contains("BPVT"), "{msg}");
        // A processed count too large for either stride: at its count field.
        let mut f = processed_section(b"xyznuv", b"set3/xyznuvpc", 20);
        f.truncate(f.len() - 1);
        assert_eq!(err(read_vertices(&f)).0, (4 + 64 + 64) as u64);
    }

    fn index_section(format: &[u8], size: usize, idx: &[u32], groups: &[[i32; 4]]) -> Vec<u8> {
        let mut f = name64(format);
        f.extend_from_slice(&(idx.len() as i32).to_le_bytes());
        f.extend_from_slice(&(groups.len() as i32).to_le_bytes());
        for &i in idx {
            f.extend_from_slice(&i.to_le_bytes()[..size]);
        }
        for g in groups {
            for v in g {
                f.extend_from_slice(&v.to_le_bytes());
            }
        }
        f
    }

    #[test]
    fn list_and_list32() {
        // 3 u16 indices: the group table follows at an unaligned offset.
        let f = index_section(b"list\0junk", 2, &[0, 1, 2], &[[0, 1, 0, 3]]);
        let ind = read_indices(&f).unwrap();
        assert_eq!(ind.format, "list");
        assert_eq!(ind.indices, [0, 1, 2]);
        assert_eq!(
            ind.groups,
            [PrimitiveGroup {
                start_index: 0,
                n_primitives: 1,
                start_vertex: 0,
                n_vertices: 3
            }]
        );
        let f = index_section(
            b"LIST32",
            4,
            &[70000, 1, 2, 3, 4, 5],
            &[[3, 1, 1, 5], [0, 1, 0, 70001]],
        );
        let ind = read_indices(&f).unwrap();
        assert_eq!(ind.format, "list32");
        assert_eq!(ind.indices, [70000, 1, 2, 3, 4, 5]);
        assert_eq!(ind.groups.len(), 2);
        assert_eq!(ind.groups[1].n_vertices, 70001);
        assert_eq!(group_triangles(&ind, 0, 6).unwrap(), &[3, 4, 5]);
    }

    #[test]
    fn index_errors() {
        let good = index_section(b"list", 2, &[0, 1, 2, 2, 1, 3], &[[0, 2, 0, 4]]);
        assert!(read_indices(&good).is_ok());
        // Unknown format.
        let (at, msg) = err(read_indices(&index_section(b"strip", 2, &[0], &[])));
        assert_eq!(at, 0);
        assert!(msg.contains("`strip`") && msg.contains("list32"), "{msg}");
        // Header truncated.
        assert_eq!(err(read_indices(&good[..70])).0, 0);
        // Negative counts.
        let mut f = good.clone();
        f[64..68].copy_from_slice(&(-1i32).to_le_bytes());
        assert_eq!(err(read_indices(&f)).0, 64);
        let mut f = good.clone();
        f[68..72].copy_from_slice(&(-1i32).to_le_bytes());
        assert_eq!(err(read_indices(&f)).0, 68);
        // Indices running past the end.
        let mut f = good.clone();
        f[64..68].copy_from_slice(&1000i32.to_le_bytes());
        let (at, msg) = err(read_indices(&f));
        assert_eq!(at, 64);
        assert!(msg.contains("1000 indices"), "{msg}");
        // Group table truncated by one byte.
        let (at, msg) = err(read_indices(&good[..good.len() - 1]));
        assert_eq!(at, 68);
        assert!(msg.contains("1 primitive groups"), "{msg}");
        // Huge group count must not overflow or allocate.
        let mut f = good.clone();
        f[68..72].copy_from_slice(&i32::MAX.to_le_bytes());
        assert_eq!(err(read_indices(&f)).0, 68);
        // Negative group field: at that field (table at 72 + 12).
        let mut f = good.clone();
        f[84 + 8..84 + 12].copy_from_slice(&(-5i32).to_le_bytes());
        let (at, msg) = err(read_indices(&f));
        assert_eq!(at, 92);
        assert!(msg.contains("startVertex"), "{msg}");
    }

    #[test]
    fn group_triangles_checks() {
        let f = index_section(
            b"list",
            2,
            &[0, 1, 2, 2, 1, 3, 9, 9, 9],
            &[[0, 1, 0, 3], [3, 1, 1, 3], [6, 1, 0, 10], [3, 3, 0, 4]],
        );
        let ind = read_indices(&f).unwrap();
        assert_eq!(group_triangles(&ind, 0, 4).unwrap(), &[0, 1, 2]);
        assert_eq!(group_triangles(&ind, 1, 4).unwrap(), &[2, 1, 3]);
        // Group not in the table: offset of the table (72 + 9 * 2).
        let (at, msg) = err(group_triangles(&ind, 4, 4));
        assert_eq!(at, 90);
        assert!(msg.contains("group 4") && msg.contains("4 group"), "{msg}");
        // Range past the index buffer: at the group's record.
        let (at, msg) = err(group_triangles(&ind, 3, 10));
        assert_eq!(at, 90 + 3 * 16);
        assert!(msg.contains("group 3"), "{msg}");
        // Index >= vertex count: names the group, the position and value,
        // and points at the index (72 + 6 * 2).
        let (at, msg) = err(group_triangles(&ind, 2, 4));
        assert_eq!(at, 84);
        assert!(
            msg.contains("group 2") && msg.contains("index 6 is 9") && msg.contains("4 vertices"),
            "{msg}"
        );
        assert!(group_triangles(&ind, 2, 10).is_ok());
        // A group whose count overflows usize arithmetic.
        let mut huge = ind.clone();
        huge.groups[0].start_index = u32::MAX;
        huge.groups[0].n_primitives = u32::MAX;
        assert!(group_triangles(&huge, 0, 4).is_err());
    }

    #[test]
    fn writers_layout() {
        let v = write_vertices(&[[1.0, 2.0, 3.0]], &[[0.0, 1.0, 0.0]]);
        assert_eq!(v.len(), 68 + 32);
        assert_eq!(&v[..7], b"xyznuv\0");
        assert_eq!(&v[64..68], &1i32.to_le_bytes());
        assert_eq!(&v[68 + 16..68 + 20], &1.0f32.to_le_bytes()); // normal y
        assert_eq!(&v[68 + 24..], &[0; 8]); // uv
        let i = write_indices(&[0, 1, 65535], &[]);
        assert_eq!(&i[..5], b"list\0");
        assert_eq!(i.len(), 72 + 6);
        let i = write_indices(&[0, 1, 65536], &[]);
        assert_eq!(&i[..7], b"list32\0");
        assert_eq!(i.len(), 72 + 12);
    }

    fn finite() -> impl Strategy<Value = f32> {
        -1.0e6f32..1.0e6
    }

    proptest! {
        #[test]
        fn vertices_round_trip(
            pts in proptest::collection::vec([finite(), finite(), finite()], 0..20)
        ) {
            let normals = vec![[0.0, 1.0, 0.0]; pts.len()];
            let bytes = write_vertices(&pts, &normals);
            prop_assert_eq!(&bytes, &write_vertices(&pts, &normals));
            let v = read_vertices(&bytes).unwrap();
            prop_assert_eq!(v.format, "xyznuv");
            prop_assert_eq!(v.positions, pts);
        }

        #[test]
        fn indices_round_trip(
            idx in proptest::collection::vec(0u32..200_000, 0..30),
            raw_groups in proptest::collection::vec(
                (0u32..1000, 0u32..1000, 0u32..1000, 0u32..1000), 0..5),
        ) {
            let groups: Vec<PrimitiveGroup> = raw_groups
                .iter()
                .map(|&(a, b, c, d)| PrimitiveGroup {
                    start_index: a, n_primitives: b, start_vertex: c, n_vertices: d,
                })
                .collect();
            let bytes = write_indices(&idx, &groups);
            prop_assert_eq!(&bytes, &write_indices(&idx, &groups));
            let ind = read_indices(&bytes).unwrap();
            let wide = idx.iter().any(|&i| i > 65535);
            prop_assert_eq!(ind.format, if wide { "list32" } else { "list" });
            prop_assert_eq!(ind.indices, idx);
            prop_assert_eq!(ind.groups, groups);
        }

        #[test]
        fn arbitrary_sections_never_panic(
            bytes in proptest::collection::vec(any::<u8>(), 0..200),
            header in prop_oneof![
                Just(&b"xyznuviiiww"[..]), Just(&b"list"[..]), Just(&b"list32"[..]),
                Just(&b"BPVT"[..])],
        ) {
            let mut f = name64(header);
            f.extend_from_slice(&bytes);
            let _ = read_vertices(&f);
            if let Ok(ind) = read_indices(&f) {
                for g in 0..=ind.groups.len() {
                    let _ = group_triangles(&ind, g, 10);
                }
            }
        }
    }
}

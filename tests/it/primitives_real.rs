//! The BinSection and `.primitives` decoders against the engine's own
//! `.primitives` files (realdata/bigworld-14.4.1): every section decodes,
//! agrees with its own header, and every primitive group is usable; then
//! the same files, truncated and bit-flipped, must give errors, not panics.

use crate::support::realdata;
use shadowcull::error::FormatError;
use shadowcull::formats::{binsection, primitives};
use shadowcull::rng::Rng;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};

fn primitives_files(root: &Path) -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        let mut entries: Vec<_> = std::fs::read_dir(dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.unwrap().path())
            .collect();
        entries.sort();
        for p in entries {
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|e| e == "primitives") {
                out.push(p);
            }
        }
    }
    let mut out = Vec::new();
    walk(&root.join("bigworld-14.4.1/res"), &mut out);
    out
}

fn header_i32(section: &[u8], at: usize) -> i32 {
    i32::from_le_bytes(section[at..at + 4].try_into().unwrap())
}

fn is_vertices(name: &str) -> bool {
    name.ends_with("vertices") && !name.ends_with("mvertices")
}

/// The vertex section that goes with an indices section, by the naming the
/// engine's exporters use (`indices`/`vertices`, `X.indices`/`X.vertices`).
/// Morphed meshes (the ranger character) have only `X.mvertices`, which the
/// `.visual` names as its vertices: a plain vertex section followed by morph
/// targets, so `read_vertices` reads its base pose.
fn vertices_for<'a>(
    bin: &binsection::BinSection<'a>,
    indices_name: &str,
) -> Option<(&'a [u8], usize)> {
    let stem = indices_name.trim_end_matches("indices");
    bin.get(&format!("{stem}vertices"))
        .or_else(|| bin.get(&format!("{stem}mvertices")))
}

/// What a full decode of one file found.
#[derive(Default)]
struct Decoded {
    vertex_sections: usize,
    index_sections: usize,
    groups: usize,
    triangles: usize,
}

/// Decodes the container, every vertices and indices section, and every
/// group of every indices section against its vertices section; errors are
/// shifted to file offsets.
fn decode_all(bytes: &[u8]) -> Result<Decoded, FormatError> {
    let bin = binsection::parse(bytes)?;
    let mut out = Decoded::default();
    for entry in &bin.entries {
        let (data, at) = bin.get(&entry.name).unwrap();
        if is_vertices(&entry.name) {
            primitives::read_vertices(data).map_err(|e| e.shifted(at))?;
            out.vertex_sections += 1;
        } else if entry.name.ends_with("indices") {
            let ind = primitives::read_indices(data).map_err(|e| e.shifted(at))?;
            out.index_sections += 1;
            let vertex_count = match vertices_for(&bin, &entry.name) {
                Some((vdata, vat)) => primitives::read_vertices(vdata)
                    .map_err(|e| e.shifted(vat))?
                    .positions
                    .len(),
                None => usize::MAX,
            };
            for g in 0..ind.groups.len() {
                let tris = primitives::group_triangles(&ind, g, vertex_count)
                    .map_err(|e| e.shifted(at))?;
                out.groups += 1;
                out.triangles += tris.len() / 3;
            }
        }
    }
    Ok(out)
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn real_primitives_decode_and_agree_with_their_headers() {
    let Some(root) = realdata("real_primitives_decode_and_agree_with_their_headers") else {
        return;
    };
    let files = primitives_files(&root);
    // README: 27 models with .primitives; a few LODs share files, so
    // expect at least 20 rather than an exact count.
    assert!(
        files.len() >= 20,
        "only {} .primitives files found",
        files.len()
    );
    for path in &files {
        let show = path.strip_prefix(&root).unwrap().display().to_string();
        let bytes = std::fs::read(path).unwrap();
        let bin = binsection::parse(&bytes).unwrap_or_else(|e| panic!("{show}: {e}"));
        assert!(bin.has_magic(), "{show}: 14.4.1 files carry the magic");

        // The entries tile the data area in order, each padded to 4 bytes,
        // and the last one ends where the index starts.
        let index_len = header_i32(&bytes, bytes.len() - 4) as usize;
        let index_start = bytes.len() - 4 - index_len;
        let mut expect = 4;
        for e in &bin.entries {
            assert_eq!(e.data.start, expect, "{show}: `{}` start", e.name);
            expect = (e.data.end + 3) & !3;
        }
        assert_eq!(expect, index_start, "{show}: data area end");

        let mut n_vertex_sections = 0;
        let mut n_index_sections = 0;
        for e in &bin.entries {
            let (data, at) = bin.get(&e.name).unwrap();
            // `.mvertices` (morph) sections start with a plain vertex
            // section and are what the ranger's `.visual` uses, so their
            // base pose is checked the same way.
            if is_vertices(&e.name) || e.name.ends_with("mvertices") {
                let v = primitives::read_vertices(data)
                    .map_err(|err| err.shifted(at))
                    .unwrap_or_else(|err| panic!("{show}: `{}`: {err}", e.name));
                assert!(
                    !data.starts_with(b"BPVT"),
                    "{show}: README lists source formats only"
                );
                assert!(
                    ["xyznuv", "xyznuvtb", "xyznuviiiwwtb"].contains(&v.format.as_str()),
                    "{show}: `{}` has format {}",
                    e.name,
                    v.format
                );
                assert_eq!(v.positions.len() as i32, header_i32(data, 64), "{show}");
                if e.name.ends_with("mvertices") {
                    // Morph targets follow the base vertices.
                    let stride = if v.format == "xyznuviiiwwtb" { 37 } else { 32 };
                    assert!(data.len() > 68 + stride * v.positions.len(), "{show}");
                } else {
                    n_vertex_sections += 1;
                }
                // A wrong stride reads normals, uvs or weights as positions;
                // exported meshes have finite, modest coordinates.
                for p in &v.positions {
                    assert!(
                        p.iter().all(|c| c.is_finite() && c.abs() < 1.0e4),
                        "{show}: `{}` position {p:?}",
                        e.name
                    );
                }
            } else if e.name.ends_with("indices") {
                let ind = primitives::read_indices(data)
                    .map_err(|err| err.shifted(at))
                    .unwrap_or_else(|err| panic!("{show}: `{}`: {err}", e.name));
                n_index_sections += 1;
                assert_eq!(ind.format, "list", "{show}: README says u16 indices");
                assert_eq!(ind.indices.len() as i32, header_i32(data, 64), "{show}");
                assert_eq!(ind.groups.len() as i32, header_i32(data, 68), "{show}");
                assert!(!ind.groups.is_empty(), "{show}: `{}` has no groups", e.name);

                let (vdata, _) = vertices_for(&bin, &e.name)
                    .unwrap_or_else(|| panic!("{show}: `{}` has no vertex section", e.name));
                let vertex_count = primitives::read_vertices(vdata)
                    .unwrap_or_else(|err| panic!("{show}: vertices of `{}`: {err}", e.name))
                    .positions
                    .len();
                let mut used = 0usize;
                for (g, group) in ind.groups.iter().enumerate() {
                    let tris = primitives::group_triangles(&ind, g, vertex_count)
                        .unwrap_or_else(|err| panic!("{show}: `{}` group {g}: {err}", e.name));
                    assert_eq!(tris.len(), 3 * group.n_primitives as usize);
                    // Indices are absolute and stay inside the group's own
                    // vertex range, which is what makes startIndex/startVertex
                    // readable as "indices" and "vertices" (base vertex 0).
                    let lo = group.start_vertex;
                    let hi = group.start_vertex + group.n_vertices;
                    assert!(
                        tris.iter().all(|&i| (lo..hi).contains(&i)),
                        "{show}: `{}` group {g} leaves its vertex range {lo}..{hi}",
                        e.name
                    );
                    used += tris.len();
                }
                assert!(
                    used <= ind.indices.len(),
                    "{show}: groups use {used} indices of {}",
                    ind.indices.len()
                );
            }
        }
        let morphed = show.contains("ranger");
        assert_eq!(
            n_vertex_sections > 0,
            !morphed,
            "{show}: only the ranger meshes lack plain vertex sections"
        );
        assert!(n_index_sections > 0, "{show}: no indices section");
        let whole = decode_all(&bytes).unwrap_or_else(|e| panic!("{show}: {e}"));
        assert_eq!(whole.index_sections, n_index_sections);
        assert!(whole.triangles > 0, "{show}: no triangles");
    }
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn damaged_real_primitives_give_errors_not_panics() {
    let Some(root) = realdata("damaged_real_primitives_give_errors_not_panics") else {
        return;
    };
    let mut failures = Vec::new();
    let mut errors = 0usize;
    let mut runs = 0usize;
    let mut check = |label: String, bytes: &[u8]| {
        runs += 1;
        match catch_unwind(AssertUnwindSafe(|| decode_all(bytes))) {
            Ok(Ok(_)) => {}
            Ok(Err(_)) => errors += 1,
            Err(_) => failures.push(label),
        }
    };
    let files = primitives_files(&root);
    assert!(!files.is_empty());
    for (file_no, path) in files.iter().enumerate() {
        let show = path.strip_prefix(&root).unwrap().display().to_string();
        let mut bytes = std::fs::read(path).unwrap();
        let len = bytes.len();

        // Truncations: every 64th of the file, then the last 16 bytes one
        // at a time (they hold the end of the index and its length).
        for k in 0..64 {
            let cut = len * k / 64;
            check(format!("{show} truncated to {cut}"), &bytes[..cut]);
        }
        for cut in len.saturating_sub(16)..len {
            check(format!("{show} truncated to {cut}"), &bytes[..cut]);
        }

        // Regions where a flip changes a length or count rather than a
        // coordinate: the index table and every section's header and, for
        // index sections, the group table.
        let bin = binsection::parse(&bytes).unwrap();
        let index_len = header_i32(&bytes, len - 4) as usize;
        let mut hot: Vec<std::ops::Range<usize>> = Vec::new();
        hot.push(len - 4 - index_len..len);
        for e in &bin.entries {
            hot.push(e.data.start..(e.data.start + 72).min(e.data.end));
            if e.name.ends_with("indices") {
                let (data, _) = bin.get(&e.name).unwrap();
                let ind = primitives::read_indices(data).unwrap();
                let groups_at = e.data.start + 72 + 2 * ind.indices.len();
                hot.push(groups_at..e.data.end);
            }
        }

        let mut rng = Rng::new(0x9E37_79B9_7F4A_7C15 ^ (file_no as u64 + 1));
        for flip in 0..200 {
            let at = if flip % 2 == 0 {
                rng.below(len)
            } else {
                let r = &hot[rng.below(hot.len())];
                r.start + rng.below(r.len())
            };
            let bit = 1u8 << rng.below(8);
            bytes[at] ^= bit;
            check(
                format!("{show} bit {bit:#04x} flipped at byte {at}"),
                &bytes,
            );
            bytes[at] ^= bit;
        }
    }
    eprintln!("damaged .primitives: {runs} decodes, {errors} errors, no panics expected");
    assert!(
        failures.is_empty(),
        "{} of {runs} damaged inputs panicked:\n{}",
        failures.len(),
        failures.join("\n")
    );
    // The damage must actually be detected somewhere, or the test proves
    // nothing about the error paths.
    assert!(
        errors > runs / 4,
        "only {errors} of {runs} damaged inputs gave errors"
    );
}

//! Terrain readers against the engine's own `blank.cdata`, and robustness of
//! the readers against truncated and bit-flipped files (Ok or Err, never a
//! panic).

use std::io::{Cursor, Read};
use std::panic::{catch_unwind, AssertUnwindSafe};

use glam::DVec3;
use shadowcull::formats::terrain::{
    decode_heights, decode_holes, read_terrain, write_terrain2_cdata, HeightMap, HoleMap,
    TerrainVersion,
};
use shadowcull::rng::Rng;
use shadowcull::scene::terrain::TerrainBlock;

use crate::support::realdata;

fn blank_cdata(test: &str) -> Option<Vec<u8>> {
    let dir = realdata(test)?;
    let path = dir.join("bigworld-14.4.1/res/terrain/blank.cdata");
    Some(std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
}

/// An entry's bytes, read with the zip crate directly (not through the
/// reader under test).
fn zip_entry(cdata: &[u8], name: &str) -> Vec<u8> {
    let mut archive = zip::ZipArchive::new(Cursor::new(cdata)).unwrap();
    let mut out = Vec::new();
    archive
        .by_name(name)
        .unwrap()
        .read_to_end(&mut out)
        .unwrap();
    out
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn blank_cdata_is_a_flat_block_of_its_header_size() {
    let Some(cdata) = blank_cdata("blank_cdata_is_a_flat_block_of_its_header_size") else {
        return;
    };
    let entry = zip_entry(&cdata, "terrain2/heights");
    // The file's own header: 'hmp\0', w, h, compression, version 4, min, max.
    assert_eq!(&entry[..4], b"hmp\0");
    let (w, h) = (u32_at(&entry, 4) as usize, u32_at(&entry, 8) as usize);
    assert_eq!(u32_at(&entry, 16), 4);
    let (min, max) = (
        f32::from_bits(u32_at(&entry, 20)),
        f32::from_bits(u32_at(&entry, 24)),
    );
    assert_eq!(
        (min, max),
        (0.0, 0.0),
        "the header says the block is flat at 0"
    );

    let t = read_terrain(&cdata, "terrain2").unwrap();
    assert_eq!(t.version, TerrainVersion::Terrain2);
    assert_eq!(t.border, 2);
    assert_eq!((t.heights.width, t.heights.height), (w, h));
    assert_eq!(t.heights.heights.len(), w * h);
    assert!(t.heights.heights.iter().all(|&v| v == 0.0));
    assert_eq!(t.holes, None, "blank.cdata has no terrain2/holes entry");

    // heightMapSize 128 + 1 + 4 border samples.
    let b = TerrainBlock::new(&t, DVec3::new(-100.0, 3.0, 200.0), 100.0).unwrap();
    assert_eq!(b.cells(), (w - 5, h - 5));
    assert_eq!(
        b.spacing(),
        (100.0 / (w - 5) as f64, 100.0 / (h - 5) as f64)
    );
    assert_eq!(b.height_at(-50.0, 250.0), Some(3.0));
    assert_eq!(b.height_at(-100.0, 300.0), Some(3.0));
    assert_eq!(b.height_at(-100.5, 250.0), None);
    assert_eq!(b.triangles().len(), 2 * (w - 5) * (h - 5));
    assert_eq!(
        b.bounds(),
        (DVec3::new(-100.0, 3.0, 200.0), DVec3::new(0.0, 3.0, 300.0))
    );

    // Its LOD entries are the same format without border; the decoder reads
    // them too, and they are flat as well.
    let lod = decode_heights(&zip_entry(&cdata, "terrain2/heights1")).unwrap();
    assert_eq!((lod.width, lod.height), (65, 65));
    assert!(lod.heights.iter().all(|&v| v == 0.0));
}

/// Runs `f` and turns a panic into a test failure naming the case.
fn no_panic<T>(case: &str, f: impl FnOnce() -> T) -> T {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(v) => v,
        Err(_) => panic!("reader panicked on {case}"),
    }
}

/// Truncations at every `step`-th offset plus every offset near both ends,
/// then `flips` seeded single-bit flips anywhere and `hot_flips` more inside
/// the `hot` byte ranges `[from, to)` (headers). `read` returns whether the bytes were
/// accepted; returns (accepted, refused) counts.
#[allow(clippy::too_many_arguments)]
fn torture(
    name: &str,
    bytes: &[u8],
    step: usize,
    flips: usize,
    hot: &[(usize, usize)],
    hot_flips: usize,
    seed: u64,
    read: impl Fn(&[u8]) -> bool,
) -> (usize, usize) {
    let n = bytes.len();
    let (mut accepted, mut refused) = (0, 0);
    let mut count = |ok: bool| {
        if ok {
            accepted += 1
        } else {
            refused += 1
        }
    };
    let mut cuts: Vec<usize> = (0..n).step_by(step).collect();
    cuts.extend(0..n.min(64));
    cuts.extend(n.saturating_sub(64)..n);
    for cut in cuts {
        count(no_panic(
            &format!("{name} truncated to {cut} bytes"),
            || read(&bytes[..cut]),
        ));
    }
    let mut rng = Rng::new(seed);
    let mut offsets: Vec<(usize, u8)> = (0..flips)
        .map(|_| (rng.below(n), rng.below(8) as u8))
        .collect();
    let hot: Vec<usize> = hot
        .iter()
        .flat_map(|&(from, to)| from..to)
        .filter(|&at| at < n)
        .collect();
    if !hot.is_empty() {
        for _ in 0..hot_flips {
            offsets.push((hot[rng.below(hot.len())], rng.below(8) as u8));
        }
    }
    let mut buf = bytes.to_vec();
    for (at, bit) in offsets {
        buf[at] ^= 1 << bit;
        count(no_panic(
            &format!("{name} with bit {bit} of byte {at} flipped"),
            || read(&buf),
        ));
        buf[at] ^= 1 << bit;
    }
    (accepted, refused)
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn damaged_blank_cdata_never_panics() {
    let Some(cdata) = blank_cdata("damaged_blank_cdata_never_panics") else {
        return;
    };
    // ZIP level: local headers, central directory and end record live in the
    // first bytes, around each entry and at the end.
    let eocd = cdata.len() - 22;
    let central = u32_at(&cdata, eocd + 16) as usize;
    let (_, refused) = torture(
        "blank.cdata",
        &cdata,
        97,
        200,
        &[(0, 64), (central, central + 96), (eocd, cdata.len())],
        200,
        0x5EED_0001,
        |b| read_terrain(b, "terrain2").is_ok(),
    );
    assert!(
        refused > 100,
        "damage went unnoticed: only {refused} refusals"
    );
    // Inside the heights entry (the ZIP's CRC would catch these first): the
    // hmp header, the "gnpq" tag and the PNG's signature and IHDR.
    let entry = zip_entry(&cdata, "terrain2/heights");
    let (accepted, refused) = torture(
        "terrain2/heights",
        &entry,
        3,
        300,
        &[(0, 36 + 33)],
        200,
        0x5EED_0002,
        |b| decode_heights(b).is_ok(),
    );
    assert!(
        accepted > 0 && refused > 100,
        "{accepted} accepted, {refused} refused"
    );
}

#[test]
fn damaged_written_block_with_holes_never_panics() {
    let w = 133;
    let heights = HeightMap {
        width: w,
        height: w,
        heights: (0..w * w)
            .map(|i| ((i * 7919) % 40_000) as f32 * 0.001 - 20.0)
            .collect(),
    };
    let holes = HoleMap {
        width: 25,
        height: 25,
        holes: (0..625).map(|i| i % 7 == 3).collect(),
    };
    let cdata = write_terrain2_cdata(&heights, Some(&holes));
    let t = read_terrain(&cdata, "terrain2").unwrap();
    assert_eq!(t.heights.heights.len(), w * w);
    assert_eq!(t.holes.as_ref(), Some(&holes));
    TerrainBlock::new(&t, DVec3::ZERO, 100.0).unwrap();

    let (_, refused) = torture(
        "written .cdata",
        &cdata,
        700,
        200,
        &[(0, 80)],
        150,
        0x5EED_0003,
        |b| match read_terrain(b, "terrain2") {
            // Whatever survives must still build a block or refuse cleanly.
            Ok(t) => TerrainBlock::new(&t, DVec3::ZERO, 100.0).is_ok(),
            Err(_) => false,
        },
    );
    assert!(
        refused > 100,
        "damage went unnoticed: only {refused} refusals"
    );
    let holes_entry = zip_entry(&cdata, "terrain2/holes");
    let (accepted, refused) = torture(
        "terrain2/holes",
        &holes_entry,
        1,
        300,
        &[(0, 16)],
        200,
        0x5EED_0004,
        |b| decode_holes(b).is_ok(),
    );
    assert!(
        accepted > 0 && refused > 50,
        "{accepted} accepted, {refused} refused"
    );
}

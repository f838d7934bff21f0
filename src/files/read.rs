//! Reads of whole files: regular files only (checked before opening and
//! again on the open handle, opened without blocking so a FIFO cannot
//! hang the run), each kind of file with a size cap.

use crate::error::{Error, Result};
use std::fs::{self, File, Metadata};
use std::io::Read;
use std::path::Path;

const MIB: u64 = 1 << 20;
const GIB: u64 = 1 << 30;

/// The most bytes read from one file, by the end of its name: the one place
/// the caps are defined. The engine's XML files (chunks, models, visuals,
/// materials, settings) are kilobytes to a few megabytes; `.primitives` and
/// `.cdata` hold geometry and terrain and can reach hundreds of megabytes.
pub const SIZE_CAPS: &[(&str, u64)] = &[
    (".chunk", 64 * MIB),
    (".model", 64 * MIB),
    (".visual", 64 * MIB),
    (".mfm", 64 * MIB),
    (".settings", 64 * MIB),
    (".primitives", GIB),
    (".cdata", GIB),
    // A distributed bake's partial result: caster bitsets of a huge world.
    (".part", GIB),
];

/// The cap of any other file (the bake settings file, a `--out` target).
pub const DEFAULT_SIZE_CAP: u64 = 64 * MIB;

/// The size cap of `path`, and the kind of file it is the cap of.
pub fn size_cap(path: &Path) -> (u64, String) {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    SIZE_CAPS
        .iter()
        .find(|(suffix, _)| name.ends_with(suffix))
        .map(|&(suffix, cap)| (cap, format!("{suffix} files")))
        .unwrap_or((DEFAULT_SIZE_CAP, "files of this kind".into()))
}

/// What a file that is not a regular file is, in words.
pub(super) fn kind_of(meta: &Metadata) -> &'static str {
    let kind = meta.file_type();
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if kind.is_fifo() {
            return "a FIFO (named pipe)";
        }
        if kind.is_char_device() {
            return "a character device";
        }
        if kind.is_block_device() {
            return "a block device";
        }
        if kind.is_socket() {
            return "a socket";
        }
    }
    if kind.is_dir() {
        "a folder"
    } else if kind.is_file() {
        "a regular file"
    } else {
        "a special file"
    }
}

pub(super) fn not_regular(path: &Path, meta: &Metadata) -> Error {
    let through_link = fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink());
    Error::invalid(
        path,
        format!(
            "is {}{}, not a regular file; only regular files are read (a pipe or device can block or never end): put the file itself there",
            kind_of(meta),
            if through_link {
                " (through a symbolic link)"
            } else {
                ""
            }
        ),
    )
}

fn too_large(path: &Path, cap: u64, kind: &str, size: Option<u64>) -> Error {
    Error::invalid(
        path,
        format!(
            "{} the cap of {} MiB for {kind}; no BigWorld file of this kind is that large: check the file",
            match size {
                Some(size) => format!("holds {size} bytes, more than"),
                None => "grew past".to_string(),
            },
            cap / MIB
        ),
    )
}

/// Opens for reading without blocking: with `O_NONBLOCK`, a FIFO swapped in
/// after the metadata check opens at once (and is then refused) instead of
/// waiting for a writer.
fn open_for_reading(path: &Path) -> std::io::Result<File> {
    let mut options = fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    options.open(path)
}

/// At most `cap + 1` bytes of `reader`: one more than the cap tells a file
/// that grew past it from one that fits exactly.
fn read_at_most(reader: impl Read, cap: u64, size_hint: u64) -> std::io::Result<Vec<u8>> {
    let mut bytes = Vec::with_capacity(size_hint.min(cap) as usize);
    reader.take(cap + 1).read_to_end(&mut bytes)?;
    Ok(bytes)
}

/// The total and the largest size of the files at `paths` (those that
/// cannot be looked at count nothing).
pub fn file_sizes<'a>(paths: impl Iterator<Item = &'a Path>) -> FileSizes {
    let sizes = paths
        .filter_map(|p| std::fs::metadata(p).ok())
        .map(|m| m.len());
    sizes.fold(FileSizes::default(), |sizes, len| FileSizes {
        total: sizes.total + len,
        largest: sizes.largest.max(len),
    })
}

/// What [`file_sizes`] found.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FileSizes {
    pub total: u64,
    pub largest: u64,
}

/// Reads a whole regular file (following symbolic links), refusing FIFOs,
/// devices and folders before opening them and files larger than the cap
/// of their kind ([`SIZE_CAPS`]).
pub fn read_file(path: &Path) -> Result<Vec<u8>> {
    let (cap, kind) = size_cap(path);
    read_file_capped(path, cap, &kind)
}

/// The most bytes read from a bake report (`--report` JSON, pretty-printed):
/// a world of thousands of chunks lists millions of group masks.
pub const REPORT_SIZE_CAP: u64 = 4 * GIB;

/// [`read_file`] for a bake report, whatever its name: its own cap.
pub fn read_report_bytes(path: &Path) -> Result<Vec<u8>> {
    read_file_capped(path, REPORT_SIZE_CAP, "bake reports")
}

/// [`read_file`] with the cap `cap` of files of the kind `kind` (words).
fn read_file_capped(path: &Path, cap: u64, kind: &str) -> Result<Vec<u8>> {
    let meta = fs::metadata(path).map_err(|e| Error::io(path, "read", e))?;
    if !meta.is_file() {
        return Err(not_regular(path, &meta));
    }
    let file = open_for_reading(path).map_err(|e| Error::io(path, "read", e))?;
    // The entry may have changed since the check: ask the open handle.
    let meta = file.metadata().map_err(|e| Error::io(path, "read", e))?;
    if !meta.is_file() {
        return Err(not_regular(path, &meta));
    }
    if meta.len() > cap {
        return Err(too_large(path, cap, kind, Some(meta.len())));
    }
    let bytes = read_at_most(file, cap, meta.len()).map_err(|e| Error::io(path, "read", e))?;
    if bytes.len() as u64 > cap {
        return Err(too_large(path, cap, kind, None));
    }
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_stop_one_byte_past_the_cap() {
        let endless = std::io::repeat(7);
        assert_eq!(read_at_most(endless, 10, 1 << 40).unwrap().len(), 11);
        assert_eq!(read_at_most(&b"abc"[..], 10, 3).unwrap(), b"abc");
    }

    #[test]
    fn caps_are_per_kind_of_file() {
        assert_eq!(size_cap(Path::new("a/b.chunk")).0, 64 * MIB);
        assert_eq!(size_cap(Path::new("b.PRIMITIVES")).0, GIB);
        assert_eq!(size_cap(Path::new("x.cdata")).0, GIB);
        assert_eq!(size_cap(Path::new("bake.xml")).0, DEFAULT_SIZE_CAP);
        // A sparse file one byte over the cap is refused without reading.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.chunk");
        File::create(&path).unwrap().set_len(64 * MIB + 1).unwrap();
        let message = read_file(&path).unwrap_err().to_string();
        assert!(
            message.contains("big.chunk") && message.contains("cap of 64 MiB for .chunk files"),
            "{message}"
        );
    }

    #[test]
    fn folders_are_not_read() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("x.chunk")).unwrap();
        let message = read_file(&dir.path().join("x.chunk"))
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("is a folder, not a regular file"),
            "{message}"
        );
    }
}

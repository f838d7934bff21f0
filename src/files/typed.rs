//! Whole files of one kind read into values or written from them: the
//! bytes come from the capped read and go to the atomic write, the values
//! from `formats`.

use super::{read_file, write_atomic};
use crate::error::{Error, Result};
use crate::formats::bake_settings::{self, BakeSettings};
use crate::formats::partial::{self, Partial};
use crate::formats::png_write;
use std::path::Path;

/// Reads and validates a bake settings file; relative paths in it are taken
/// relative to the file's folder.
pub fn read_bake_settings(path: &Path) -> Result<BakeSettings> {
    let bytes = read_file(path)?;
    bake_settings::from_bytes(&bytes, path)
}

/// Reads and checks the partial at `path`; every error names it.
pub fn read_partial(path: &Path) -> Result<Partial> {
    let bytes = read_file(path)?;
    partial::decode(&bytes).map_err(|e| e.in_file(path))
}

/// Writes `partial` to `path` atomically.
pub fn write_partial(path: &Path, partial: &Partial) -> Result<()> {
    write_atomic(path, &partial::encode(partial))
}

/// Encodes an 8-bit RGB picture as PNG and writes `path` atomically.
pub fn write_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<()> {
    let bytes = png_write::encode_rgb(width, height, rgb)
        .map_err(|message| Error::invalid(path, message))?;
    write_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unwritable_png_path_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("a-file");
        std::fs::write(&file, b"x").unwrap();
        let target = file.join("out.png");
        let message = write_png(&target, 1, 1, &[1, 2, 3])
            .unwrap_err()
            .to_string();
        assert!(message.contains("a-file"), "{message}");
    }
}

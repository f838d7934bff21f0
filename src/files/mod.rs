//! Every access to the file system, so that `formats` turns bytes into
//! values and back and the rest of the crate works on values: res-path
//! lookup, capped reads of regular files, folder walks, batch writes that
//! never leave a torn file (with the sweep of a killed run's temporary
//! files), and what the system says about processes.

mod process;
mod read;
mod replaceable;
mod res_paths;
mod temporaries;
mod typed;
mod walk;
mod write;

pub use process::{host_name, resident_memory, ResidentMemory};
pub use read::{read_file, size_cap, total_size, DEFAULT_SIZE_CAP, SIZE_CAPS};
pub use replaceable::check_replaceable;
pub use res_paths::{in_folder_or_bare, normalise, stays_inside, ResPaths};
pub use temporaries::STALE_TEMPORARY_AGE;
pub use typed::{read_bake_settings, read_partial, write_partial, write_png};
pub use walk::{find_files, find_files_in, walk, Walk};
pub use write::{write_atomic, write_files, write_files_beside, write_tree};

use std::path::{Path, PathBuf};

/// The folder `path` lies in (`.` for a bare name).
fn folder_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Names in `dir`, sorted.
#[cfg(test)]
fn names(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

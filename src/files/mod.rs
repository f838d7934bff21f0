//! Every access to the file system, so that `formats` turns bytes into
//! values and back and the rest of the crate works on values: res-path
//! lookup, capped reads of regular files, folder walks, batch writes that
//! never leave a torn file (with the sweep of a killed run's temporary
//! files), and what the system says about processes.

mod cache_dir;
mod process;
mod read;
mod replaceable;
mod res_paths;
mod stamp;
mod temporaries;
mod typed;
mod walk;
mod write;

pub use cache_dir::{
    cache_entry_exists, list_cache_files, read_cache_entry, remove_cache_file,
    remove_empty_cache_folders, touch_cache_entry, write_cache_entry, CacheFile, CACHE_ENTRY_CAP,
};
pub use process::{
    host_name, own_executable_stamp, read_own_executable, resident_memory, Invocation,
    ResidentMemory,
};
pub use read::{
    file_sizes, read_file, read_report_bytes, size_cap, FileSizes, DEFAULT_SIZE_CAP,
    REPORT_SIZE_CAP, SIZE_CAPS,
};
pub use replaceable::check_replaceable;
pub use res_paths::{in_folder_or_bare, normalise, normalised, stays_inside, ResPaths};
pub use stamp::{exists, folder_names, is_folder, stamp, Stamp};
pub use temporaries::STALE_TEMPORARY_AGE;
pub use typed::{read_bake_settings, read_partial, write_partial, write_png};
pub use walk::{find_files, find_files_in, walk, Walk};
pub use write::{
    commit_staged, stage, write_atomic, write_atomic_streamed, write_files, write_files_beside,
    write_tree, Staged, Staging,
};

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

#[cfg(test)]
mod tests {
    use super::*;

    /// How this crate's code reaches the file system.
    const FILE_SYSTEM_CALLS: &[&str] = &[
        "std::fs",
        "fs::",
        "File::",
        "OpenOptions",
        "read_dir",
        ".is_file()",
        ".is_dir()",
        ".exists()",
        ".metadata()",
        "canonicalize",
        "/proc/",
    ];

    /// The lines of `text` before its inline test module (unit tests set up
    /// their folders as they need), comments left out.
    fn code_lines(text: &str) -> Vec<(usize, &str)> {
        let lines: Vec<&str> = text.lines().collect();
        let end = lines
            .windows(2)
            .position(|w| w[0].trim() == "#[cfg(test)]" && w[1].trim_start().starts_with("mod "))
            .filter(|&i| lines[i + 1].trim_end().ends_with('{'))
            .unwrap_or(lines.len());
        lines[..end]
            .iter()
            .enumerate()
            .map(|(i, line)| (i + 1, line.split("//").next().unwrap_or_default()))
            .collect()
    }

    fn calls_in(line: &str) -> bool {
        FILE_SYSTEM_CALLS.iter().any(|call| {
            line.match_indices(call).any(|(at, _)| {
                // A name as a path of its own (`fs::`), not the end of
                // another name (`refs::`).
                let in_a_name = |c: char| c.is_alphanumeric() || c == '_';
                !(call.starts_with(in_a_name)
                    && line[..at].chars().next_back().is_some_and(in_a_name))
            })
        })
    }

    #[test]
    fn only_files_touches_the_file_system() {
        assert!(calls_in("let meta = std::fs::metadata(path)?;"));
        assert!(calls_in("if !path.is_file() {"));
        assert!(!calls_in("let refs::x = 1;"));
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
        let mut found = Vec::new();
        for path in find_files(&src, ".rs").unwrap() {
            let test_file = path.file_name().is_some_and(|n| n == "tests.rs");
            if path.starts_with(src.join("files")) || test_file {
                continue;
            }
            let text = String::from_utf8(read_file(&path).unwrap()).unwrap();
            for (number, line) in code_lines(&text) {
                if calls_in(line) {
                    found.push(format!("{}:{number}: {}", path.display(), line.trim()));
                }
            }
        }
        assert!(
            found.is_empty(),
            "file-system calls outside src/files/:\n{}",
            found.join("\n")
        );
    }
}

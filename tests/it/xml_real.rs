//! Every real BigWorld text file parses into a section tree.

use crate::support::realdata;
use shadowcull::formats::xml;
use std::path::{Path, PathBuf};

pub fn files_with_extensions(dir: &Path, extensions: &[&str]) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let mut pending = vec![dir.to_path_buf()];
    while let Some(dir) = pending.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for entry in entries.flatten() {
            let path = entry.path();
            if path.is_dir() {
                pending.push(path);
            } else if path
                .file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|name| extensions.iter().any(|e| name.ends_with(e)))
            {
                found.push(path);
            }
        }
    }
    found.sort();
    found
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn every_real_text_file_parses() {
    let Some(root) = realdata("every_real_text_file_parses") else {
        return;
    };
    let files = files_with_extensions(&root, &[".chunk", ".visual", ".model", "space.settings"]);
    // arctic: 104 chunks, 20 .model, 20 .visual, space.settings;
    // bigworld-14.4.1: 26 .model, 26 .visual, space.settings.
    assert_eq!(files.len(), 145 + 53);
    for path in &files {
        let bytes = std::fs::read(path).unwrap();
        let section = xml::parse(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert!(!section.children.is_empty(), "{}", path.display());
    }
}

#[test]
#[cfg_attr(
    not(shadowcull_realdata),
    ignore = "needs real BigWorld data: set SHADOWCULL_REALDATA (README.md, Development)"
)]
fn arctic_chunk_roots_have_both_naming_styles() {
    let Some(root) = realdata("arctic_chunk_roots_have_both_naming_styles") else {
        return;
    };
    let dir = root.join("fantasydemo-arctic/res/spaces/arctic");
    let (mut named_root, mut named_file) = (0, 0);
    for path in files_with_extensions(&dir, &["o.chunk"]) {
        let section = xml::parse(&std::fs::read(&path).unwrap()).unwrap();
        let file_name = path.file_name().unwrap().to_str().unwrap();
        if section.name == "root" {
            named_root += 1;
        } else {
            assert_eq!(section.name, file_name);
            named_file += 1;
        }
    }
    // README: 54 `<root>` chunks in all (4 of them indoor), 50 named after the file.
    assert_eq!((named_root, named_file), (50, 50));
}

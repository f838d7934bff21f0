//! Resource lookup over several res paths (like the engine's `paths.xml`,
//! searched in order): a name may not climb out of the roots, and a file
//! whose symbolic links lead outside every root is refused.

use super::read_file;
use crate::error::{Error, Result};
use std::borrow::Cow;
use std::fs;
use std::path::{Component, Path, PathBuf};

/// The resource roots, searched in order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ResPaths {
    pub roots: Vec<PathBuf>,
}

/// A resource name as written in XML, normalised: forward slashes, no
/// leading slash, no surrounding white space.
pub fn normalise(name: &str) -> String {
    normalised(name).into_owned()
}

/// [`normalise`] without a copy when `name` needs no change but trimming
/// (nearly every name a chunk gives: placing millions looks each up).
pub fn normalised(name: &str) -> Cow<'_, str> {
    let name = name.trim();
    if name.contains('\\') {
        Cow::Owned(name.replace('\\', "/").trim_start_matches('/').to_string())
    } else {
        Cow::Borrowed(name.trim_start_matches('/'))
    }
}

/// A normalised name that stays below the folder it is joined to: not
/// empty, no `..`, no drive or root prefix.
pub fn stays_inside(name: &str) -> bool {
    !name.is_empty()
        && Path::new(name)
            .components()
            .all(|c| matches!(c, Component::Normal(_) | Component::CurDir))
}

impl ResPaths {
    pub fn new(roots: Vec<PathBuf>) -> Self {
        ResPaths { roots }
    }

    /// The first root holding `name`, as a full path. A name that climbs out
    /// with `..`, or an entry whose symbolic links lead outside every root,
    /// resolves to nothing ([`ResPaths::read`] says why).
    pub fn resolve(&self, name: &str) -> Option<PathBuf> {
        self.locate(name).ok().flatten()
    }

    fn locate(&self, name: &str) -> Result<Option<PathBuf>> {
        let name = normalise(name);
        if !stays_inside(&name) {
            return Ok(None);
        }
        for root in &self.roots {
            let path = root.join(&name);
            // `metadata` follows links but opens nothing: a FIFO is found
            // here and refused by `read_file`, never opened.
            if fs::metadata(&path).is_ok_and(|m| !m.is_dir()) {
                self.check_inside(&path)?;
                return Ok(Some(path));
            }
        }
        Ok(None)
    }

    /// Errors when `path`, with every symbolic link resolved, lies outside
    /// every res root (a link planted in a res folder pointing elsewhere).
    /// A path that does not exist passes: reading it says so.
    pub fn check_inside(&self, path: &Path) -> Result<()> {
        let real = match fs::canonicalize(path) {
            Ok(real) => real,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
            Err(e) => return Err(Error::io(path, "resolve", e)),
        };
        let inside = self
            .roots
            .iter()
            .filter_map(|root| fs::canonicalize(root).ok())
            .any(|root| real.starts_with(root));
        if inside {
            return Ok(());
        }
        Err(Error::invalid(
            path,
            format!(
                "leads to {}, outside every res path ({}); refused: copy the file into a res path or add its folder to <resPaths>",
                real.display(),
                self.roots_list()
            ),
        ))
    }

    fn roots_list(&self) -> String {
        self.roots
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// The root a full path lies under, and the path relative to it.
    pub fn relative<'a>(&'a self, path: &'a Path) -> Option<(&'a Path, &'a Path)> {
        self.roots.iter().find_map(|root| {
            path.strip_prefix(root)
                .ok()
                .map(|rel| (root.as_path(), rel))
        })
    }

    /// The file `name` that a file in `dir` names relative to its own
    /// folder (a chunk's terrain `.cdata`): in `dir` itself (or its bare name
    /// there, [`in_folder_or_bare`]); when neither is there, resource
    /// `folder/name` (then `folder/BARE`) through the roots in order, as the
    /// engine's resource manager finds it, `folder` being `dir`'s resource
    /// name. So the chunks of a copy that holds only chunks (`bake --out`)
    /// find their terrain in a root after it. Found nowhere: the path in
    /// `dir`, whose read says what is missing. A file whose links lead
    /// outside every root is refused.
    pub fn beside(&self, dir: &Path, folder: &str, name: &str) -> Result<PathBuf> {
        let local = in_folder_or_bare(dir, name);
        // `metadata` opens nothing: a FIFO here is refused by the read.
        if fs::metadata(&local).is_err() {
            let bare = Path::new(name).file_name().and_then(|n| n.to_str());
            for candidate in [Some(name), bare].into_iter().flatten() {
                if let Some(found) = self.locate(&format!("{folder}/{candidate}"))? {
                    return Ok(found);
                }
            }
        }
        self.check_inside(&local)?;
        Ok(local)
    }

    /// Reads resource `name`; `referenced_by` is the file that named it, for
    /// the error.
    pub fn read(&self, name: &str, referenced_by: &Path) -> Result<(PathBuf, Vec<u8>)> {
        let normal = normalise(name);
        if !normal.is_empty() && !stays_inside(&normal) {
            return Err(Error::invalid(
                referenced_by,
                format!("resource `{normal}` climbs out of the res paths (`..` or a drive prefix); refused: name resources relative to a res path"),
            ));
        }
        let path = self.locate(name)?.ok_or_else(|| Error::NotFound {
            name: normal,
            referenced_by: referenced_by.to_path_buf(),
            searched: self.roots.clone(),
        })?;
        let bytes = read_file(&path)?;
        Ok((path, bytes))
    }
}

/// `name` in `dir`, or the bare file name of `name` in `dir` when `dir/name`
/// is no file: engines write a chunk's `.cdata` relative to the chunk's
/// folder, some tools with the space folder prefixed.
pub fn in_folder_or_bare(dir: &Path, name: &str) -> PathBuf {
    let path = dir.join(name);
    if path.is_file() {
        return path;
    }
    match Path::new(name).file_name() {
        Some(bare) => dir.join(bare),
        None => path,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::files::write_atomic;

    #[test]
    fn search_order_and_normalisation() {
        let first = tempfile::tempdir().unwrap();
        let second = tempfile::tempdir().unwrap();
        write_atomic(&second.path().join("sets/a.model"), b"2").unwrap();
        write_atomic(&first.path().join("sets/b.model"), b"1").unwrap();
        write_atomic(&second.path().join("sets/b.model"), b"2").unwrap();
        let paths = ResPaths::new(vec![first.path().into(), second.path().into()]);
        assert_eq!(paths.read("sets/b.model", Path::new("x")).unwrap().1, b"1");
        assert_eq!(
            paths.read("\t/sets\\a.model ", Path::new("x")).unwrap().1,
            b"2"
        );
        assert_eq!(paths.resolve("../etc/passwd"), None);
        let err = paths
            .read("sets/none.model", Path::new("c.chunk"))
            .unwrap_err();
        let message = err.to_string();
        assert!(
            message.starts_with("c.chunk:") && message.contains("sets/none.model"),
            "{message}"
        );
    }

    #[test]
    fn names_are_normalised_the_same_with_or_without_a_copy() {
        for (name, normal) in [
            ("sets/a.model", "sets/a.model"),
            ("\t/sets\\a.model ", "sets/a.model"),
            ("//sets/a.model", "sets/a.model"),
            ("\\\\sets\\b\\c.model", "sets/b/c.model"),
            (" / ", ""),
            ("", ""),
        ] {
            assert_eq!(normalised(name), normal, "{name:?}");
            assert_eq!(normalise(name), normal, "{name:?}");
        }
        assert!(matches!(normalised(" sets/a.model"), Cow::Borrowed(_)));
    }

    #[test]
    fn names_that_climb_out_are_refused() {
        for name in ["a/b.model", "./a.model", "x"] {
            assert!(stays_inside(name), "{name}");
        }
        for name in ["", "../a.model", "a/../../b", "a/.."] {
            assert!(!stays_inside(name), "{name}");
        }
        let root = tempfile::tempdir().unwrap();
        let paths = ResPaths::new(vec![root.path().join("res")]);
        write_atomic(&root.path().join("secret.model"), b"x").unwrap();
        let message = paths
            .read("../secret.model", Path::new("c.chunk"))
            .unwrap_err()
            .to_string();
        assert!(
            message.starts_with("c.chunk:") && message.contains("climbs out"),
            "{message}"
        );
    }

    #[test]
    fn a_file_beside_is_looked_up_in_its_folder_then_through_the_roots() {
        let copy = tempfile::tempdir().unwrap();
        let first = tempfile::tempdir().unwrap();
        let second = tempfile::tempdir().unwrap();
        let paths = ResPaths::new(vec![
            copy.path().into(),
            first.path().into(),
            second.path().into(),
        ]);
        let dir = copy.path().join("spaces/a");
        write_atomic(&second.path().join("spaces/a/t.cdata"), b"2").unwrap();
        write_atomic(&second.path().join("spaces/a/u.cdata"), b"2").unwrap();
        write_atomic(&first.path().join("spaces/a/u.cdata"), b"1").unwrap();
        let found = |name: &str| paths.beside(&dir, "spaces/a", name).unwrap();
        // Not in the chunk's folder: the roots in order.
        assert_eq!(found("t.cdata"), second.path().join("spaces/a/t.cdata"));
        assert_eq!(found("u.cdata"), first.path().join("spaces/a/u.cdata"));
        // A name with the space folder before it: its bare name.
        assert_eq!(
            found("spaces/a/u.cdata"),
            first.path().join("spaces/a/u.cdata")
        );
        // In the chunk's folder: that one.
        write_atomic(&dir.join("u.cdata"), b"0").unwrap();
        assert_eq!(found("u.cdata"), dir.join("u.cdata"));
        // Nowhere: the path in the chunk's folder, whose read fails.
        assert_eq!(found("v.cdata"), dir.join("v.cdata"));
        assert!(read_file(&found("v.cdata")).is_err());
    }

    #[cfg(unix)]
    #[test]
    fn links_out_of_the_res_paths_are_refused() {
        let root = tempfile::tempdir().unwrap();
        let outside = tempfile::tempdir().unwrap();
        write_atomic(&outside.path().join("b.model"), b"outside").unwrap();
        write_atomic(&root.path().join("real/c.model"), b"inside").unwrap();
        std::fs::create_dir_all(root.path().join("sets")).unwrap();
        std::os::unix::fs::symlink(
            outside.path().join("b.model"),
            root.path().join("sets/b.model"),
        )
        .unwrap();
        std::os::unix::fs::symlink(
            root.path().join("real/c.model"),
            root.path().join("sets/c.model"),
        )
        .unwrap();
        let paths = ResPaths::new(vec![root.path().into()]);
        let message = paths
            .read("sets/b.model", Path::new("c.chunk"))
            .unwrap_err()
            .to_string();
        assert!(message.contains("outside every res path"), "{message}");
        assert_eq!(paths.resolve("sets/b.model"), None);
        // A link that stays inside the roots is followed.
        assert_eq!(
            paths.read("sets/c.model", Path::new("c.chunk")).unwrap().1,
            b"inside"
        );
        // A file beside a chunk is held to the roots alike, wherever the
        // lookup finds it.
        let copy = tempfile::tempdir().unwrap();
        let paths = ResPaths::new(vec![copy.path().into(), root.path().into()]);
        let message = paths
            .beside(&copy.path().join("sets"), "sets", "b.model")
            .unwrap_err()
            .to_string();
        assert!(message.contains("outside every res path"), "{message}");
    }
}

//! The library's typed errors. Every error a user can see names the file and,
//! where the format has one, the element or byte offset inside it, and says
//! what to do about it.

use std::fmt;
use std::path::PathBuf;

/// Where inside a file something went wrong.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum Location {
    /// The file as a whole (e.g. it is empty, or of the wrong kind).
    #[default]
    File,
    /// A byte offset from the start of the file (or of the ZIP entry named in
    /// the path).
    Byte(u64),
    /// An XML element, as a slash-separated path from the root, plus the byte
    /// offset of its start tag (text XML) or of its data (packed XML).
    Element { path: String, offset: u64 },
}

impl Location {
    /// The byte offset, when the location has one.
    pub fn offset(&self) -> Option<u64> {
        match self {
            Location::File => None,
            Location::Byte(offset) | Location::Element { offset, .. } => Some(*offset),
        }
    }
}

/// A 1-based line and column (in characters) inside a text file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TextPosition {
    pub line: usize,
    pub column: usize,
}

impl TextPosition {
    /// Where byte `offset` of text `bytes` lies, or `None` when the offset
    /// is past them or a NUL byte before it shows they are not text (a
    /// binary section; `formats::text_position` also knows packed XML).
    pub fn of(bytes: &[u8], offset: u64) -> Option<TextPosition> {
        let offset = usize::try_from(offset).ok()?;
        if offset > bytes.len() {
            return None;
        }
        let before = &bytes[..offset];
        if before.contains(&0) {
            return None;
        }
        let line_start = before
            .iter()
            .rposition(|&b| b == b'\n')
            .map_or(0, |i| i + 1);
        let line = 1 + before.iter().filter(|&&b| b == b'\n').count();
        let column = 1 + String::from_utf8_lossy(&before[line_start..])
            .chars()
            .count();
        Some(TextPosition { line, column })
    }
}

impl fmt::Display for TextPosition {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}", self.line, self.column)
    }
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Location::File => Ok(()),
            Location::Byte(offset) => write!(f, " at byte {offset}"),
            Location::Element { path, offset } => {
                write!(f, " in element <{path}> (byte {offset})")
            }
        }
    }
}

/// A problem found while decoding bytes, before the caller attaches the path
/// of the file those bytes came from (decoders work on slices, not files):
/// `in_file`, or `in_source` (in `formats`, which knows which bytes are text)
/// for line and column too.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FormatError {
    pub at: Location,
    pub message: String,
}

impl FormatError {
    pub fn new(at: Location, message: impl Into<String>) -> Self {
        FormatError {
            at,
            message: message.into(),
        }
    }

    pub fn at_byte(offset: usize, message: impl Into<String>) -> Self {
        FormatError::new(Location::Byte(offset as u64), message)
    }

    pub fn whole_file(message: impl Into<String>) -> Self {
        FormatError::new(Location::File, message)
    }

    /// Moves a byte location by `base`, for errors found inside a part of a
    /// file (a BinSection entry) so they still point into the whole file.
    pub fn shifted(mut self, base: usize) -> Self {
        if let Location::Byte(offset) = &mut self.at {
            *offset += base as u64;
        }
        self
    }

    /// Attaches the file the bytes came from.
    pub fn in_file(self, path: impl Into<PathBuf>) -> Error {
        Error::Format {
            path: path.into(),
            at: self.at,
            message: self.message,
            position: None,
        }
    }
}

impl fmt::Display for FormatError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}{}", self.message, self.at)
    }
}

impl std::error::Error for FormatError {}

/// The library's error type.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The OS error is part of the message and deliberately not a
    /// `#[source]`: error chains (anyhow's `{:#}`) would print it twice.
    #[error("{}: cannot {action}: {os_error}", path.display())]
    Io {
        path: PathBuf,
        action: &'static str,
        os_error: std::io::Error,
    },
    #[error("{}{}{at}: {message}", path.display(), position.map(|p| format!(":{p}")).unwrap_or_default())]
    Format {
        path: PathBuf,
        at: Location,
        message: String,
        /// Line and column of `at` in a text file.
        position: Option<TextPosition>,
    },
    #[error("{}: resource `{name}` not found in any res path ({}); check <resPaths> in the settings file", referenced_by.display(), searched.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", "))]
    NotFound {
        name: String,
        referenced_by: PathBuf,
        searched: Vec<PathBuf>,
    },
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
    /// Files a write would have to replace but must not (read-only, not a
    /// regular file, not writable by this user): checked before anything
    /// is written, so nothing was.
    #[error("nothing was written: {} file(s) cannot be replaced:{}", files.len(), files.iter().map(|(path, why)| format!("\n  {}: {why}", path.display())).collect::<String>())]
    Refused { files: Vec<(PathBuf, String)> },
}

impl Error {
    pub fn io(path: impl Into<PathBuf>, action: &'static str, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            action,
            os_error: source,
        }
    }

    pub fn invalid(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Invalid {
            path: path.into(),
            message: message.into(),
        }
    }
}

impl Error {
    /// The error as a problem about `file`: what (the file, with line and
    /// column in a text file, `path:line:column` as editors take it) and
    /// why (the rest), so a list that prints `what: why` says the path
    /// once. An error about another file keeps its whole message.
    pub fn as_problem_of(&self, file: &std::path::Path) -> (String, String) {
        let what = file.display().to_string();
        if self.path() != Some(file) {
            return (what, self.to_string());
        }
        match self {
            Error::Io {
                action, os_error, ..
            } => (what, format!("cannot {action}: {os_error}")),
            Error::Format {
                at,
                message,
                position,
                ..
            } => {
                let what = match position {
                    Some(p) => format!("{what}:{p}"),
                    None => what,
                };
                let place = at.to_string();
                let why = if place.is_empty() {
                    message.clone()
                } else {
                    format!("{}: {message}", place.trim_start())
                };
                (what, why)
            }
            Error::Invalid { message, .. } => (what, message.clone()),
            other => (what, other.to_string()),
        }
    }

    /// The file the error is about, when it names one.
    pub fn path(&self) -> Option<&std::path::Path> {
        match self {
            Error::Io { path, .. } | Error::Format { path, .. } | Error::Invalid { path, .. } => {
                Some(path)
            }
            Error::NotFound { referenced_by, .. } => Some(referenced_by),
            Error::Refused { .. } => None,
        }
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_positions_count_lines_and_characters() {
        let text = "<a>\n\t<bé>x</bé>\n</a>".as_bytes();
        let at = text.iter().position(|&b| b == b'x').unwrap() as u64;
        assert_eq!(
            TextPosition::of(text, at),
            Some(TextPosition { line: 2, column: 6 })
        );
        assert_eq!(
            TextPosition::of(text, 0),
            Some(TextPosition { line: 1, column: 1 })
        );
        assert_eq!(TextPosition::of(text, 999), None);
        assert_eq!(TextPosition::of(b"ab\0cd", 4), None);
        let err = FormatError::at_byte(at as usize, "bad").in_file("f.xml");
        assert_eq!(err.to_string(), format!("f.xml at byte {at}: bad"));
    }
}

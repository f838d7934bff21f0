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
/// of the file those bytes came from (decoders work on slices, not files).
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
    #[error("{}: cannot {action}: {source}", path.display())]
    Io {
        path: PathBuf,
        action: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error("{}{at}: {message}", path.display())]
    Format {
        path: PathBuf,
        at: Location,
        message: String,
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
            source,
        }
    }

    pub fn invalid(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Invalid {
            path: path.into(),
            message: message.into(),
        }
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

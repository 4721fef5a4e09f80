//! Errors raised while importing a trained network from disk.
//!
//! Every message is a single line that starts with the offending path, so a
//! user staring at a directory of 304 near-identical `.bin` files knows which
//! one to look at without a backtrace.

use std::path::PathBuf;

/// Why a PFNN weight directory could not be imported.
///
/// One flat enum on purpose: callers either show the message or match on the
/// variant in tests; nobody needs a hierarchy.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// The path given as the weight directory exists but is a file (or
    /// something else that is not a directory).
    #[error("{}: not a directory", .path.display())]
    NotADirectory { path: PathBuf },

    /// A file (or the directory itself) the format requires does not exist.
    #[error("{}: not found", .path.display())]
    MissingFile { path: PathBuf },

    /// The file exists but has the wrong length. The files carry no header,
    /// so the byte count is the only shape check available; a mismatch
    /// usually means a truncated copy or a model with other dimensions.
    #[error(
        "{}: wrong size: expected {expected} bytes ({} float32), found {found} bytes",
        .path.display(),
        .expected / 4
    )]
    WrongSize {
        path: PathBuf,
        expected: u64,
        found: u64,
    },

    /// The dimensions read off the files imply a size that does not fit a
    /// `usize` (a directory of huge or sparse files): refused before any
    /// arithmetic can wrap.
    #[error("{}: {what} is more than fits in memory (its size overflows)", .path.display())]
    SizeOverflow { path: PathBuf, what: String },

    /// A NaN or infinity in the weights would silently poison every output
    /// (and break fixed-point calibration), so it is rejected at import.
    #[error(
        "{}: value at float index {index} is not finite ({value})",
        .path.display()
    )]
    NonFinite {
        path: PathBuf,
        index: usize,
        value: f32,
    },

    /// An input standard deviation of exactly zero. The network divides the
    /// raw input by it, so it would turn every input into ±inf or NaN.
    #[error(
        "{}: standard deviation at index {index} is zero; inputs are divided by it",
        .path.display()
    )]
    ZeroStd { path: PathBuf, index: usize },

    /// Any other operating-system failure (permissions, I/O error, ...).
    ///
    /// The underlying error is part of the one-line message rather than
    /// exposed through `source()`, so that `anyhow`'s `{:#}` does not print
    /// it twice.
    #[error("{}: {error}", .path.display())]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
}

impl ImportError {
    /// The file or directory the error is about.
    pub fn path(&self) -> &std::path::Path {
        match self {
            Self::NotADirectory { path }
            | Self::MissingFile { path }
            | Self::WrongSize { path, .. }
            | Self::SizeOverflow { path, .. }
            | Self::NonFinite { path, .. }
            | Self::ZeroStd { path, .. }
            | Self::Io { path, .. } => path,
        }
    }

    /// Classifies an I/O error: "not found" is common enough (a wrong path,
    /// an incomplete copy) to deserve its own variant and message.
    pub(crate) fn from_io(path: PathBuf, error: std::io::Error) -> Self {
        if error.kind() == std::io::ErrorKind::NotFound {
            Self::MissingFile { path }
        } else {
            Self::Io { path, error }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn all_variants() -> Vec<ImportError> {
        let p = || PathBuf::from("net/W1_007.bin");
        vec![
            ImportError::NotADirectory { path: p() },
            ImportError::MissingFile { path: p() },
            ImportError::WrongSize {
                path: p(),
                expected: 1_048_576,
                found: 1000,
            },
            ImportError::NonFinite {
                path: p(),
                index: 42,
                value: f32::NAN,
            },
            ImportError::ZeroStd {
                path: p(),
                index: 3,
            },
            ImportError::Io {
                path: p(),
                error: std::io::Error::new(std::io::ErrorKind::PermissionDenied, "denied"),
            },
        ]
    }

    #[test]
    fn every_message_is_one_line_starting_with_the_path() {
        for e in all_variants() {
            let msg = e.to_string();
            assert!(msg.starts_with("net/W1_007.bin: "), "{msg}");
            assert!(!msg.contains('\n'), "{msg}");
            assert_eq!(e.path(), std::path::Path::new("net/W1_007.bin"));
        }
    }

    #[test]
    fn messages_carry_the_numbers() {
        let v = all_variants();
        assert_eq!(
            v[2].to_string(),
            "net/W1_007.bin: wrong size: expected 1048576 bytes (262144 float32), found 1000 bytes"
        );
        assert!(v[3].to_string().contains("index 42"));
        assert!(v[3].to_string().contains("NaN"));
        assert!(v[5].to_string().ends_with("denied"));
    }

    #[test]
    fn not_found_maps_to_missing_file() {
        let e = ImportError::from_io(
            PathBuf::from("x.bin"),
            std::io::Error::from(std::io::ErrorKind::NotFound),
        );
        assert!(matches!(e, ImportError::MissingFile { .. }));
        let e = ImportError::from_io(
            PathBuf::from("x.bin"),
            std::io::Error::from(std::io::ErrorKind::PermissionDenied),
        );
        assert!(matches!(e, ImportError::Io { .. }));
    }
}

/// An import error that concerns the weights file of a (description,
/// weights) pair rather than the description (an OMG `config.json` with
/// its `model.safetensors`, a graph description with its `.npz`): a missing
/// array, a wrong shape, a non-finite value. The readers name the weights
/// file for these, the description for the rest.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct InWeights(pub String);

/// [`InWeights`] as an [`anyhow::Error`].
pub fn in_weights(message: String) -> anyhow::Error {
    anyhow::Error::new(InWeights(message))
}

/// Whether `e` (or an error it wraps) is [`InWeights`].
pub fn concerns_weights(e: &anyhow::Error) -> bool {
    e.chain().any(|c| c.is::<InWeights>())
}

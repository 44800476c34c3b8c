//! The crate's error type.

use std::path::PathBuf;

/// Everything that can go wrong in `canpos-sim`. Parsers and constructors return this instead of
/// panicking; the `Display` text is meant to be shown to a user as is.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// A sensor specification was asked for with values the product does not offer
    /// (stroke out of range, too many magnets, ...).
    #[error("invalid sensor specification: {0}")]
    Spec(String),

    /// An order code could not be parsed.
    #[error("invalid order code \"{code}\": {reason}")]
    OrderCode {
        /// The code as given (trimmed).
        code: String,
        /// What is wrong, naming the box (character position) where possible.
        reason: String,
    },

    /// A textual motion specification could not be parsed.
    #[error("invalid motion spec \"{spec}\": {reason}")]
    MotionSpec {
        /// The (part of the) specification that failed.
        spec: String,
        /// What is wrong.
        reason: String,
    },

    /// A CSV trajectory has a malformed line.
    #[error("{source_name}:{line}: {reason}")]
    Csv {
        /// File name (or a label for in-memory text).
        source_name: String,
        /// 1-based line number (0 when the problem concerns the whole file).
        line: usize,
        /// What is wrong.
        reason: String,
    },

    /// A file could not be read.
    #[error("cannot read {}: {message}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's message.
        message: String,
    },

    /// A run-time request (live set-point, fault) carried an invalid value.
    #[error("invalid request: {0}")]
    Request(String),
}

/// Shorthand for `Result<T, canpos_sim::Error>`.
pub type Result<T> = std::result::Result<T, Error>;

//! Why a storage operation failed. One type for the whole module so that a caller streaming over
//! a shard set (reader, window, merge, sort) handles one error, and every case names the file it
//! is about, says what is wrong and what to do about it.

use std::path::{Path, PathBuf};

/// What to tell the user when a file is damaged: it cannot be repaired, only made again.
const REMAKE: &str =
    "restore it from a copy or make the shard set again with `voxrad-shard convert`";

#[derive(Debug, thiserror::Error)]
pub enum StorageError {
    #[error("cannot {action} {}: {source}", path.display())]
    Io {
        path: PathBuf,
        /// What was being done ("read", "write", "map", ...).
        action: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{} is not a voxrad {kind}: it starts with {found:?}, expected {expected:?}; check the \
         path",
        path.display()
    )]
    BadMagic {
        path: PathBuf,
        kind: &'static str,
        found: Vec<u8>,
        expected: Vec<u8>,
    },
    #[error(
        "{} has {kind} format version {found}; this build reads versions {min} to {max}: use a \
         voxrad that supports it, or convert the scene again with this one",
        path.display()
    )]
    UnsupportedVersion {
        path: PathBuf,
        kind: &'static str,
        found: u32,
        min: u32,
        max: u32,
    },
    #[error("{} has an invalid header: {what}; {REMAKE}", path.display())]
    BadHeader { path: PathBuf, what: String },
    #[error("{} is truncated or has extra bytes: {what}; {REMAKE}", path.display())]
    BadLength { path: PathBuf, what: String },
    #[error(
        "{} is corrupted: checksum {computed:#010x} of its contents does not match the stored \
         {stored:#010x}; {REMAKE}",
        path.display()
    )]
    ChecksumMismatch {
        path: PathBuf,
        stored: u32,
        computed: u32,
    },
    #[error(
        "{} is not sorted: record {index} (voxel {voxel:?}) comes before record {} (voxel \
         {previous:?}) in order {order}; {REMAKE}",
        path.display(), index - 1
    )]
    Unsorted {
        path: PathBuf,
        order: u32,
        index: u64,
        voxel: [i32; 3],
        previous: [i32; 3],
    },
    #[error("{} cannot be used: {what}", path.display())]
    Invalid { path: PathBuf, what: String },
    #[error(
        "{} is not a valid shard-set manifest: {source}; {REMAKE}",
        path.display()
    )]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error(
        "a memory budget of {budget_bytes} bytes is too small to sort records (the least that \
         makes progress is {minimum_bytes} bytes); give a larger --memory"
    )]
    BudgetTooSmall {
        budget_bytes: u64,
        minimum_bytes: u64,
    },
}

impl StorageError {
    pub(crate) fn io(path: &Path, action: &'static str, source: std::io::Error) -> Self {
        StorageError::Io {
            path: path.to_path_buf(),
            action,
            source,
        }
    }

    pub(crate) fn invalid(path: &Path, what: impl Into<String>) -> Self {
        StorageError::Invalid {
            path: path.to_path_buf(),
            what: what.into(),
        }
    }

    /// Whether the user's input is at fault (exit status 2): a damaged, missing or unreadable
    /// input file, a budget too small. A failure to write, or a read failing for another reason
    /// (an I/O error of the device), is not (exit status 1).
    pub fn is_bad_input(&self) -> bool {
        use std::io::ErrorKind;
        match self {
            StorageError::Io { action, source, .. } => {
                matches!(*action, "read" | "map")
                    && matches!(
                        source.kind(),
                        ErrorKind::NotFound
                            | ErrorKind::PermissionDenied
                            | ErrorKind::UnexpectedEof
                            | ErrorKind::InvalidData
                            | ErrorKind::IsADirectory
                    )
            }
            _ => true,
        }
    }

    /// The file the error is about (`None` only for a budget that is too small).
    pub fn path(&self) -> Option<&Path> {
        match self {
            StorageError::Io { path, .. }
            | StorageError::BadMagic { path, .. }
            | StorageError::UnsupportedVersion { path, .. }
            | StorageError::BadHeader { path, .. }
            | StorageError::BadLength { path, .. }
            | StorageError::ChecksumMismatch { path, .. }
            | StorageError::Unsorted { path, .. }
            | StorageError::Invalid { path, .. }
            | StorageError::Json { path, .. } => Some(path),
            StorageError::BudgetTooSmall { .. } => None,
        }
    }
}

impl From<crate::output::OutputError> for StorageError {
    /// The atomic writer's errors (shared with `output`) already name the file.
    fn from(e: crate::output::OutputError) -> Self {
        use crate::output::OutputError;
        match e {
            OutputError::Io { path, source } => StorageError::Io {
                path,
                action: "write",
                source,
            },
            OutputError::Json { path, source } => StorageError::Invalid {
                path,
                what: format!("cannot encode it as JSON: {source}"),
            },
            OutputError::Invalid { path, what } => StorageError::Invalid { path, what },
        }
    }
}

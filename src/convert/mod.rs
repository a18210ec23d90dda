//! The shard conversion tool's library (`voxrad-shard`, whose binary in `tools/` only parses
//! arguments): scenes into shard sets, and shard sets inspected, verified, re-split; results
//! exported. Everything streams under a memory budget.
//!
//! One concept per file:
//! - [`pieces`]: the external sort of voxelization pieces (runs on disk, k-way merge).
//! - [`stream`]: out-of-core voxelization: the same surfels as `voxel::voxelize`, produced in
//!   shard order without holding them all.
//! - [`shardset`]: writing a shard set (staging directory, equal-count split, manifest, the
//!   rename into place), verifying one, describing one.
//! - [`export`]: a solve's `surfels.bin` streamed into PLY or CSV.
//! - [`pack`]: a shard set as one zstd-compressed file, and back (verified before use).
//! - [`commands`]: the subcommands as functions of parsed options.
//!
//! Errors are [`ConvertError`]: bad input (exit status 2, the message names the file) or a
//! failure of anything else (1).

pub mod commands;
pub mod export;
pub mod pack;
pub mod pieces;
pub mod shardset;
pub mod stream;

use crate::storage::StorageError;

/// Why a conversion command failed, with the exit status it maps to.
#[derive(Debug, thiserror::Error)]
pub enum ConvertError {
    /// The user's input is wrong (the message names the file and says what to do): status 2.
    #[error("{0}")]
    BadInput(String),
    /// Anything else (a write failed, the disk is full): status 1.
    #[error("{0}")]
    Failure(String),
}

impl ConvertError {
    pub fn exit_code(&self) -> i32 {
        match self {
            ConvertError::BadInput(_) => 2,
            ConvertError::Failure(_) => 1,
        }
    }
}

impl From<StorageError> for ConvertError {
    /// Damaged, missing or unreadable input files are the user's input; a failure to write, or a
    /// read failing for another reason (an I/O error of the device), is not.
    fn from(e: StorageError) -> Self {
        if e.is_bad_input() {
            ConvertError::BadInput(e.to_string())
        } else {
            ConvertError::Failure(e.to_string())
        }
    }
}

impl From<crate::output::OutputError> for ConvertError {
    fn from(e: crate::output::OutputError) -> Self {
        ConvertError::Failure(e.to_string())
    }
}

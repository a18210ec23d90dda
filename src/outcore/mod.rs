//! The out-of-core solver: the same radiosity as `solve::jacobi`, with every array that grows
//! with the scene kept in files and a memory budget on everything held.
//!
//! **Layout.** The surfels come in the canonical order of their source (a shard set, see
//! [`source`]). Before iterating, [`workset`] writes three *axis copies* of them: copy `m` is
//! sorted by `(x_m, x_v, x_u)`, the direction's main axis `m` first (`u, v` the two others, as in
//! `geometry::lines`). Every direction whose main axis is `m` has all its lines running through
//! the layers of `x_m` in increasing order, one voxel per layer, so reading copy `m` layer by
//! layer lists every line's surfels in order along the line. A copy's static records are kept in
//! compressed frames ([`framed`]): alike neighbours make them about ten times smaller; its
//! canonical ids and the canonical surfels' places in it likewise ([`packed_index`]).
//!
//! **A direction** ([`band`]) is solved band by band: a band is a range of line columns
//! `j0 <= j < j1` (all `i`), cut so that its surfels fit the budget. In layer `x_m = z`, the
//! lines of a band hold the rows `x_v` in `[j0 - shift(z), j1 - shift(z))`, one contiguous range
//! of copy `m`; the band is these ranges read layer after layer, so the bands of one direction
//! read every record exactly once, and the per-line frontier is never larger than a band's
//! lines. Inside a band the in-memory engine runs unchanged (`solve::dispatch` into lists,
//! `solve::propagate` along them, on the worker threads), and the light gathered is added to
//! that of the axis's earlier directions at the same ranges: read from one of two gather files
//! and written to the other, so that the light of the directions done stays whole on disk for a
//! checkpoint (`workset::WorkSet::gathered`).
//!
//! **An iteration** ([`solver`]) walks the directions grouped by main axis, then brings the
//! three gather files back to canonical order ([`scatter`]), computes `B = E + rho H / S(n)`
//! there, and sends the new radiosity to each copy in turn, before that copy's directions (the
//! three share one radiosity file).
//!
//! **Partner links** ([`links`]): a direction's first pass writes its bands' links to a work
//! file of its own, within a disk allowance; later iterations replay them band by band instead
//! of reading the static records, dispatching and searching (the same bits), reading the light
//! of several consecutive bands at once ([`band`]). Directions whose lines have the same slope
//! along `v` have the same bands: one pass gathers them together (searching or replaying),
//! reading and writing each band once for all of them ([`solver`]).
//!
//! **The direct-light pass** ([`direct`]) for small emitters runs before the iterations, on
//! parts of the scene that hold its emitters' lines, within the same budget.
//!
//! **Memory** ([`budget`]): the row histogram of one copy, the per-layer cursors, then one of
//! (a band's arrays and line counters | a replay's light of several bands, its staging buffer
//! and one band's links | a sort bucket | a permutation chunk) at a time, and fixed-size I/O
//! buffers. Not counted: code, stacks and the allocator's own overhead, a few MiB; see the
//! tests for the allowance measured under an address-space limit.

pub mod band;
pub mod budget;
pub mod direct;
pub mod files;
pub mod framed;
pub mod links;
pub mod packed_index;
pub mod pick;
pub mod scatter;
pub mod solver;
pub mod source;
pub mod workset;

pub use budget::{parse_bytes, parse_bytes_or_zero, MemoryPlan};
pub use solver::{
    solve_out_of_core, solve_out_of_core_checkpointed, OocCheckpoints, OocSolution, OocStats,
};
pub use source::{InMemorySource, ShardSetSource, SurfelSource};

use crate::storage::StorageError;
use std::path::{Path, PathBuf};

/// Why an out-of-core solve failed.
#[derive(Debug, thiserror::Error)]
pub enum OocError {
    #[error(transparent)]
    Storage(#[from] StorageError),
    #[error("cannot {action} {}: {source}", path.display())]
    Io {
        path: PathBuf,
        action: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "a memory budget of {} is too small: {what} needs about {}; give --memory {} or more",
        budget::format_bytes(*budget),
        budget::format_bytes(*needed),
        budget::format_bytes(*needed + *budget / 2)
    )]
    BudgetTooSmall {
        budget: u64,
        needed: u64,
        what: String,
    },
    #[error(
        "the work files need about {} on the disk of {}, which has {} free: no space left for \
         them; give --work-dir (or --out) a directory on a larger disk, or free space",
        budget::format_bytes(*needed),
        path.display(),
        budget::format_bytes(*free)
    )]
    DiskTooSmall {
        path: PathBuf,
        needed: u64,
        free: u64,
    },
    #[error("{source_name} cannot be solved: {what}")]
    BadData { source_name: String, what: String },
    #[error("could not start {threads} worker threads: {message}")]
    Threads { threads: usize, message: String },
    #[error(transparent)]
    Checkpoint(#[from] crate::checkpoint::CheckpointError),
    #[error("{0}")]
    Interrupted(crate::checkpoint::Interruption),
}

impl From<crate::checkpoint::Interruption> for OocError {
    fn from(i: crate::checkpoint::Interruption) -> Self {
        OocError::Interrupted(i)
    }
}

impl OocError {
    pub(crate) fn io(path: &Path, action: &'static str, source: std::io::Error) -> Self {
        OocError::Io {
            path: path.to_path_buf(),
            action,
            source,
        }
    }

    /// Whether the user can fix it by changing the input or options (exit status 2).
    pub fn is_bad_input(&self) -> bool {
        match self {
            OocError::Storage(e) => e.is_bad_input(),
            OocError::BudgetTooSmall { .. } | OocError::BadData { .. } => true,
            OocError::Checkpoint(e) => e.is_bad_input(),
            OocError::Io { .. }
            | OocError::Threads { .. }
            | OocError::DiskTooSmall { .. }
            | OocError::Interrupted(_) => false,
        }
    }
}

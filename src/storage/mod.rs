//! Out-of-core storage: shard sets on disk, read through bounded memory-map windows, sorted and
//! merged under a memory budget.
//!
//! A shard set is a directory: a `manifest.json` ([`manifest`]) and shard files ([`shard`]) of
//! fixed-size surfel records ([`record`]) sorted in one lexicographic order
//! (`geometry::order`). The contract every reader relies on: a file under a shard or manifest
//! name is complete (written under a temporary name, synced, renamed) and never changes
//! afterwards; every file carries a magic, a version and a checksum, checked on read.
//!
//! One concept per file:
//! - [`record`]: the 80-byte on-disk surfel record, encode and decode.
//! - [`shard`]: the shard file format, its writer (footer only by an explicit `finish`), its
//!   reader (magic, version, lengths, checksum) and `verify` (also the order).
//! - [`window`]: memory maps in bounded, page-aligned windows, and the record iterator over
//!   them. The only memory maps and the only `unsafe` in `storage`, with the safety argument.
//! - [`merge`]: the generic k-way merge of sorted iterators, with the tie rule as a parameter.
//! - [`external_sort`]: sorting more records than fit in a memory budget: runs and merges, the
//!   budget's split and its counters.
//! - [`manifest`]: the shard set's JSON manifest.
//! - [`error`]: [`StorageError`], which names the file and says what to do.
//! - [`write_set`]: a surfel set in memory written as a shard set.
//!
//! Used by the out-of-core solver (`outcore`) and the shard tool (`convert`, `voxrad-shard`).

pub mod error;
pub mod external_sort;
pub mod manifest;
pub mod merge;
pub mod record;
pub mod shard;
pub mod window;
pub mod write_set;

pub use error::StorageError;
pub use external_sort::{ExternalSort, SortPlan, SortStats, SortedRecords};
pub use manifest::{Manifest, MaterialEntry, ShardEntry, MANIFEST_FILE};
pub use merge::KWayMerge;
pub use record::RECORD_LEN;
pub use shard::{verify, ShardInfo, ShardReader, ShardRecords, ShardWriter, WriteOptions};
pub use window::{WindowedFile, WindowedRecords};
pub use write_set::write_shard_set;

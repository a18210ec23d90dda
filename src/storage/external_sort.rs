//! Sorting more surfels than fit in memory: sorted runs spilled to disk, then k-way merges.
//!
//! [`ExternalSort::sort`] reads its input into a run buffer; each time the buffer is full it is
//! sorted (stably) and written as a temporary shard file (a run) in a private temporary directory.
//! If the input ends before the first spill, the sort stays in memory and touches no disk. Else
//! the runs are merged `fan_in` at a time (consecutive runs together, so stability survives) until
//! at most `fan_in` remain, and the last merge streams to the caller. The output is exactly a
//! stable sort of the input by `order::sort_key`: the same for every budget.
//!
//! ## The memory guarantee
//! Everything this module holds that grows with the data lives inside `budget_bytes` (a
//! [`SortPlan`] splits it; the figures use `R` = 80-byte on-disk record, `S` = in-memory
//! `Surfel` size, `H` = the merge heap's bytes per source):
//! - run formation: a run buffer of `run_records` surfels, the stable sort's scratch space (up to
//!   the same size again) and one write buffer of `io_bytes`:
//!   `2 * S * run_records + io_bytes <= budget_bytes`;
//! - each merge: `fan_in` read buffers of `io_bytes`, `fan_in` heap entries, and one write buffer
//!   (the caller's, when the last merge streams out; [`SortedRecords::write_shard`] uses
//!   `io_bytes`): `fan_in * (io_bytes + H) + io_bytes <= budget_bytes`.
//!
//! Not counted: a fixed overhead of a few hundred bytes per open run (its path and file handle),
//! the heap's and the run list's vectors of a few words per run, and code and stack. Progress
//! needs runs of at least two records and merges of at least two runs, which with
//! `io_bytes = R` is [`ExternalSort::minimum_budget_bytes`] (a few hundred bytes); a smaller
//! budget is refused with [`StorageError::BudgetTooSmall`]. Disk use peaks at about twice the
//! input's encoded size, during an intermediate merge pass.

use super::merge::{self, KWayMerge};
use super::record::RECORD_LEN;
use super::shard::{self, ShardInfo, ShardReader, ShardWriter, WriteOptions};
use super::StorageError;
use crate::voxel::Surfel;
use std::path::{Path, PathBuf};
use tempfile::TempDir;

type Key = (i64, i64, i64);

const SURFEL_BYTES: u64 = std::mem::size_of::<Surfel>() as u64;
const HEAD_BYTES: u64 = merge::head_bytes::<Key, usize, Surfel>() as u64;
/// Beyond this, larger I/O buffers gain nothing (the kernel reads ahead anyway) and only take
/// memory from the run buffer.
const MAX_IO_BYTES: u64 = 256 << 10;

/// How a budget is split (see the module header).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SortPlan {
    pub budget_bytes: u64,
    /// Size of each read and write buffer: a whole number of records.
    pub io_bytes: u64,
    /// Records per run (the run buffer's capacity).
    pub run_records: u64,
    /// Runs merged at once.
    pub fan_in: u64,
}

impl SortPlan {
    pub fn new(budget_bytes: u64) -> Result<Self, StorageError> {
        let record = RECORD_LEN as u64;
        let io_bytes = (budget_bytes / 16 / record * record).clamp(record, MAX_IO_BYTES);
        let rest = budget_bytes.saturating_sub(io_bytes);
        let plan = SortPlan {
            budget_bytes,
            io_bytes,
            run_records: rest / (2 * SURFEL_BYTES),
            fan_in: rest / (io_bytes + HEAD_BYTES),
        };
        if plan.run_records < 2 || plan.fan_in < 2 {
            return Err(StorageError::BudgetTooSmall {
                budget_bytes,
                minimum_bytes: ExternalSort::minimum_budget_bytes(),
            });
        }
        Ok(plan)
    }
}

/// What a sort did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SortStats {
    /// Records sorted.
    pub records: u64,
    /// Bytes written to temporary files (initial runs and intermediate merges).
    pub bytes_spilled: u64,
    /// Initial sorted runs written (0 if everything fitted in memory).
    pub runs: u64,
    /// Merge passes over the data, the final streaming merge included.
    pub merge_passes: u64,
}

/// A sort of surfels into one order under a memory budget (see the module header).
#[derive(Clone, Debug)]
pub struct ExternalSort {
    order: usize,
    plan: SortPlan,
    temp_parent: PathBuf,
}

impl ExternalSort {
    /// A sort into order `order` holding at most `budget_bytes` (see the module header; use
    /// `u64::MAX` for no limit), with temporary files in a new directory under `temp_parent`.
    pub fn new(order: usize, budget_bytes: u64, temp_parent: &Path) -> Result<Self, StorageError> {
        if order >= shard::ORDERS {
            return Err(StorageError::invalid(
                temp_parent,
                format!(
                    "cannot sort into order {order}: there are {}",
                    shard::ORDERS
                ),
            ));
        }
        Ok(ExternalSort {
            order,
            plan: SortPlan::new(budget_bytes)?,
            temp_parent: temp_parent.to_path_buf(),
        })
    }

    /// The smallest budget that makes progress: runs of two records, merges of two runs.
    pub const fn minimum_budget_bytes() -> u64 {
        let record = RECORD_LEN as u64;
        let runs = record + 2 * 2 * SURFEL_BYTES;
        let merges = record + 2 * (record + HEAD_BYTES);
        if runs > merges {
            runs
        } else {
            merges
        }
    }

    pub fn plan(&self) -> &SortPlan {
        &self.plan
    }

    /// Sorts `input` (stably, by `order::sort_key` of the voxel). Runs are spilled as the input
    /// is read; the returned iterator performs the last merge as it is consumed.
    pub fn sort<I>(&self, input: I) -> Result<SortedRecords, StorageError>
    where
        I: IntoIterator<Item = Surfel>,
    {
        let order = self.order;
        let mut stats = SortStats::default();
        let mut spill: Option<Spill> = None;
        let mut buffer: Vec<Surfel> = Vec::new();
        for s in input {
            if buffer.len() as u64 == self.plan.run_records {
                let spill = match &mut spill {
                    Some(spill) => spill,
                    None => spill.insert(Spill::new(&self.temp_parent, order, self.plan)?),
                };
                spill.write_run(&mut buffer, &mut stats)?;
            }
            if buffer.len() == buffer.capacity() {
                // Grow by doubling, but never past the run size: the buffer's capacity, not its
                // length, is what the budget has to hold.
                let want = (buffer.capacity() as u64 * 2)
                    .max(64)
                    .min(self.plan.run_records) as usize;
                buffer.reserve_exact(want - buffer.len());
            }
            buffer.push(s);
            stats.records += 1;
        }
        let Some(mut spill) = spill else {
            buffer.sort_by_key(|s| shard::key(order, s));
            return Ok(SortedRecords {
                inner: Box::new(buffer.into_iter().map(Ok)),
                stats,
                _dir: None,
            });
        };
        if !buffer.is_empty() {
            spill.write_run(&mut buffer, &mut stats)?;
        }
        // Give the run buffer back before merging: the merges need the budget.
        drop(buffer);
        while spill.runs.len() as u64 > self.plan.fan_in {
            spill.merge_pass(&mut stats)?;
        }
        stats.merge_passes += 1;
        let merged = merge_runs(&spill.runs, order, self.plan.io_bytes)?;
        Ok(SortedRecords {
            inner: Box::new(merged),
            stats,
            _dir: Some(spill.dir),
        })
    }
}

/// The temporary directory and the runs in it, in input order.
struct Spill {
    dir: TempDir,
    order: usize,
    plan: SortPlan,
    runs: Vec<PathBuf>,
    next_name: u64,
}

impl Spill {
    fn new(parent: &Path, order: usize, plan: SortPlan) -> Result<Self, StorageError> {
        let dir = tempfile::Builder::new()
            .prefix("voxrad-sort-")
            .tempdir_in(parent)
            .map_err(|e| StorageError::io(parent, "create a temporary directory in", e))?;
        Ok(Spill {
            dir,
            order,
            plan,
            runs: Vec::new(),
            next_name: 0,
        })
    }

    fn writer(&mut self) -> Result<ShardWriter, StorageError> {
        let path = self
            .dir
            .path()
            .join(format!("run-{:06}.vxs", self.next_name));
        self.next_name += 1;
        // Runs live only as long as the sort; syncing them would only cost time.
        let options = WriteOptions {
            buffer_bytes: self.plan.io_bytes as usize,
            sync: false,
        };
        ShardWriter::create_with(&path, self.order, options)
    }

    /// Sorts the buffer, writes it as the next run and empties it (keeping its capacity).
    fn write_run(
        &mut self,
        buffer: &mut Vec<Surfel>,
        stats: &mut SortStats,
    ) -> Result<(), StorageError> {
        let order = self.order;
        buffer.sort_by_key(|s| shard::key(order, s));
        let mut w = self.writer()?;
        for s in buffer.iter() {
            w.push(s)?;
        }
        let info = w.finish()?;
        buffer.clear();
        stats.runs += 1;
        stats.bytes_spilled += info.bytes;
        self.runs.push(info.path);
        Ok(())
    }

    /// Merges consecutive groups of `fan_in` runs into one run each, deleting the inputs.
    fn merge_pass(&mut self, stats: &mut SortStats) -> Result<(), StorageError> {
        let old = std::mem::take(&mut self.runs);
        for group in old.chunks(self.plan.fan_in as usize) {
            let mut w = self.writer()?;
            for s in merge_runs(group, self.order, self.plan.io_bytes)? {
                w.push(&s?)?;
            }
            let info = w.finish()?;
            stats.bytes_spilled += info.bytes;
            self.runs.push(info.path);
            for path in group {
                std::fs::remove_file(path).map_err(|e| StorageError::io(path, "remove", e))?;
            }
        }
        stats.merge_passes += 1;
        Ok(())
    }
}

/// A stable merge of the runs at `paths`, each read through a buffer of `io_bytes`.
fn merge_runs(
    paths: &[PathBuf],
    order: usize,
    io_bytes: u64,
) -> Result<impl Iterator<Item = Result<Surfel, StorageError>> + Send, StorageError> {
    let sources = paths
        .iter()
        .map(|p| ShardReader::open_lazy(p)?.records(io_bytes as usize))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(KWayMerge::new(
        sources,
        move |s: &Surfel| shard::key(order, s),
        merge::by_source,
    ))
}

/// The sorted records, produced as they are consumed. Holds the temporary runs until dropped.
pub struct SortedRecords {
    /// `Send`, so that a sort can feed a pass running on another thread.
    inner: Box<dyn Iterator<Item = Result<Surfel, StorageError>> + Send>,
    stats: SortStats,
    _dir: Option<TempDir>,
}

impl SortedRecords {
    pub fn stats(&self) -> &SortStats {
        &self.stats
    }

    /// Streams the sorted records into a new shard file at `path` through a write buffer of
    /// `buffer_bytes`, and returns it with the sort's statistics.
    pub fn write_shard(
        self,
        path: &Path,
        order: usize,
        buffer_bytes: usize,
    ) -> Result<(ShardInfo, SortStats), StorageError> {
        let stats = self.stats;
        let options = WriteOptions {
            buffer_bytes,
            sync: true,
        };
        let mut w = ShardWriter::create_with(path, order, options)?;
        for s in self {
            w.push(&s?)?;
        }
        Ok((w.finish()?, stats))
    }
}

impl Iterator for SortedRecords {
    type Item = Result<Surfel, StorageError>;

    fn next(&mut self) -> Option<Self::Item> {
        self.inner.next()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::record::tests::{random_surfel, SplitMix};

    fn input(n: usize) -> Vec<Surfel> {
        let mut rng = SplitMix(2024);
        // A small span: many surfels share a voxel, so the stability of ties is tested.
        (0..n).map(|_| random_surfel(&mut rng, 5)).collect()
    }

    fn sorted(order: usize, budget_bytes: u64, data: &[Surfel]) -> (Vec<Surfel>, SortStats) {
        let dir = tempfile::TempDir::new().unwrap();
        let sorter = ExternalSort::new(order, budget_bytes, dir.path()).unwrap();
        let out = sorter.sort(data.iter().copied()).unwrap();
        let stats = *out.stats();
        let records = out.collect::<Result<Vec<_>, _>>().unwrap();
        // The temporary directory goes with the iterator.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        (records, stats)
    }

    #[test]
    fn every_budget_gives_the_in_memory_stable_sort() {
        let n = 3000;
        let data = input(n);
        let encoded = (n * RECORD_LEN) as u64;
        for order in 0..4 {
            let mut expected = data.clone();
            expected.sort_by_key(|s| shard::key(order, s));
            for budget in [1 << 10, 64 << 10, u64::MAX] {
                let (records, stats) = sorted(order, budget, &data);
                assert_eq!(records, expected, "order {order}, budget {budget}");
                assert_eq!(stats.records, n as u64);
                let plan = SortPlan::new(budget).unwrap();
                if budget == u64::MAX {
                    assert_eq!(
                        stats,
                        SortStats {
                            records: n as u64,
                            ..Default::default()
                        }
                    );
                    continue;
                }
                let runs = (n as u64).div_ceil(plan.run_records);
                assert_eq!(stats.runs, runs, "budget {budget}: {plan:?}");
                // Each pass divides the number of runs by the fan-in.
                let mut passes = 1;
                let mut left = runs;
                while left > plan.fan_in {
                    left = left.div_ceil(plan.fan_in);
                    passes += 1;
                }
                assert_eq!(stats.merge_passes, passes, "budget {budget}: {plan:?}");
                // The runs and every pass but the last (which streams out) write all the data once,
                // plus a header and footer per file.
                assert!(stats.bytes_spilled >= encoded * passes, "{stats:?}");
                assert!(
                    stats.bytes_spilled <= (encoded + runs * 52) * passes,
                    "{stats:?}"
                );
            }
        }
    }

    #[test]
    fn a_tiny_budget_needs_several_merge_passes() {
        let plan = SortPlan::new(1 << 10).unwrap();
        assert_eq!(plan.io_bytes, 80);
        assert!(plan.run_records >= 2 && plan.fan_in >= 2, "{plan:?}");
        let (_, stats) = sorted(1, 1 << 10, &input(3000));
        assert!(stats.merge_passes >= 3, "{stats:?}");
    }

    #[test]
    fn an_impossible_budget_is_refused_clearly() {
        let dir = tempfile::TempDir::new().unwrap();
        let min = ExternalSort::minimum_budget_bytes();
        assert!(min < 10 * RECORD_LEN as u64, "a few records: {min}");
        let e = ExternalSort::new(0, min - 1, dir.path()).unwrap_err();
        assert!(matches!(e, StorageError::BudgetTooSmall { .. }), "{e}");
        assert!(e.to_string().contains(&min.to_string()), "{e}");
        // The minimum itself works.
        let data = input(100);
        let (records, _) = sorted(0, min, &data);
        let mut expected = data;
        expected.sort_by_key(|s| shard::key(0, s));
        assert_eq!(records, expected);
    }

    #[test]
    fn sorted_output_writes_a_valid_shard() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("sorted.vxs");
        let sorter = ExternalSort::new(3, 16 << 10, dir.path()).unwrap();
        let (info, stats) = sorter
            .sort(input(1000))
            .unwrap()
            .write_shard(&path, 3, 4096)
            .unwrap();
        assert_eq!(info.count, 1000);
        assert!(stats.runs > 1);
        assert_eq!(shard::verify(&path).unwrap(), info);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}

//! Sorting voxelization pieces (one triangle's share of one voxel) into shard order under a
//! memory budget: sorted runs spilled to scratch files, then k-way merges (`storage::merge`).
//!
//! This is the piece-level twin of `storage::external_sort`, which sorts finished surfels. Pieces
//! are sorted rather than surfels because a surfel is the combination of all the pieces of one
//! (voxel, plane group, facing), and those pieces come from different triangles, far apart in the
//! input: sorting the pieces brings them together, and the merged stream then turns into surfels
//! in one pass, already in shard order. The key is the voxel's `order::sort_key` followed by
//! [`Piece::merge_key`] (group, facing, material, triangle), which is unique per piece: the
//! result does not depend on the budget, the run boundaries or the sorting algorithm, and the
//! pieces of each surfel come out in exactly the order the in-memory voxelizer merges them.
//!
//! Scratch files ("runs") keep the pieces' `f64` values bit for bit: a run record is
//! [`PIECE_LEN`] bytes, little-endian, no header. They are private to one conversion, deleted
//! with their directory, never synced; each run's CRC-32 is kept in memory and checked when the
//! run has been read back, so a disk that returns wrong bytes cannot slip into a shard set.
//!
//! ## The memory guarantee
//! With `P` = in-memory piece size, `H` = the merge heap's bytes per source, a [`PiecePlan`]
//! splits `budget_bytes` so that
//! - run formation holds `run_pieces * P + io_bytes` (the buffer, sorted in place, and one write
//!   buffer);
//! - each merge holds `fan_in * (io_bytes + H) + out_bytes`, `out_bytes` being the caller's
//!   output buffer (the shard writer), also taken from the budget.
//!
//! Not counted: a few hundred bytes per open run (its path, handle and hasher), code and stack.

use super::ConvertError;
use crate::geometry::order;
use crate::storage::merge::{self, KWayMerge};
use crate::storage::StorageError;
use crate::voxel::voxelize::Piece;
use glam::DVec3;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use tempfile::TempDir;

/// Bytes of one piece in a run file.
pub const PIECE_LEN: usize = 132;

type Key = ((i64, i64, i64), (u32, u8, u32, u32));

const PIECE_BYTES: u64 = std::mem::size_of::<Piece>() as u64;
const HEAD_BYTES: u64 = merge::head_bytes::<Key, usize, Piece>() as u64;
const MAX_IO_BYTES: u64 = 256 << 10;

/// The sort key of a piece in order `order`.
pub(crate) fn key(order: usize, p: &Piece) -> Key {
    (order::sort_key(order, p.voxel), p.merge_key())
}

fn encode(p: &Piece, out: &mut [u8; PIECE_LEN]) {
    let mut at = 0;
    let mut put = |bytes: &[u8]| {
        out[at..at + bytes.len()].copy_from_slice(bytes);
        at += bytes.len();
    };
    for v in p.voxel {
        put(&v.to_le_bytes());
    }
    for v in [p.group, p.side as u32, p.material, p.triangle] {
        put(&v.to_le_bytes());
    }
    put(&p.area.to_le_bytes());
    for v in [p.centroid_sum, p.contact, p.lo, p.hi] {
        for c in v.to_array() {
            put(&c.to_le_bytes());
        }
    }
    debug_assert_eq!(at, PIECE_LEN);
}

fn decode(b: &[u8; PIECE_LEN]) -> Piece {
    let u = |i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
    let f = |i: usize| {
        let mut w = [0u8; 8];
        w.copy_from_slice(&b[i..i + 8]);
        f64::from_le_bytes(w)
    };
    let v = |i: usize| DVec3::new(f(i), f(i + 8), f(i + 16));
    Piece {
        voxel: [u(0) as i32, u(4) as i32, u(8) as i32],
        group: u(12),
        side: u(16) as u8,
        material: u(20),
        triangle: u(24),
        area: f(28),
        centroid_sum: v(36),
        contact: v(60),
        lo: v(84),
        hi: v(108),
    }
}

/// How a budget is split (see the module header).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PiecePlan {
    pub budget_bytes: u64,
    /// Each read and write buffer: a whole number of pieces.
    pub io_bytes: u64,
    /// The output buffer of the final merge (the shard writer's), in whole surfel records.
    pub out_bytes: u64,
    /// Pieces per run.
    pub run_pieces: u64,
    /// Runs merged at once.
    pub fan_in: u64,
}

impl PiecePlan {
    /// Below this the fixed costs (code, stack, the scene, a few buffers) dwarf the budget and a
    /// conversion would make absurd numbers of tiny runs; refusing is more useful.
    pub const MIN_BUDGET_BYTES: u64 = 64 << 10;

    pub fn new(budget_bytes: u64) -> Result<Self, ConvertError> {
        let record = PIECE_LEN as u64;
        let io_bytes = (budget_bytes / 32 / record * record).clamp(record, MAX_IO_BYTES);
        let surfel = crate::storage::RECORD_LEN as u64;
        let out_bytes = (budget_bytes / 32 / surfel * surfel).clamp(surfel, MAX_IO_BYTES);
        let plan = PiecePlan {
            budget_bytes,
            io_bytes,
            out_bytes,
            run_pieces: budget_bytes.saturating_sub(io_bytes) / PIECE_BYTES,
            fan_in: budget_bytes.saturating_sub(out_bytes) / (io_bytes + HEAD_BYTES),
        };
        if budget_bytes < Self::MIN_BUDGET_BYTES || plan.run_pieces < 2 || plan.fan_in < 2 {
            return Err(ConvertError::BadInput(format!(
                "--memory {budget_bytes} bytes is too small: a conversion needs at least {} \
                 ({} KiB); give a larger --memory",
                Self::MIN_BUDGET_BYTES,
                Self::MIN_BUDGET_BYTES >> 10
            )));
        }
        Ok(plan)
    }
}

/// What a piece sort did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct PieceStats {
    pub pieces: u64,
    /// Sorted runs written (0 if every piece fitted in one buffer).
    pub runs: u64,
    /// Merge passes, the final streaming one included (0 without runs).
    pub merge_passes: u64,
    /// Bytes written to scratch files.
    pub bytes_spilled: u64,
    /// The largest number of pieces held in memory at once.
    pub peak_buffered: u64,
}

struct Run {
    path: PathBuf,
    count: u64,
    crc32: u32,
}

/// Collects pieces, spilling sorted runs when the buffer is full; [`PieceSorter::finish`] gives
/// them back merged.
pub(crate) struct PieceSorter {
    order: usize,
    plan: PiecePlan,
    parallel: bool,
    buffer: Vec<Piece>,
    dir: TempDir,
    runs: Vec<Run>,
    next_name: u64,
    stats: PieceStats,
}

/// Scratch files are this program's own: whatever goes wrong with them is never bad input.
fn io_err(path: &Path, action: &'static str, e: std::io::Error) -> ConvertError {
    ConvertError::Failure(
        StorageError::Io {
            path: path.to_path_buf(),
            action,
            source: e,
        }
        .to_string(),
    )
}

impl PieceSorter {
    /// A sorter into order `order` with scratch files in a new directory under `scratch`.
    /// `parallel` sorts each run with rayon's pool.
    pub fn new(
        order: usize,
        plan: PiecePlan,
        scratch: &Path,
        parallel: bool,
    ) -> Result<Self, ConvertError> {
        let dir = tempfile::Builder::new()
            .prefix("voxrad-pieces-")
            .tempdir_in(scratch)
            .map_err(|e| io_err(scratch, "create a temporary directory in", e))?;
        Ok(PieceSorter {
            order,
            plan,
            parallel,
            buffer: Vec::new(),
            dir,
            runs: Vec::new(),
            next_name: 0,
            stats: PieceStats::default(),
        })
    }

    pub fn push(&mut self, p: Piece) -> Result<(), ConvertError> {
        if self.buffer.len() as u64 == self.plan.run_pieces {
            self.spill()?;
        }
        if self.buffer.capacity() == 0 {
            // The whole run buffer at once, never grown: growing would hold the old and the new
            // buffer together for a moment, half as much again as the budget. Pages untouched
            // (a small scene) cost address space only, which the budget covers anyway.
            self.buffer.reserve_exact(self.plan.run_pieces as usize);
        }
        self.buffer.push(p);
        self.stats.pieces += 1;
        self.stats.peak_buffered = self.stats.peak_buffered.max(self.buffer.len() as u64);
        Ok(())
    }

    fn sort_buffer(&mut self) {
        let order = self.order;
        if self.parallel {
            use rayon::slice::ParallelSliceMut;
            self.buffer.par_sort_unstable_by_key(|p| key(order, p));
        } else {
            self.buffer.sort_unstable_by_key(|p| key(order, p));
        }
    }

    fn run_path(&mut self) -> PathBuf {
        let path = self
            .dir
            .path()
            .join(format!("run-{:06}.pieces", self.next_name));
        self.next_name += 1;
        path
    }

    fn write_run(
        &mut self,
        pieces: impl Iterator<Item = Result<Piece, ConvertError>>,
    ) -> Result<Run, ConvertError> {
        let path = self.run_path();
        let file = File::create(&path).map_err(|e| io_err(&path, "create", e))?;
        let mut out = BufWriter::with_capacity(self.plan.io_bytes as usize, file);
        let mut hasher = crc32fast::Hasher::new();
        let mut count = 0u64;
        let mut bytes = [0u8; PIECE_LEN];
        for p in pieces {
            encode(&p?, &mut bytes);
            hasher.update(&bytes);
            out.write_all(&bytes)
                .map_err(|e| io_err(&path, "write", e))?;
            count += 1;
        }
        out.flush().map_err(|e| io_err(&path, "write", e))?;
        self.stats.bytes_spilled += count * PIECE_LEN as u64;
        Ok(Run {
            path,
            count,
            crc32: hasher.finalize(),
        })
    }

    fn spill(&mut self) -> Result<(), ConvertError> {
        self.sort_buffer();
        let buffer = std::mem::take(&mut self.buffer);
        let run = self.write_run(buffer.iter().map(|p| Ok(*p)))?;
        self.buffer = buffer;
        self.buffer.clear();
        self.runs.push(run);
        self.stats.runs += 1;
        Ok(())
    }

    /// The pieces sorted, as they are consumed. Merges runs `fan_in` at a time until at most
    /// `fan_in` remain; the last merge streams out.
    pub fn finish(mut self) -> Result<SortedPieces, ConvertError> {
        if self.runs.is_empty() {
            self.sort_buffer();
            let stats = self.stats;
            let buffer = std::mem::take(&mut self.buffer);
            return Ok(SortedPieces {
                inner: Box::new(buffer.into_iter().map(Ok)),
                stats,
                _dir: self.dir,
            });
        }
        if !self.buffer.is_empty() {
            self.spill()?;
        }
        // The run buffer goes back before merging: the merges need the budget.
        self.buffer = Vec::new();
        while self.runs.len() as u64 > self.plan.fan_in {
            let old = std::mem::take(&mut self.runs);
            for group in old.chunks(self.plan.fan_in as usize) {
                let merged = merge_runs(group, self.order, self.plan.io_bytes)?;
                let run = self.write_run(merged)?;
                self.runs.push(run);
                for r in group {
                    std::fs::remove_file(&r.path).map_err(|e| io_err(&r.path, "remove", e))?;
                }
            }
            self.stats.merge_passes += 1;
        }
        self.stats.merge_passes += 1;
        let merged = merge_runs(&self.runs, self.order, self.plan.io_bytes)?;
        Ok(SortedPieces {
            inner: Box::new(merged),
            stats: self.stats,
            _dir: self.dir,
        })
    }
}

/// A run read back through a buffer, its CRC checked after the last piece.
struct RunReader {
    path: PathBuf,
    file: BufReader<File>,
    left: u64,
    crc32: u32,
    hasher: crc32fast::Hasher,
    done: bool,
}

impl Iterator for RunReader {
    type Item = Result<Piece, ConvertError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        if self.left == 0 {
            self.done = true;
            let computed = self.hasher.clone().finalize();
            return (computed != self.crc32).then(|| {
                Err(ConvertError::Failure(format!(
                    "scratch file {} of the external sort reads back with checksum {computed:#010x}, \
                     not the {:#010x} written: the disk or file system returned wrong data",
                    self.path.display(),
                    self.crc32
                )))
            });
        }
        let mut b = [0u8; PIECE_LEN];
        if let Err(e) = self.file.read_exact(&mut b) {
            self.done = true;
            return Some(Err(io_err(&self.path, "read", e)));
        }
        self.hasher.update(&b);
        self.left -= 1;
        Some(Ok(decode(&b)))
    }
}

fn merge_runs(
    runs: &[Run],
    order: usize,
    io_bytes: u64,
) -> Result<impl Iterator<Item = Result<Piece, ConvertError>> + Send, ConvertError> {
    let sources = runs
        .iter()
        .map(|r| {
            let file = File::open(&r.path).map_err(|e| io_err(&r.path, "read", e))?;
            Ok(RunReader {
                path: r.path.clone(),
                file: BufReader::with_capacity(io_bytes as usize, file),
                left: r.count,
                crc32: r.crc32,
                hasher: crc32fast::Hasher::new(),
                done: false,
            })
        })
        .collect::<Result<Vec<_>, ConvertError>>()?;
    // Keys are unique, so the tie rule never decides anything; the stable one is as good as any.
    Ok(KWayMerge::new(
        sources,
        move |p: &Piece| key(order, p),
        merge::by_source,
    ))
}

/// The sorted pieces, produced as they are consumed. Holds the scratch runs until dropped.
pub(crate) struct SortedPieces {
    inner: Box<dyn Iterator<Item = Result<Piece, ConvertError>> + Send>,
    stats: PieceStats,
    _dir: TempDir,
}

impl SortedPieces {
    pub fn stats(&self) -> &PieceStats {
        &self.stats
    }
}

impl Iterator for SortedPieces {
    type Item = Result<Piece, ConvertError>;

    fn next(&mut self) -> Option<Self::Item> {
        self.inner.next()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn piece(k: u64) -> Piece {
        let f = |s: u64| ((k.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> s) % 1000) as f64 / 997.0;
        Piece {
            voxel: [(k % 7) as i32 - 3, (k % 5) as i32, (k % 3) as i32],
            group: (k % 4) as u32,
            side: (k % 2) as u8,
            material: (k % 3) as u32,
            triangle: k as u32,
            area: f(3),
            centroid_sum: DVec3::new(f(5), f(7), f(11)),
            contact: DVec3::new(f(13), f(17), f(19)),
            lo: DVec3::new(f(23), f(29), f(31)),
            hi: DVec3::new(f(37), f(41), f(43)),
        }
    }

    #[test]
    fn encoding_is_bit_exact() {
        for k in 0..100 {
            let p = piece(k * 7919 + 1);
            let mut b = [0u8; PIECE_LEN];
            encode(&p, &mut b);
            assert_eq!(decode(&b), p);
        }
    }

    #[test]
    fn every_budget_gives_the_same_order() {
        let input: Vec<Piece> = (0..5000).map(|k| piece(k * 31 + 5)).collect();
        let mut expected = input.clone();
        expected.sort_by_key(|p| key(2, p));
        for budget in [64 << 10, 200 << 10, 1 << 30] {
            let dir = tempfile::TempDir::new().unwrap();
            let plan = PiecePlan::new(budget).unwrap();
            let mut sorter = PieceSorter::new(2, plan, dir.path(), budget > 100 << 10).unwrap();
            for p in &input {
                sorter.push(*p).unwrap();
            }
            let sorted = sorter.finish().unwrap();
            let stats = *sorted.stats();
            let out: Vec<Piece> = sorted.collect::<Result<_, _>>().unwrap();
            assert_eq!(out, expected, "budget {budget}");
            assert!(stats.peak_buffered <= plan.run_pieces, "{stats:?}");
            if budget == 1 << 30 {
                assert_eq!(stats.runs, 0);
            } else {
                assert_eq!(stats.runs, 5000u64.div_ceil(plan.run_pieces), "{stats:?}");
            }
            assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        }
    }

    /// More runs than one merge takes: intermediate passes, the same order.
    #[test]
    fn many_runs_take_several_merge_passes() {
        let budget = 64 << 10;
        let plan = PiecePlan::new(budget).unwrap();
        let n = plan.run_pieces * plan.fan_in * 2;
        let input: Vec<Piece> = (0..n).map(|k| piece(k * 13 + 2)).collect();
        let dir = tempfile::TempDir::new().unwrap();
        let mut sorter = PieceSorter::new(0, plan, dir.path(), false).unwrap();
        for p in &input {
            sorter.push(*p).unwrap();
        }
        let sorted = sorter.finish().unwrap();
        let stats = *sorted.stats();
        let out: Vec<Piece> = sorted.collect::<Result<_, _>>().unwrap();
        let mut expected = input;
        expected.sort_by_key(|p| key(0, p));
        assert!(out == expected);
        assert!(stats.runs > plan.fan_in, "{stats:?} {plan:?}");
        assert_eq!(stats.merge_passes, 2, "{stats:?} {plan:?}");
        // The runs, then the intermediate pass, each wrote every piece once.
        assert_eq!(stats.bytes_spilled, 2 * n * PIECE_LEN as u64);
    }

    #[test]
    fn a_damaged_run_is_an_error() {
        let plan = PiecePlan::new(64 << 10).unwrap();
        let dir = tempfile::TempDir::new().unwrap();
        let mut sorter = PieceSorter::new(0, plan, dir.path(), false).unwrap();
        for k in 0..plan.run_pieces * 2 {
            sorter.push(piece(k)).unwrap();
        }
        let run = sorter.runs[0].path.clone();
        let mut bytes = std::fs::read(&run).unwrap();
        bytes[PIECE_LEN + 40] ^= 1;
        std::fs::write(&run, bytes).unwrap();
        let items: Vec<_> = sorter.finish().unwrap().collect();
        let e = items.last().unwrap().as_ref().unwrap_err();
        assert!(e.to_string().contains("checksum"), "{e}");
        assert_eq!(e.exit_code(), 1, "a scratch file is not the user's input");
    }

    #[test]
    fn tiny_budgets_are_refused() {
        let e = PiecePlan::new(1024).unwrap_err();
        assert!(e.to_string().contains("too small"), "{e}");
    }
}

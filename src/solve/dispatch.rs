//! Dispatch: putting the surfels of one direction into their discrete lines.
//!
//! The surfels arrive in the lexicographic order that sorts every line along the direction
//! (`geometry::order`). Following the paper's section 3.1, each thread takes an equal, contiguous
//! part of that order and dispatches it into its own partial lists; the partial lists of a line
//! are then stitched end to end. Here the lists live in one array: a counting pass gives each
//! (line, thread) pair its slot range, laid out so that thread `t`'s partial list of a line sits
//! just before thread `t + 1`'s. Stitching therefore costs nothing, no list is ever re-sorted, and
//! the result is the same array for any thread count.

use crate::geometry::lines::LineFrame;
use rayon::prelude::*;

/// A surfel in an order: its voxel (for the line index) and its index in the surfel set.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OrderedEntry {
    pub voxel: [i32; 3],
    pub index: u32,
}

/// The surfels of `set` in each of the four lexicographic orders (`geometry::order`), sorted once
/// per solve: every direction's dispatch reads the order of its octant.
pub fn lexicographic_orders(set: &crate::voxel::SurfelSet) -> Vec<Vec<OrderedEntry>> {
    (0..4)
        .into_par_iter()
        .map(|o| {
            let mut entries: Vec<OrderedEntry> = set
                .surfels
                .iter()
                .enumerate()
                .map(|(i, s)| OrderedEntry {
                    voxel: s.voxel,
                    index: i as u32,
                })
                .collect();
            entries.sort_by_key(|e| (crate::geometry::order::sort_key(o, e.voxel), e.index));
            entries
        })
        .collect()
}

/// The lines of one direction: `members[starts[l]..starts[l + 1]]` are line `l`'s surfel indices,
/// sorted along the direction. Buffers are reused across directions.
#[derive(Default)]
pub struct Lines {
    pub starts: Vec<u32>,
    pub members: Vec<u32>,
    /// Per thread: slot counters, then next free slot, per line.
    counters: Vec<Vec<u32>>,
    /// Per thread: the line of each surfel of its part, found by the counting pass and read
    /// again by the filling pass (about a sixth of a dispatch's instructions went to finding
    /// it twice).
    line_of: Vec<Vec<u32>>,
}

impl Lines {
    pub fn line_count(&self) -> usize {
        self.starts.len().saturating_sub(1)
    }

    /// Surfel indices of line `line`, in order along the direction.
    pub fn line(&self, line: usize) -> &[u32] {
        &self.members[self.starts[line] as usize..self.starts[line + 1] as usize]
    }
}

/// A dense numbering of the lines a dispatch fills: all lines of a direction ([`LineFrame`]) or
/// a band of them (the out-of-core solver's).
pub trait LineNumbering: Sync {
    /// Number of lines; every index is below it.
    fn line_count(&self) -> usize;
    /// Dense index of the line through `voxel`.
    fn line_index(&self, voxel: [i32; 3]) -> u64;
}

impl LineNumbering for LineFrame {
    fn line_count(&self) -> usize {
        self.line_count as usize
    }

    #[inline]
    fn line_index(&self, voxel: [i32; 3]) -> u64 {
        LineFrame::line_index(self, voxel)
    }
}

/// Fills `lines` for `frame` from `ordered` using `threads` contiguous parts.
pub fn dispatch<F: LineNumbering>(
    ordered: &[OrderedEntry],
    frame: &F,
    threads: usize,
    lines: &mut Lines,
) {
    let line_count = frame.line_count();
    // Line indices are kept as `u32`, as the slots are: a grid with more lines than that would
    // need counters of 16 GiB a thread.
    assert!(
        u32::try_from(line_count).is_ok(),
        "{line_count} lines in one direction: more than a dispatch can count"
    );
    let parts = threads.max(1);
    let part_len = ordered.len().div_ceil(parts).max(1);
    lines.counters.resize_with(parts, Vec::new);
    lines.line_of.resize_with(parts, Vec::new);
    // 1. Each thread counts its part's surfels per line.
    lines
        .counters
        .par_iter_mut()
        .zip(lines.line_of.par_iter_mut())
        .enumerate()
        .for_each(|(t, (counts, line_of))| {
            counts.clear();
            counts.resize(line_count, 0);
            let part = ordered.chunks(part_len).nth(t).unwrap_or(&[]);
            line_of.clear();
            line_of.extend(part.iter().map(|e| {
                let line = frame.line_index(e.voxel) as u32;
                counts[line as usize] += 1;
                line
            }));
        });
    // 2. Slot ranges: line by line, thread by thread (partial lists laid end to end). A prefix
    // sum over the lines, in blocks of lines on the threads: each block's total, then the
    // blocks' starts, then each block's slots (in one thread, the other threads waited: at
    // resolution 256 a direction has up to a million lines).
    lines.starts.clear();
    lines.starts.resize(line_count + 1, 0);
    let block_len = line_count.div_ceil(parts * 8).max(1);
    let block_totals: Vec<u32> = (0..line_count.div_ceil(block_len))
        .into_par_iter()
        .map(|b| {
            let range = b * block_len..((b + 1) * block_len).min(line_count);
            lines
                .counters
                .iter()
                .map(|counts| counts[range.clone()].iter().sum::<u32>())
                .sum()
        })
        .collect();
    let mut block_starts = Vec::with_capacity(block_totals.len());
    let mut next = 0u32;
    for total in &block_totals {
        block_starts.push(next);
        next += total;
    }
    lines.starts[line_count] = next;
    // Each block gets its part of `starts` and of every thread's counters.
    let mut blocks: Vec<LineBlock> = Vec::new();
    let mut starts_rest = &mut lines.starts[..line_count];
    let mut counts_rest: Vec<&mut [u32]> = lines
        .counters
        .iter_mut()
        .map(|c| c.as_mut_slice())
        .collect();
    for &start in &block_starts {
        let len = block_len.min(starts_rest.len());
        let (starts, tail) = std::mem::take(&mut starts_rest).split_at_mut(len);
        starts_rest = tail;
        let mut counts = Vec::with_capacity(counts_rest.len());
        for rest in counts_rest.iter_mut() {
            let (head, tail) = std::mem::take(rest).split_at_mut(len);
            counts.push(head);
            *rest = tail;
        }
        blocks.push((start, starts, counts));
    }
    blocks
        .into_par_iter()
        .for_each(|(mut next, starts, mut counts)| {
            for (l, start) in starts.iter_mut().enumerate() {
                *start = next;
                for thread_counts in counts.iter_mut() {
                    let c = thread_counts[l];
                    thread_counts[l] = next;
                    next += c;
                }
            }
        });
    // 3. Each thread appends its part to its partial lists, keeping the order.
    lines.members.clear();
    lines.members.resize(ordered.len(), 0);
    let members = SharedSlots(lines.members.as_mut_ptr());
    lines
        .counters
        .par_iter_mut()
        .zip(lines.line_of.par_iter())
        .enumerate()
        .for_each(|(t, (slots, line_of))| {
            let part = ordered.chunks(part_len).nth(t).unwrap_or(&[]);
            for (e, &line) in part.iter().zip(line_of) {
                let slot = &mut slots[line as usize];
                // SAFETY: the slot ranges of different (line, thread) pairs are disjoint and lie in
                // `0..ordered.len()` (step 2 hands out exactly `ordered.len()` slots), so every write
                // goes to a distinct element of `members`, which outlives this loop.
                unsafe { members.write(*slot as usize, e.index) };
                *slot += 1;
            }
        });
}

/// A block of lines in step 2 of [`dispatch`]: its first slot, its part of `starts`, and its
/// part of each thread's counters.
type LineBlock<'a> = (u32, &'a mut [u32], Vec<&'a mut [u32]>);

/// A pointer to slots that threads fill at provably disjoint indices.
#[derive(Clone, Copy)]
struct SharedSlots(*mut u32);
// SAFETY: used only for writes at disjoint indices (see `dispatch`).
unsafe impl Send for SharedSlots {}
unsafe impl Sync for SharedSlots {}

impl SharedSlots {
    /// # Safety
    /// `index` must be in bounds and written by no other thread.
    unsafe fn write(self, index: usize, value: u32) {
        unsafe { *self.0.add(index) = value };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{lines::line_of, order};

    #[test]
    fn lists_are_complete_sorted_and_thread_independent() {
        let dims = [9, 7, 5];
        let mut voxels = Vec::new();
        for x in 0..9 {
            for y in 0..7 {
                for z in 0..5 {
                    if (x * 7 + y * 3 + z) % 3 != 0 {
                        voxels.push([x, y, z]);
                    }
                }
            }
        }
        for s in [[2i64, -1, 3], [-1, -1, 1], [3, 0, 0], [1, 2, 2]] {
            let o = order::order_of(s);
            let mut ordered: Vec<OrderedEntry> = voxels
                .iter()
                .enumerate()
                .map(|(i, &v)| OrderedEntry {
                    voxel: v,
                    index: i as u32,
                })
                .collect();
            ordered.sort_by_key(|e| order::sort_key(o, e.voxel));
            let frame = LineFrame::new(s, dims);
            let mut reference = Lines::default();
            dispatch(&ordered, &frame, 1, &mut reference);
            for threads in [2, 3, 8] {
                let mut lines = Lines::default();
                dispatch(&ordered, &frame, threads, &mut lines);
                assert_eq!(lines.starts, reference.starts);
                assert_eq!(lines.members, reference.members);
            }
            let mut seen = vec![false; voxels.len()];
            for l in 0..reference.line_count() {
                let line = reference.line(l);
                for w in line.windows(2) {
                    let (a, b) = (voxels[w[0] as usize], voxels[w[1] as usize]);
                    assert_eq!(line_of(s, a.map(i64::from)), line_of(s, b.map(i64::from)));
                    let along =
                        |v: [i32; 3]| v[0] as i64 * s[0] + v[1] as i64 * s[1] + v[2] as i64 * s[2];
                    assert!(along(b) > along(a));
                }
                for &m in line {
                    assert!(!seen[m as usize]);
                    seen[m as usize] = true;
                }
            }
            assert!(seen.iter().all(|&x| x));
        }
    }
}

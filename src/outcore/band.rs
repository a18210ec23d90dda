//! One direction, band by band (see the `outcore` module header): cutting the direction's line
//! columns into bands that fit the budget, reading a band's ranges of its axis copy, running the
//! in-memory dispatch and propagation on it (or, once its partner links are kept, replaying
//! them: `super::links`), and adding the gathered light to the copy's file (in place, or read
//! from one file and written to another, see [`CopyFiles::previous`]). Directions with the
//! same bands can share a pass ([`DirectionPass::run_together`]): each band is read once and
//! each direction's lines are gathered on it in turn.

use super::budget::MemoryPlan;
use super::files::{
    decode_static, AxisLight, IoCounters, Radiosity, RecordFile, LIGHT32_LEN, RADIOSITY_LEN,
    STATIC_LEN,
};
use super::framed::{FramedRuns, FramedStatics};
use super::links::BandLinks;
use super::workset::AxisCopy;
use super::OocError;
use crate::geometry::directions::Direction;
use crate::geometry::lines::LineFrame;
use crate::solve::dispatch::{dispatch, LineNumbering, Lines, OrderedEntry};
use crate::solve::jacobi::gather_all_lines;
use crate::solve::links::gather_and_record;
use crate::solve::propagate::{DirectionInput, PropSurfel};
use std::time::Instant;

/// Where a pass reads its copy's static records: an axis copy's compressed frames (the
/// one-process solver, `super::framed`), or a rank's held files, whose framed records lie end
/// to end in runs of several files (the data mode, `distribute::ooc`).
pub enum StaticFile {
    Framed(std::sync::Arc<FramedStatics>),
    Runs(std::sync::Arc<FramedRuns>),
}

impl StaticFile {
    /// Fills `out` (a whole number of records) with the records from `start` on.
    fn read(&self, start: u64, out: &mut [u8], io: &mut IoCounters) -> Result<(), OocError> {
        match self {
            StaticFile::Framed(frames) => frames.read(start, out, io),
            StaticFile::Runs(runs) => runs.read(start, out, io),
        }
    }
}

/// The open files of one axis copy, and the shared file of gathered light.
pub struct CopyFiles {
    pub statics: StaticFile,
    pub radiosity: RecordFile,
    /// Where a direction writes the light gathered so far, its own added.
    pub gathered: RecordFile,
    /// Where the light of the copy's earlier directions is read from, when not from `gathered`
    /// itself. Every direction writes every record of the copy, so two files used in turn hold
    /// the light of the directions done whole while one is in progress (the one-process solver
    /// saves it in checkpoints from there; a direction stopped by a signal leaves it intact).
    pub previous: Option<RecordFile>,
}

impl CopyFiles {
    /// A copy's files (its static records `statics`, opened once for the copy) reading the
    /// earlier directions' light from `previous` and writing it, with this direction's added,
    /// to `gathered`.
    pub fn open_from(
        copy: &AxisCopy,
        statics: &std::sync::Arc<FramedStatics>,
        previous: &std::path::Path,
        gathered: &std::path::Path,
    ) -> Result<Self, OocError> {
        Ok(CopyFiles {
            statics: StaticFile::Framed(statics.clone()),
            radiosity: RecordFile::open(&copy.radiosity)?,
            gathered: RecordFile::open(gathered)?,
            previous: Some(RecordFile::open(previous)?),
        })
    }
}

/// The arrays of one band, reused from band to band.
#[derive(Default)]
pub struct BandBuffers {
    props: Vec<PropSurfel>,
    radiosity: Vec<Radiosity>,
    gathered: Vec<AxisLight>,
    entries: Vec<OrderedEntry>,
    lines: Lines,
    ranges: Vec<(u64, u64)>,
    bytes: Vec<u8>,
    cursor: Vec<u64>,
    next_row: Vec<usize>,
    columns: Vec<u64>,
    /// A replay's bands waiting to be replayed together ([`DirectionPass::replay_group`]):
    /// each band's surfels and the end of its ranges in `group_ranges`.
    group: Vec<(u64, usize)>,
    group_ranges: Vec<(u64, u64)>,
    /// The group's ranges in file order, each with its place in `radiosity` and `gathered`.
    pieces: Vec<(u64, u64, u64)>,
    /// The light of one run of the copy, read or written at once.
    staged_radiosity: Vec<Radiosity>,
    staged_gathered: Vec<AxisLight>,
}

/// Time spent per phase of the directions, summed.
#[derive(Clone, Copy, Debug, Default)]
pub struct BandTimes {
    pub read: f64,
    pub dispatch: f64,
    pub propagate: f64,
    pub write: f64,
    pub bands: u64,
    /// Columns too big for one band, solved in blocks.
    pub tiled_columns: u64,
    /// Bands whose links were replayed, and the groups their light was read in (several
    /// consecutive bands of a direction at once, see `DirectionPass::replay_group`).
    pub replayed_bands: u64,
    pub replay_groups: u64,
    /// Passes that gathered several directions together, and the directions they gathered
    /// beyond one each (`super::solver`).
    pub joint_passes: u64,
    pub joint_directions: u64,
}

/// A block of lines: rows `i0..i0 + rows` of columns `j0..j0 + width`, numbered
/// `(i - i0) * width + j - j0`.
#[derive(Clone, Copy, Debug)]
struct Block {
    i0: u64,
    rows: u64,
    j0: u64,
    width: u64,
}

struct BandNumbering<'a> {
    frame: &'a LineFrame,
    block: Block,
}

impl LineNumbering for BandNumbering<'_> {
    fn line_count(&self) -> usize {
        (self.block.rows * self.block.width) as usize
    }

    #[inline]
    fn line_index(&self, voxel: [i32; 3]) -> u64 {
        let (su, sv) = self.frame.layer_shift(voxel[self.frame.main] as usize);
        let b = &self.block;
        (voxel[self.frame.u] as u64 + su - b.i0) * b.width
            + (voxel[self.frame.v] as u64 + sv - b.j0)
    }
}

/// Everything one direction pass needs.
pub struct DirectionPass<'a> {
    pub copy: &'a AxisCopy,
    pub files: &'a CopyFiles,
    /// The copy's row histogram.
    pub histogram: &'a [u32],
    pub dims: [u32; 3],
    pub plan: &'a MemoryPlan,
    pub threads: usize,
    /// Channels to gather (1 for a grey scene, see `solve::jacobi`).
    pub channels: usize,
    /// First direction of this copy in this iteration: the gathered file is overwritten, not
    /// added to (nothing is read from [`CopyFiles::previous`]).
    pub first: bool,
    /// A stop signal abandons the direction between two bands (one process: the solver then
    /// stops where the direction began). Under MPI the ranks must agree on where they stop, so
    /// there the signal waits for the next step's agreement.
    pub stops_on_signal: bool,
}

impl DirectionPass<'_> {
    /// Solves direction `d` over the whole copy, doing with its bands' partner links what
    /// `links` says (see `super::links`).
    pub fn run(
        &self,
        d: &Direction,
        links: &mut BandLinks,
        buffers: &mut BandBuffers,
        io: &mut IoCounters,
        times: &mut BandTimes,
    ) -> Result<(), OocError> {
        self.run_together(&[d], links, buffers, io, times)
    }

    /// Solves directions `ds` over the whole copy in one pass: each band is read once, and
    /// each direction's lines are gathered on it in turn, in the order of `ds`. Several
    /// directions must have the same bands ([`Self::band_cuts`]); `links` names one recording
    /// or reader per direction (or searches for all).
    pub fn run_together(
        &self,
        ds: &[&Direction],
        links: &mut BandLinks,
        buffers: &mut BandBuffers,
        io: &mut IoCounters,
        times: &mut BandTimes,
    ) -> Result<(), OocError> {
        let copy = self.copy;
        let alongs: Vec<Along> = ds.iter().map(|d| Along::new(d, copy, self.dims)).collect();
        let Along { frame, .. } = &alongs[0];
        // What an earlier direction stopped by a signal left waiting.
        buffers.group.clear();
        buffers.group_ranges.clear();
        self.count_columns(frame, &mut buffers.columns);
        buffers.cursor.clear();
        buffers
            .cursor
            .extend_from_slice(&copy.layer_start[..copy.layers]);
        buffers.next_row.clear();
        buffers.next_row.resize(copy.layers, 0);
        let mut j0 = 0u64;
        while j0 < frame.nj {
            // A stop signal abandons the direction (the solver checks again after it and never
            // uses its light): on a large scene one direction can take minutes, longer than a
            // batch system waits.
            if self.stops_on_signal && crate::interrupt::requested().is_some() {
                return Ok(());
            }
            let (width, surfels) = self.next_cut(frame, &buffers.columns, j0);
            let block = Block {
                i0: 0,
                rows: frame.ni,
                j0,
                width,
            };
            if surfels == 0 {
                self.take_rows(frame, j0 + width, buffers, false);
            } else if self.whole_band(frame, width, surfels) {
                self.take_rows(frame, j0 + width, buffers, true);
                let band = Band { block, surfels };
                self.process(&alongs, band, links, buffers, io, times)?;
            } else {
                // One column too big for a band (a floor seen along its own plane): cut it
                // along i as well. Its tiles follow the slope along `u`: one direction only.
                assert_eq!(
                    alongs.len(),
                    1,
                    "directions passed together have whole bands"
                );
                let column = Column {
                    vector: ds[0].vector,
                    j0,
                    surfels,
                };
                self.tiled_column(&alongs[0], column, links, buffers, io, times)?;
            }
            j0 += width;
        }
        if let BandLinks::Replay(readers, scratch) = links {
            self.replay_group(readers, scratch, buffers, io, times)?;
        }
        Ok(())
    }

    /// The surfels of each line column `j` of `frame` into `columns`.
    fn count_columns(&self, frame: &LineFrame, columns: &mut Vec<u64>) {
        let copy = self.copy;
        columns.clear();
        columns.resize(frame.nj as usize, 0);
        for z in 0..copy.layers {
            let sv = frame.layer_shift(z).1 as usize;
            let row_counts = &self.histogram[z * copy.rows..(z + 1) * copy.rows];
            for (v, &h) in row_counts.iter().enumerate() {
                columns[v + sv] += h as u64;
            }
        }
    }

    /// The band that begins at column `j0`: its width in columns, widened while it fits, and
    /// its surfels.
    fn next_cut(&self, frame: &LineFrame, columns: &[u64], j0: u64) -> (u64, u64) {
        let max_width = (self.plan.band_lines / frame.ni.max(1)).max(1);
        let mut width = 0u64;
        let mut surfels = 0u64;
        while j0 + width < frame.nj && width < max_width {
            let c = columns[(j0 + width) as usize];
            if width > 0 && surfels + c > self.plan.band_surfels {
                break;
            }
            surfels += c;
            width += 1;
        }
        (width, surfels)
    }

    /// Whether the band of `width` columns holding `surfels` is solved whole (else its one
    /// column is cut along `i` as well, [`Self::tiled_column`]).
    fn whole_band(&self, frame: &LineFrame, width: u64, surfels: u64) -> bool {
        surfels <= self.plan.band_surfels && frame.ni * width <= self.plan.band_lines
    }

    /// The bands of direction `d` as `(first column, width)`, the empty ones included, or
    /// `None` where a column is cut along `i` (its tiles follow the direction's slope along
    /// `u`). Directions whose lines have the same slope along `v` put every surfel in the same
    /// column, so where their lists are equal their bands hold the same surfels in the same
    /// order, and they can be gathered in one pass ([`Self::run_together`]).
    pub fn band_cuts(&self, d: &Direction, columns: &mut Vec<u64>) -> Option<Vec<(u64, u64)>> {
        let frame = LineFrame::new(d.vector, self.dims);
        self.count_columns(&frame, columns);
        let mut cuts = Vec::new();
        let mut j0 = 0u64;
        while j0 < frame.nj {
            let (width, surfels) = self.next_cut(&frame, columns, j0);
            if surfels > 0 && !self.whole_band(&frame, width, surfels) {
                return None;
            }
            cuts.push((j0, width));
            j0 += width;
        }
        Some(cuts)
    }

    /// Advances the per-layer row cursors past the rows of columns below `j1`, and (if
    /// `keep`) records the ranges of copy records they hold in `buffers.ranges`.
    fn take_rows(&self, frame: &LineFrame, j1: u64, buffers: &mut BandBuffers, keep: bool) {
        let copy = self.copy;
        buffers.ranges.clear();
        for z in 0..copy.layers {
            let sv = frame.layer_shift(z).1;
            let end = (j1.saturating_sub(sv) as usize).min(copy.rows);
            let row = buffers.next_row[z];
            if end > row {
                let base = z * copy.rows;
                let count: u64 = self.histogram[base + row..base + end]
                    .iter()
                    .map(|&h| h as u64)
                    .sum();
                if keep && count > 0 {
                    buffers.ranges.push((buffers.cursor[z], count));
                }
                buffers.cursor[z] += count;
                buffers.next_row[z] = end;
            }
        }
    }

    /// The voxel coordinate along `u` of copy record `index`.
    fn u_of(&self, index: u64, io: &mut IoCounters) -> Result<i64, OocError> {
        let mut record = [0u8; STATIC_LEN];
        self.files.statics.read(index, &mut record, io)?;
        let at = 4 * self.copy.u;
        let word = record[at..at + 4].try_into().expect("4 bytes");
        Ok(super::files::static_coordinate(word) as i64)
    }

    /// Solves a column `j0` holding `surfels`, in blocks of rows `i` that fit the budget. In each
    /// layer the column is one row of the copy, sorted by `u`, so a block's part of it is a
    /// contiguous range found by binary search.
    fn tiled_column(
        &self,
        along: &Along,
        column: Column,
        links: &mut BandLinks,
        buffers: &mut BandBuffers,
        io: &mut IoCounters,
        times: &mut BandTimes,
    ) -> Result<(), OocError> {
        let Column {
            vector,
            j0,
            surfels,
        } = column;
        let frame = &along.frame;
        // This column's range of the copy in each layer: [from, to).
        let mut spans: Vec<(usize, u64, u64)> = Vec::new();
        let cursor_before: Vec<u64> = buffers.cursor.clone();
        self.take_rows(frame, j0 + 1, buffers, false);
        for (z, (&before, &after)) in cursor_before.iter().zip(&buffers.cursor).enumerate() {
            if after > before {
                spans.push((z, before, after));
            }
        }
        drop(cursor_before);
        times.tiled_columns += 1;
        let capacity = self.plan.band_surfels;
        let mut remaining = surfels;
        let mut i0 = 0u64;
        let mut ends = vec![0u64; spans.len()];
        while i0 < frame.ni && remaining > 0 {
            let left = frame.ni - i0;
            let guess = (left as f64 * capacity as f64 * 0.9 / remaining as f64) as u64;
            let mut rows = guess.clamp(1, left).min(self.plan.band_lines.max(1));
            let count = loop {
                let mut count = 0;
                for (k, &(z, from, to)) in spans.iter().enumerate() {
                    let limit = (i0 + rows) as i64 - frame.layer_shift(z).0 as i64;
                    // First record of [from, to) with u >= limit: galloping from `from`, then
                    // bisection. The ends move forward block by block, so the answer is
                    // usually near `from`, in the frame of static records read last
                    // (`super::framed`): a bisection over the whole span read a frame at each
                    // probe.
                    let (mut lo, mut hi, mut step) = (from, from, 1);
                    while hi < to && self.u_of(hi, io)? < limit {
                        lo = hi + 1;
                        hi = (hi + step).min(to);
                        step *= 2;
                    }
                    while lo < hi {
                        let mid = lo + (hi - lo) / 2;
                        if self.u_of(mid, io)? < limit {
                            lo = mid + 1;
                        } else {
                            hi = mid;
                        }
                    }
                    ends[k] = lo;
                    count += lo - from;
                }
                if count <= capacity || rows == 1 {
                    break count;
                }
                rows = (rows / 2).max(1);
            };
            if count > capacity {
                return Err(OocError::BudgetTooSmall {
                    budget: self.plan.budget,
                    needed: (self.plan.budget - self.plan.working)
                        + count * super::budget::BAND_BYTES_PER_SURFEL * 4 / 3,
                    what: format!("one line of direction {vector:?} holding {count} surfels"),
                });
            }
            buffers.ranges.clear();
            for (k, span) in spans.iter_mut().enumerate() {
                if ends[k] > span.1 {
                    buffers.ranges.push((span.1, ends[k] - span.1));
                }
                span.1 = ends[k];
            }
            if count > 0 {
                let block = Block {
                    i0,
                    rows,
                    j0,
                    width: 1,
                };
                let band = Band {
                    block,
                    surfels: count,
                };
                let one = std::slice::from_ref(along);
                self.process(one, band, links, buffers, io, times)?;
            }
            remaining -= count;
            i0 += rows;
        }
        Ok(())
    }

    /// Reads the records of `buffers.ranges` (`band.surfels` of them), solves their lines,
    /// which all lie in `band.block`, and adds the light gathered to the copy's file. A replay
    /// of links only sets the band aside: its light is read, and its links replayed, with the
    /// bands after it ([`Self::replay_group`]). With several directions (`alongs`, whose bands
    /// are the same), the band is read once and each direction's lines are gathered on it in
    /// turn; `band.block` is the first one's.
    fn process(
        &self,
        alongs: &[Along],
        band: Band,
        links: &mut BandLinks,
        buffers: &mut BandBuffers,
        io: &mut IoCounters,
        times: &mut BandTimes,
    ) -> Result<(), OocError> {
        let Band { block, surfels } = band;
        if let BandLinks::Replay(readers, scratch) = links {
            let waiting: u64 = buffers.group.iter().map(|&(n, _)| n).sum();
            if waiting > 0 && waiting + surfels > self.plan.replay_surfels {
                self.replay_group(readers, scratch, buffers, io, times)?;
            }
            buffers.group_ranges.extend_from_slice(&buffers.ranges);
            buffers.group.push((surfels, buffers.group_ranges.len()));
            return Ok(());
        }
        let t0 = Instant::now();
        let n = surfels as usize;
        // A replay before (some direction's links kept) left its staging buffer, and its
        // group's arrays where they held more than a band: a search needs the room for its
        // other arrays.
        buffers.staged_radiosity = Vec::new();
        buffers.staged_gathered = Vec::new();
        if buffers.radiosity.capacity() > self.plan.band_surfels as usize {
            buffers.radiosity = Vec::new();
            buffers.gathered = Vec::new();
        }
        buffers.props.clear();
        buffers.props.reserve_exact(n);
        buffers.entries.clear();
        buffers.entries.reserve_exact(n);
        let piece = (self.plan.io_bytes / STATIC_LEN).max(1) as u64;
        buffers.bytes.resize(piece as usize * STATIC_LEN, 0);
        for &(start, count) in &buffers.ranges {
            let mut at = 0;
            while at < count {
                let k = piece.min(count - at);
                let bytes = &mut buffers.bytes[..k as usize * STATIC_LEN];
                self.files.statics.read(start + at, bytes, io)?;
                for rec in bytes.chunks_exact(STATIC_LEN) {
                    let r = decode_static(rec);
                    buffers.entries.push(OrderedEntry {
                        voxel: r.prop.voxel,
                        index: buffers.props.len() as u32,
                    });
                    buffers.props.push(r.prop);
                }
                at += k;
            }
        }
        let BandBuffers {
            ranges,
            radiosity,
            gathered,
            ..
        } = buffers;
        self.read_light(ranges.iter().copied(), n, radiosity, gathered, io)?;
        times.read += t0.elapsed().as_secs_f64();
        for (k, along) in alongs.iter().enumerate() {
            let t1 = Instant::now();
            // A band of several directions holds whole columns: every row `i` of each.
            let block = if k == 0 {
                block
            } else {
                Block {
                    rows: along.frame.ni,
                    ..block
                }
            };
            let numbering = BandNumbering {
                frame: &along.frame,
                block,
            };
            dispatch(
                &buffers.entries,
                &numbering,
                self.threads,
                &mut buffers.lines,
            );
            let t2 = Instant::now();
            let input = DirectionInput {
                unit: along.unit,
                weight: along.weight,
                surfels: &buffers.props,
                radiosity: &buffers.radiosity,
                channels: self.channels,
            };
            let (lines, acc) = (&buffers.lines, &mut buffers.gathered);
            if let BandLinks::Record(recordings) = links {
                let kept = gather_and_record(lines, &input, acc, self.threads);
                recordings[k].band(n, &kept, io)?;
            } else {
                gather_all_lines(lines, &input, acc, self.threads);
            }
            times.dispatch += (t2 - t1).as_secs_f64();
            times.propagate += t2.elapsed().as_secs_f64();
            times.bands += 1;
        }
        let t3 = Instant::now();
        self.write_light(buffers.ranges.iter().copied(), &buffers.gathered, io)?;
        times.write += t3.elapsed().as_secs_f64();
        Ok(())
    }

    /// Replays the links of the bands set aside by [`Self::process`], in their order, and
    /// empties the group.
    ///
    /// A replay reads and writes only the light, but a band's light lies in one short range
    /// of the copy per layer: with bands sized for a search (props, lines, links), a replay
    /// made a read of the radiosity, a read of the earlier light and a write per layer and
    /// band, and waited on these calls more than on the bytes. So the light of consecutive
    /// bands, as many as [`MemoryPlan::replay_surfels`] allows, is read and written together:
    /// each band's light has a section of its own, in the band's order, where its links
    /// replay as they would in the band alone (the same bits); the bands' ranges that meet in
    /// a layer form runs, and a run of short ranges is read (and written back) at once through
    /// a staging buffer of a few hundred KiB at most, its parts copied to and from the
    /// sections. Long ranges are read and written in place, each on its own ([`apart`]): at
    /// large budgets the copy would cost more than the calls it saves (a link map instead of
    /// the sections cost as much again: 2 s of the city building's 38 s at 64 MiB).
    fn replay_group(
        &self,
        readers: &mut [super::links::Replaying],
        scratch: &mut super::links::LinkScratch,
        buffers: &mut BandBuffers,
        io: &mut IoCounters,
        times: &mut BandTimes,
    ) -> Result<(), OocError> {
        if buffers.group.is_empty() {
            return Ok(());
        }
        let t0 = Instant::now();
        // A search before (links not kept for some direction) left its arrays: the group's
        // light takes their room.
        buffers.props = Vec::new();
        buffers.entries = Vec::new();
        buffers.lines = Lines::default();
        let BandBuffers {
            radiosity,
            gathered,
            group,
            group_ranges,
            pieces,
            staged_radiosity,
            staged_gathered,
            ..
        } = buffers;
        // Every range of every band, with where it goes in the arrays (the bands one after the
        // other, each in its own order), then in file order: the ranges of different bands
        // never overlap, and those that meet are read and written as one.
        pieces.clear();
        let mut place = 0u64;
        for &(start, count) in group_ranges.iter() {
            pieces.push((start, count, place));
            place += count;
        }
        pieces.sort_unstable_by_key(|p| p.0);
        let total = place as usize;
        if radiosity.capacity() < total {
            // Room for the largest group at once: growing by steps would hold the old and the
            // new arrays together, over the budget.
            let most = (self.plan.replay_surfels as usize).max(total);
            *radiosity = Vec::with_capacity(most);
            *gathered = Vec::with_capacity(most);
        }
        // Every place below `total` is written before it is read: the arrays only grow.
        if radiosity.len() < total {
            radiosity.resize(total, [[0.0; 3]; 2]);
            gathered.resize(total, [[0.0; 3]; 2]);
        }
        let chunk = self.plan.replay_chunk();
        let earlier = self.files.previous.as_ref().unwrap_or(&self.files.gathered);
        for_each_run(pieces, chunk, |(start, count), parts| {
            if apart(count, parts.len()) {
                for &(from, len, to) in parts {
                    let (len, to) = (len as usize, to as usize);
                    self.files.radiosity.read_at(
                        from * RADIOSITY_LEN as u64,
                        bytemuck::cast_slice_mut(&mut radiosity[to..to + len]),
                        io,
                    )?;
                    let light = &mut gathered[to..to + len];
                    if self.first {
                        light.fill([[0.0; 3]; 2]);
                    } else {
                        let bytes = bytemuck::cast_slice_mut(light);
                        earlier.read_at(from * LIGHT32_LEN as u64, bytes, io)?;
                    }
                }
                return Ok(());
            }
            let n = count as usize;
            if staged_radiosity.len() < n {
                staged_radiosity.resize(n, [[0.0; 3]; 2]);
                staged_gathered.resize(n, [[0.0; 3]; 2]);
            }
            self.files.radiosity.read_at(
                start * RADIOSITY_LEN as u64,
                bytemuck::cast_slice_mut(&mut staged_radiosity[..n]),
                io,
            )?;
            if self.first {
                staged_gathered[..n].fill([[0.0; 3]; 2]);
            } else {
                let bytes = bytemuck::cast_slice_mut(&mut staged_gathered[..n]);
                earlier.read_at(start * LIGHT32_LEN as u64, bytes, io)?;
            }
            for &(from, len, to) in parts {
                let (from, len, to) = ((from - start) as usize, len as usize, to as usize);
                radiosity[to..to + len].copy_from_slice(&staged_radiosity[from..from + len]);
                gathered[to..to + len].copy_from_slice(&staged_gathered[from..from + len]);
            }
            Ok(())
        })?;
        let t1 = Instant::now();
        // Reading the links counts as reading.
        let mut link_reads = 0.0;
        let mut base = 0usize;
        for &(surfels, _) in group.iter() {
            let n = surfels as usize;
            // Directions replayed together add to each surfel in walk order, as one after the
            // other would: the same bits.
            for replaying in readers.iter_mut() {
                let read = Instant::now();
                let kept = replaying.band(n, scratch, io)?;
                link_reads += read.elapsed().as_secs_f64();
                kept.replay(
                    &radiosity[base..base + n],
                    self.channels,
                    &mut gathered[base..base + n],
                );
            }
            base += n;
        }
        let t2 = Instant::now();
        for_each_run(pieces, chunk, |(start, count), parts| {
            if apart(count, parts.len()) {
                for &(from, len, to) in parts {
                    let (len, to) = (len as usize, to as usize);
                    let bytes = bytemuck::cast_slice(&gathered[to..to + len]);
                    self.files
                        .gathered
                        .write_at(from * LIGHT32_LEN as u64, bytes, io)?;
                }
                return Ok(());
            }
            let n = count as usize;
            for &(from, len, to) in parts {
                let (from, len, to) = ((from - start) as usize, len as usize, to as usize);
                staged_gathered[from..from + len].copy_from_slice(&gathered[to..to + len]);
            }
            let bytes = bytemuck::cast_slice(&staged_gathered[..n]);
            self.files
                .gathered
                .write_at(start * LIGHT32_LEN as u64, bytes, io)
        })?;
        times.read += (t1 - t0).as_secs_f64() + link_reads;
        times.propagate += (t2 - t1).as_secs_f64() - link_reads;
        times.write += t2.elapsed().as_secs_f64();
        // A band counts once for each direction replayed on it.
        times.bands += (group.len() * readers.len()) as u64;
        times.replayed_bands += (group.len() * readers.len()) as u64;
        times.replay_groups += 1;
        group.clear();
        group_ranges.clear();
        Ok(())
    }

    /// Reads the radiosity and the earlier directions' light (zero for the copy's first
    /// direction) of the copy records of `ranges`, `surfels` in all, into `radiosity` and
    /// `gathered`, one read of each per range. The light records are the arrays' own bytes
    /// (see `files`), read straight into them.
    fn read_light(
        &self,
        ranges: impl Iterator<Item = (u64, u64)>,
        surfels: usize,
        radiosity: &mut Vec<Radiosity>,
        gathered: &mut Vec<AxisLight>,
        io: &mut IoCounters,
    ) -> Result<(), OocError> {
        radiosity.clear();
        radiosity.reserve_exact(surfels);
        gathered.clear();
        gathered.reserve_exact(surfels);
        for (start, count) in ranges {
            let from = radiosity.len();
            radiosity.resize(from + count as usize, [[0.0; 3]; 2]);
            self.files.radiosity.read_at(
                start * RADIOSITY_LEN as u64,
                bytemuck::cast_slice_mut(&mut radiosity[from..]),
                io,
            )?;
            gathered.resize(from + count as usize, [[0.0; 3]; 2]);
            if !self.first {
                let earlier = self.files.previous.as_ref();
                earlier.unwrap_or(&self.files.gathered).read_at(
                    start * LIGHT32_LEN as u64,
                    bytemuck::cast_slice_mut(&mut gathered[from..]),
                    io,
                )?;
            }
        }
        debug_assert_eq!(radiosity.len(), surfels);
        Ok(())
    }

    /// Writes `gathered`, the light of the copy records of `ranges` in their order, to the
    /// copy's file of gathered light, one write per range.
    fn write_light(
        &self,
        ranges: impl Iterator<Item = (u64, u64)>,
        gathered: &[AxisLight],
        io: &mut IoCounters,
    ) -> Result<(), OocError> {
        let mut done = 0usize;
        for (start, count) in ranges {
            let light = &gathered[done..done + count as usize];
            self.files.gathered.write_at(
                start * LIGHT32_LEN as u64,
                bytemuck::cast_slice(light),
                io,
            )?;
            done += count as usize;
        }
        Ok(())
    }
}

/// Pieces of a run this long on average (records) are read and written each on its own, in
/// place: a call then costs little beside the bytes, and going through the staging buffer
/// would copy them once more. Shorter ones (a small budget's bands, tens of records a layer)
/// are read and written as one run: the calls cost more than the copy.
const APART_RECORDS: u64 = 1024;

/// Whether a run of `count` records holding `parts` parts is read and written part by part.
fn apart(count: u64, parts: usize) -> bool {
    parts == 1 || count / parts as u64 >= APART_RECORDS
}

/// Calls `f` on the runs of `pieces` (copy ranges `(start, count, place)` in file order, none
/// overlapping): each stretch of the copy where pieces meet, cut into runs of at most `chunk`
/// records, with the parts of the pieces that fall in the run (`(start, count, place)` again).
fn for_each_run(
    pieces: &[(u64, u64, u64)],
    chunk: u64,
    mut f: impl FnMut((u64, u64), &[(u64, u64, u64)]) -> Result<(), OocError>,
) -> Result<(), OocError> {
    let mut parts = Vec::new();
    let mut k = 0;
    while k < pieces.len() {
        // The stretch of pieces k.. that meet.
        let mut end = k + 1;
        while end < pieces.len() && pieces[end - 1].0 + pieces[end - 1].1 == pieces[end].0 {
            end += 1;
        }
        let (first, last) = (pieces[k].0, pieces[end - 1].0 + pieces[end - 1].1);
        let mut at = first;
        let mut p = k;
        while at < last {
            let stop = last.min(at + chunk.max(1));
            parts.clear();
            while p < end && pieces[p].0 < stop {
                let (start, count, place) = pieces[p];
                let (from, to) = (start.max(at), (start + count).min(stop));
                parts.push((from, to - from, place + (from - start)));
                if start + count <= stop {
                    p += 1;
                } else {
                    break;
                }
            }
            f((at, stop - at), &parts)?;
            at = stop;
        }
        k = end;
    }
    Ok(())
}

/// One direction of a pass: its lines, the unit vector its searches point along (the way the
/// lines run through the layers, in increasing order), and its weight.
struct Along {
    frame: LineFrame,
    unit: glam::DVec3,
    weight: f64,
}

impl Along {
    fn new(d: &Direction, copy: &AxisCopy, dims: [u32; 3]) -> Self {
        let frame = LineFrame::new(d.vector, dims);
        debug_assert_eq!((frame.main, frame.u, frame.v), (copy.main, copy.u, copy.v));
        let unit = if d.vector[copy.main] < 0 {
            -d.unit
        } else {
            d.unit
        };
        Along {
            frame,
            unit,
            weight: d.solid_angle / std::f64::consts::PI,
        }
    }
}

/// The lines of one band and the surfels they hold.
#[derive(Clone, Copy, Debug)]
struct Band {
    block: Block,
    surfels: u64,
}

/// A column of lines too big for one band.
#[derive(Clone, Copy, Debug)]
struct Column {
    vector: [i64; 3],
    j0: u64,
    surfels: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Runs cover exactly the pieces, meeting pieces share a run, no run is longer than the
    /// chunk, and every part lands at its piece's place plus its offset in the piece.
    #[test]
    fn runs_cover_the_pieces_in_chunks() {
        // Copy ranges (start, count, place): three that meet (10..14, 14..20, 20..21), one
        // apart (30..37), and one alone that a chunk of 4 cuts (50..59).
        let pieces = [
            (10, 4, 100),
            (14, 6, 0),
            (20, 1, 50),
            (30, 7, 200),
            (50, 9, 300),
        ];
        for chunk in [1, 3, 4, 100] {
            let mut seen: Vec<(u64, u64)> = Vec::new();
            let mut runs = Vec::new();
            for_each_run(&pieces, chunk, |run, parts| {
                runs.push(run);
                assert!(run.1 <= chunk && run.1 > 0);
                let mut at = run.0;
                for &(from, len, place) in parts {
                    assert_eq!(from, at, "parts follow each other through the run");
                    at += len;
                    for r in from..from + len {
                        seen.push((r, place + (r - from)));
                    }
                }
                assert_eq!(at, run.0 + run.1, "the parts fill the run");
                Ok(())
            })
            .expect("no error");
            let expected: Vec<(u64, u64)> = pieces
                .iter()
                .flat_map(|&(s, c, p)| (s..s + c).map(move |r| (r, p + r - s)))
                .collect();
            assert_eq!(seen, expected, "chunk {chunk}");
            if chunk == 100 {
                assert_eq!(runs, [(10, 11), (30, 7), (50, 9)]);
            }
        }
    }
}

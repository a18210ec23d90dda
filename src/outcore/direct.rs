//! The direct-light pass out of core: the emitters' light gathered once along the dense
//! directions (`solve::direct`), with the scene in its source and the light in a work file.
//!
//! The in-memory pass walks, per dense direction, only the lines through emitting surfels; a
//! line reads its surfels from a table of the whole scene. Out of core the scene does not fit,
//! but the pass never reads more than the surfels on its emitters' lines. So:
//!
//! 1. One pass over the source finds the emitting surfels and an occupancy map: one bit per
//!    brick of `e x e x e` voxels over the whole grid, `e` the smallest power of two whose map
//!    takes at most an eighth of the budget (`e = 1`, one bit a voxel, on most grids).
//! 2. The dense directions are taken in *parts* of whole groups (a sender's balance is settled
//!    over a group, `solve::direct`): for each direction of a part, its emitters' lines are
//!    walked through the occupancy map and the voxels of occupied bricks on them listed; a part
//!    takes as many groups as the budget holds the surfels of those voxels for (estimated from
//!    the scene's surfels per brick voxel; a part whose surfels turn out too many is taken again
//!    with half its groups). A group that does not fit a part alone (in a building, a lamp's
//!    lines cross every floor: one direction's lines held a twentieth of a building's surfels) is
//!    *split*: its directions' lines are taken in order, as many as a part holds, a part ending
//!    inside a direction and the next one going on from there with the senders' sums so far
//!    (`solve::direct::Piece`). The light each piece gathers is kept in a work file, unscaled,
//!    until the group is complete; then its senders' balance is settled and the kept light,
//!    scaled, added to the sums in the order it was gathered: what the whole group adds, bit
//!    for bit.
//! 3. The source hands over these surfels, in canonical order (`outcore::pick`: a shard set
//!    in the voxels' order is searched for them, any other source streamed): a small scene of
//!    its own, on which `solve::direct::gather_groups` (or, for a split group's pieces,
//!    `gather_pieces`, the same walk of each line) runs unchanged. Every line it walks is whole
//!    there, so it finds the links the whole scene gives.
//! 4. The light and weight shifts of the part's surfels are added to the running sums, kept by
//!    canonical index in a work file ([`SUM_LEN`] bytes a surfel), starting from the sums of the
//!    parts before: each surfel adds its contributions in direction order, exactly as the
//!    in-memory pass adds them, so the answer is that pass's bit for bit.
//! 5. A last pass divides each side's light by `S_dense(n)` plus its shift into the direct-light
//!    file ([`LIGHT32_LEN`] bytes a surfel, canonical order, rounded once to f32: the data mode
//!    carries it in its records, and both read the same values), which every update reads.
//!
//! **Memory.** The occupancy map and the emitters' voxels stay for the whole pass; a part holds
//! its voxels' keys and its surfels (about [`PART_BYTES_PER_SURFEL`] each with the tables the
//! gathering builds). A split group's pieces are held the same way; the refusal is left for a
//! budget that cannot hold the surfels of a single line.

use super::budget::{format_bytes, MemoryPlan};
use super::files::{encode_light32, IoCounters, RecordFile, SeqReader, SeqWriter, LIGHT32_LEN};
use super::source::SurfelSource;
use super::OocError;
use crate::geometry::directions::DirectionSet;
use crate::geometry::lines::LineFrame;
use crate::solve::direct::{
    add_scaled, emits, emitting, for_each_voxel_on_line, gather_groups, gather_pieces,
    group_scales, sender_key, sender_of_key, DirectStats, GatherOn, Piece, Sender, SenderBalance,
    Sums, DIRECTIONS_PER_GROUP,
};
use crate::solve::mix_hash::MixMap;
use crate::solve::normalize::cosine_sums;
use crate::solve::propagate::prop_surfels;
use crate::solve::propagate::PropSurfel;
use crate::voxel::SurfelSet;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Bytes of one surfel's running sums: light by side and channel (f64 x 6), then each side's
/// shift of its gathered weights (f64 x 2).
pub const SUM_LEN: usize = 64;

/// Bytes a part holds per surfel: the surfel and its propagation data, emission, the voxel
/// table's entry, the sums and the canonical index, with room for the per-direction lists.
pub const PART_BYTES_PER_SURFEL: u64 = 320;

/// The direct light, out of core: a work file of [`LIGHT32_LEN`] bytes per surfel in canonical
/// order (`H_dense(E) / S_dense(n)` by side and channel), and what the pass did.
pub struct DirectFile {
    pub path: PathBuf,
    pub stats: DirectStats,
}

/// Bricks of `edge`^3 voxels holding a surfel, one bit each over the whole grid.
struct Occupancy {
    /// log2 of the brick edge.
    shift: u32,
    /// Bricks along each axis.
    bricks: [u64; 3],
    bits: Vec<u64>,
}

impl Occupancy {
    /// The finest map of a grid of `dims` that takes at most `bytes`.
    fn new(dims: [u32; 3], bytes: u64) -> Self {
        let mut shift = 0;
        loop {
            let bricks = dims.map(|d| (d as u64).div_ceil(1 << shift));
            let count = bricks[0] * bricks[1] * bricks[2];
            if count.div_ceil(8) <= bytes || shift >= 20 {
                return Occupancy {
                    shift,
                    bricks,
                    bits: vec![0; count.div_ceil(64) as usize],
                };
            }
            shift += 1;
        }
    }

    fn at(&self, voxel: [i32; 3]) -> u64 {
        let b = voxel.map(|c| (c as u64) >> self.shift);
        (b[2] * self.bricks[1] + b[1]) * self.bricks[0] + b[0]
    }

    fn insert(&mut self, voxel: [i32; 3]) {
        let at = self.at(voxel);
        self.bits[(at / 64) as usize] |= 1 << (at % 64);
    }

    fn contains(&self, voxel: [i32; 3]) -> bool {
        let at = self.at(voxel);
        self.bits[(at / 64) as usize] & (1 << (at % 64)) != 0
    }

    fn bytes(&self) -> u64 {
        self.bits.len() as u64 * 8
    }

    /// Voxels in the bricks that hold a surfel.
    fn voxels_marked(&self) -> u64 {
        let ones: u64 = self.bits.iter().map(|w| w.count_ones() as u64).sum();
        ones << (3 * self.shift)
    }
}

/// The refusal of a budget whose room for a part (`room` bytes) cannot hold one group's
/// `needed` bytes (`voxels` listed voxels of `directions` dense directions).
fn too_small(
    plan: &MemoryPlan,
    room: u64,
    needed: u64,
    voxels: usize,
    directions: usize,
) -> OocError {
    OocError::BudgetTooSmall {
        budget: plan.budget,
        needed: plan.budget - room + needed,
        what: format!(
            "the direct-light pass (the surfels of {voxels} voxels on the emitters' lines of \
             {directions} dense directions; --direct-directions 0 turns the pass off)"
        ),
    }
}

/// A voxel as one sortable number, in `(z, y, x)` order: the order of a shard set's surfels, so
/// that a part's sorted keys are met in order along its stream.
fn voxel_key(voxel: [i32; 3]) -> u64 {
    crate::solve::direct::VoxelTable::key(voxel)
}

/// What the pass's parts share: the source, the plan and what the first pass over the source
/// found.
struct Pass<'a> {
    source: &'a dyn SurfelSource,
    dense: &'a DirectionSet,
    plan: &'a MemoryPlan,
    pool: &'a rayon::ThreadPool,
    occupancy: Occupancy,
    emitter_voxels: Vec<[i32; 3]>,
    /// Surfels per listed voxel, as estimated: the scene's mean over the marked bricks at
    /// first, raised to what a part found (lines through lamps cross floors and walls, where
    /// the surfels are denser than the mean).
    density: std::cell::Cell<f64>,
    /// Bytes a part may take.
    room: u64,
    /// Whether a part's voxel table keeps a bit per voxel of the grid.
    bitmap: bool,
    cosine_sum: Vec<f64>,
    sums_file: RecordFile,
}

/// A part whose surfels were more than its room holds, and the surfels per listed voxel met
/// before the room was full (more than the scene's mean, which the estimate took).
struct Overflow {
    density: f64,
}

/// The surfels of a part, in canonical order, and their canonical indices.
struct Part {
    set: SurfelSet,
    ids: Vec<u64>,
}

impl Pass<'_> {
    fn emission_of(&self, material: [u32; 2]) -> [[f32; 3]; 2] {
        let materials = &self.source.info().materials;
        material.map(|m| materials[m as usize].emission.map(|e| e as f32))
    }

    /// Raises the estimate of surfels per listed voxel to `seen`, what a part met.
    fn learn(&self, seen: f64) {
        self.density.set(self.density.get().max(seen));
    }

    /// Bytes a part takes: its listed voxels' keys (8 bytes each) and its surfels.
    fn part_bytes(&self, keys: usize, surfels: f64) -> u64 {
        keys as u64 * 8 + (surfels * PART_BYTES_PER_SURFEL as f64) as u64
    }

    /// Listed voxels a part can hold, at most: their keys and their surfels fill its room.
    fn most_keys(&self) -> usize {
        let per_voxel = 8.0 + self.density.get() * PART_BYTES_PER_SURFEL as f64;
        (self.room as f64 / per_voxel) as usize
    }

    /// The occupied voxels on the emitters' lines of the dense directions `which`, and the bytes
    /// a part holding their surfels is estimated to take; `None` where they are more than a
    /// part holds ([`Pass::most_keys`]: listing them all would take more than the budget).
    fn listed(&self, which: &[usize]) -> Option<(Vec<u64>, u64)> {
        let keys = self.lines().voxels(which, self.pool, self.most_keys())?;
        let needed = self.part_bytes(keys.len(), keys.len() as f64 * self.density.get());
        Some((keys, needed))
    }

    /// The bytes a part holding the surfels on the emitters' lines of the dense directions
    /// `which` would take, at most: their voxels counted direction by direction
    /// ([`EmitterLines::count`]), none held.
    fn counted(&self, which: &[usize]) -> u64 {
        let voxels = self.lines().count(which, self.pool);
        self.part_bytes(voxels as usize, voxels as f64 * self.density.get())
    }

    /// The emitters' lines as this pass walks them.
    fn lines(&self) -> EmitterLines<'_> {
        EmitterLines {
            dense: self.dense,
            dims: self.source.info().grid.dims,
            emitter_voxels: &self.emitter_voxels,
            occupancy: &self.occupancy,
        }
    }

    /// The refusal of a part of `directions` directions that needs `needed` bytes for the
    /// surfels of `voxels` voxels. The budget it names is enough whether or not the larger
    /// budget's part gets an occupancy bitmap (which takes from the part's room).
    fn too_small(&self, needed: u64, voxels: usize, directions: usize) -> OocError {
        let grid = self.source.info().grid.dims;
        let voxels_of_grid: u64 = grid.iter().map(|&d| d as u64).product();
        let bitmap_room = if self.bitmap || voxels_of_grid > crate::solve::direct::MAX_BITMAP_VOXELS
        {
            0
        } else {
            crate::solve::direct::bitmap_bytes(voxels_of_grid)
        };
        too_small(
            self.plan,
            self.room,
            needed + bitmap_room,
            voxels,
            directions,
        )
    }

    /// The surfels of the voxels `keys` (sorted), in canonical order (`outcore::pick`: a shard
    /// set in the voxels' order is searched for them, any other source streamed whole); an
    /// [`Overflow`] if they are more than the part's room holds.
    fn pick(&self, keys: &[u64], io: &mut IoCounters) -> Result<Result<Part, Overflow>, OocError> {
        let info = self.source.info();
        let cap =
            (self.room.saturating_sub(keys.len() as u64 * 8) / PART_BYTES_PER_SURFEL) as usize;
        let mut set = SurfelSet {
            grid: info.grid,
            surfels: Vec::new(),
            normals: info.normals.clone(),
            materials: info.materials.clone(),
        };
        let mut ids: Vec<u64> = Vec::new();
        let mut overflow = None;
        io.read += self
            .source
            .pick_voxels(keys, self.plan.io_bytes as u64, &mut |id, s, at| {
                if set.surfels.len() >= cap {
                    overflow = Some(Overflow {
                        density: cap as f64 / at.max(1) as f64,
                    });
                    return Ok(false);
                }
                set.surfels.push(s);
                ids.push(id);
                Ok(true)
            })?;
        Ok(match overflow {
            Some(o) => Err(o),
            None => Ok(Part { set, ids }),
        })
    }

    /// Whole groups `which` on `part`: their light added to the running sums of its surfels.
    fn gather_whole(
        &self,
        part: &Part,
        which: &[usize],
        first: bool,
        progress: &indicatif::ProgressBar,
        stats: &mut DirectStats,
        io: &mut IoCounters,
    ) -> Result<(), OocError> {
        let mut light = vec![[[0f64; 3]; 2]; part.ids.len()];
        let mut rescaled = vec![[0f64; 2]; part.ids.len()];
        let mut run = Vec::new();
        if !first {
            self.for_sums_in_runs(&part.ids, &mut run, io, |k, sum| {
                (light[k], rescaled[k]) = decode_sum(sum);
            })?;
        }
        let sums = Sums {
            light: &mut light,
            rescaled: &mut rescaled,
            stats,
        };
        let (emission, emitters, surfels) = self.part_tables(part);
        let on = self.gather_on(part, &emission, &emitters, &surfels);
        gather_groups(&on, which, SenderBalance::PerDirection, progress, sums);
        // Written in runs of consecutive surfels (from the start when this part is the first:
        // the file holds no sums yet).
        self.for_sums_in_runs_written(&part.ids, !first, &mut run, io, |k, sum| {
            encode_sum(&light[k], &rescaled[k], sum);
        })
    }

    /// Hands `f` the running sums of the surfels `ids` (sorted, distinct) as read from the sums
    /// file, by their place in `ids`: a run of consecutive surfels (at most [`SUM_RUN`]) in one
    /// read, not one a surfel (the surfels of neighbouring lines of a direction sit next to one
    /// another in the canonical order). `run` is the read's buffer.
    fn for_sums_in_runs(
        &self,
        ids: &[u64],
        run: &mut Vec<u8>,
        io: &mut IoCounters,
        mut f: impl FnMut(usize, &[u8; SUM_LEN]),
    ) -> Result<(), OocError> {
        for (first, len) in runs_of(ids) {
            run.resize(len * SUM_LEN, 0);
            self.sums_file
                .read_at(ids[first] * SUM_LEN as u64, run, io)?;
            for (j, sum) in run.chunks_exact(SUM_LEN).enumerate() {
                f(first + j, sum.try_into().expect("a sum"));
            }
        }
        Ok(())
    }

    /// Has `f` fill in the running sums of the surfels `ids` (sorted, distinct) by their place
    /// in `ids`, each run of consecutive surfels read first where `read` (for `f` to change
    /// them), and written back in one write.
    fn for_sums_in_runs_written(
        &self,
        ids: &[u64],
        read: bool,
        run: &mut Vec<u8>,
        io: &mut IoCounters,
        mut f: impl FnMut(usize, &mut [u8; SUM_LEN]),
    ) -> Result<(), OocError> {
        for (first, len) in runs_of(ids) {
            run.resize(len * SUM_LEN, 0);
            let at = ids[first] * SUM_LEN as u64;
            if read {
                self.sums_file.read_at(at, run, io)?;
            }
            for (j, sum) in run.chunks_exact_mut(SUM_LEN).enumerate() {
                f(first + j, sum.try_into().expect("a sum"));
            }
            self.sums_file.write_at(at, run, io)?;
        }
        Ok(())
    }

    /// What the gathering reads of a part besides its surfels: their emission, the emitting
    /// ones, their propagation records.
    fn part_tables(&self, part: &Part) -> (Vec<[[f32; 3]; 2]>, Vec<u32>, Vec<PropSurfel>) {
        let emission: Vec<[[f32; 3]; 2]> = part
            .set
            .surfels
            .iter()
            .map(|s| self.emission_of(s.material))
            .collect();
        let emitters = emitting(&emission);
        (emission, emitters, prop_surfels(&part.set))
    }

    /// What the gathering reads of `part`, with its tables.
    fn gather_on<'b>(
        &'b self,
        part: &'b Part,
        emission: &'b [[[f32; 3]; 2]],
        emitters: &'b [u32],
        surfels: &'b [PropSurfel],
    ) -> GatherOn<'b> {
        GatherOn {
            set: &part.set,
            surfels,
            emission,
            emitters,
            cosine_sum: &self.cosine_sum,
            directions: self.dense,
            pool: self.pool,
            bitmap: self.bitmap,
        }
    }

    /// The emitters' lines of `frame`, sorted, each once.
    fn lines_of(&self, frame: &LineFrame) -> Vec<u64> {
        emitter_lines(frame, &self.emitter_voxels)
    }

    /// The frame of dense direction `k`'s lines.
    fn frame(&self, k: usize) -> LineFrame {
        LineFrame::new(
            self.dense.directions[k].vector,
            self.source.info().grid.dims,
        )
    }

    /// The occupied voxels on `lines` of dense direction `k` (`frame` its frame), in the
    /// order met.
    fn voxels_on(&self, k: usize, frame: &LineFrame, lines: &[u64], out: &mut Vec<u64>) {
        let dims = self.source.info().grid.dims;
        let vector = self.dense.directions[k].vector;
        for &line in lines {
            for_each_voxel_on_line(frame, dims, vector, line, |voxel| {
                if self.occupancy.contains(voxel) {
                    out.push(voxel_key(voxel));
                }
            });
        }
    }

    /// One group whose emitters' lines do not fit a part (a building's lamps are crossed by
    /// lines through every floor: one direction's lines can hold a twentieth of its surfels). Its
    /// directions' lines are taken in order, as many consecutive ones as a part holds (a part may
    /// end inside a direction and the next go on from there, carrying the senders' sums so
    /// far), each piece's light kept in a work file ([`TERM_LEN`] bytes a contribution) and
    /// each direction's senders in memory. Once the group is complete its senders' balance is
    /// settled, and the kept light, scaled, is added to the running sums in direction order:
    /// what the whole group adds. Returns the parts taken.
    fn gather_split(
        &self,
        group: &[usize],
        dir: &Path,
        stats: &mut DirectStats,
        io: &mut IoCounters,
    ) -> Result<u64, OocError> {
        let kept_path = dir.join("direct-group.bin");
        let mut split = Split {
            kept: SeqWriter::create(&kept_path, self.plan.io_bytes)?,
            senders: vec![Vec::new(); group.len()],
            counts: vec![0; group.len()],
            parts: 0,
        };
        self.pack(group, |pieces, keys| {
            self.split_part(group, pieces, Some(keys), &mut split, stats, io)
        })?;
        io.written += split.kept.finish()?;
        let refs: Vec<&[((u32, usize), Sender)]> =
            split.senders.iter().map(Vec::as_slice).collect();
        let scales = group_scales(&refs, SenderBalance::PerDirection);
        // The kept light in runs as large as the room holds, each run's terms applied by
        // surfel (a stable sort keeps each surfel's terms in the order gathered) with one read
        // and one write of its sums.
        // (Besides each term, `apply` lists each surfel once with where its terms begin.)
        let per_term = std::mem::size_of::<Term>() as u64 + 16;
        let run = (self.room / per_term).max(1) as usize;
        let mut terms: Vec<Term> = Vec::with_capacity(run.min(1 << 20));
        let mut reader = SeqReader::<TERM_LEN>::open(&kept_path, self.plan.io_bytes)?;
        let damaged = || {
            OocError::io(
                &kept_path,
                "read",
                std::io::Error::new(
                    std::io::ErrorKind::InvalidData,
                    "a kept contribution names a sender its direction does not have",
                ),
            )
        };
        for (j, &count) in split.counts.iter().enumerate() {
            for _ in 0..count {
                let (id, side, sender, light, weight) = decode_term(&reader.expect_record()?);
                let at = split.senders[j]
                    .binary_search_by_key(&sender_of_key(sender), |s| s.0)
                    .map_err(|_| damaged())?;
                terms.push(Term {
                    id,
                    side,
                    light,
                    weight,
                    scale: scales[j][at],
                });
                if terms.len() >= run {
                    self.apply(&mut terms, io)?;
                }
            }
        }
        self.apply(&mut terms, io)?;
        io.read += split.counts.iter().sum::<u64>() * TERM_LEN as u64;
        drop(reader);
        std::fs::remove_file(&kept_path).map_err(|e| OocError::io(&kept_path, "remove", e))?;
        tracing::debug!(
            parts = split.parts,
            contributions = split.counts.iter().sum::<u64>(),
            "direct-light pass: a split group gathered"
        );
        Ok(split.parts)
    }

    /// Packs the lines of `group`'s directions, in order, into parts greedily, by the distinct
    /// voxels they cross (lines of neighbouring directions through one lamp share most of
    /// their voxels near it), and hands each part to `part`: its pieces (the lines of
    /// directions `group[j]`) and its voxels' keys, sorted.
    fn pack(
        &self,
        group: &[usize],
        mut part: impl FnMut(Vec<(usize, Vec<u64>)>, Vec<u64>) -> Result<(), OocError>,
    ) -> Result<(), OocError> {
        let mut pending: Vec<(usize, Vec<u64>)> = Vec::new();
        let mut distinct: MixMap<()> = MixMap::default();
        let mut voxels = Vec::new();
        let mut flush = |pending: &mut Vec<(usize, Vec<u64>)>, distinct: &mut MixMap<()>| {
            let mut keys: Vec<u64> = distinct.drain().map(|(key, ())| key).collect();
            keys.sort_unstable();
            part(std::mem::take(pending), keys)
        };
        for (j, &k) in group.iter().enumerate() {
            let frame = self.frame(k);
            for line in self.lines_of(&frame) {
                voxels.clear();
                self.voxels_on(k, &frame, &[line], &mut voxels);
                let new = voxels.iter().filter(|v| !distinct.contains_key(v)).count();
                // A listed voxel's key, its entry in `distinct` (kept while the part is held)
                // and its surfels.
                let per_voxel =
                    8.0 + DISTINCT_ENTRY_BYTES + self.density.get() * PART_BYTES_PER_SURFEL as f64;
                let most = (self.room as f64 / per_voxel) as usize;
                if distinct.len() + new > most && !pending.is_empty() {
                    flush(&mut pending, &mut distinct)?;
                }
                distinct.extend(voxels.iter().map(|&v| (v, ())));
                match pending.last_mut() {
                    Some((last, lines)) if *last == j => lines.push(line),
                    _ => pending.push((j, vec![line])),
                }
            }
        }
        if !pending.is_empty() {
            flush(&mut pending, &mut distinct)?;
        }
        Ok(())
    }

    /// Gathers `pieces` (the lines of directions `group[j]`, in order) as one part, or, where
    /// their surfels are more than a part holds, as two halves one after the other. `keys` are
    /// the occupied voxels on their lines, sorted, each once, if known.
    fn split_part(
        &self,
        group: &[usize],
        pieces: Vec<(usize, Vec<u64>)>,
        keys: Option<Vec<u64>>,
        split: &mut Split,
        stats: &mut DirectStats,
        io: &mut IoCounters,
    ) -> Result<(), OocError> {
        let keys = keys.unwrap_or_else(|| {
            let mut keys = Vec::new();
            for (j, lines) in &pieces {
                let k = group[*j];
                self.voxels_on(k, &self.frame(k), lines, &mut keys);
            }
            keys.sort_unstable();
            keys.dedup();
            keys
        });
        let mut needed = self.part_bytes(keys.len(), keys.len() as f64 * self.density.get());
        let part = if needed > self.room {
            None
        } else {
            match self.pick(&keys, io)? {
                Ok(part) => Some(part),
                Err(overflow) => {
                    self.learn(overflow.density);
                    // More surfels than the estimate: at least twice what the room holds.
                    needed = needed.max(2 * self.room);
                    None
                }
            }
        };
        let Some(part) = part else {
            let lines: usize = pieces.iter().map(|(_, lines)| lines.len()).sum();
            if lines <= 1 {
                return Err(self.too_small(needed, keys.len(), 1));
            }
            drop(keys);
            // Halves of about equal lines, in order.
            let (mut first, mut second) = (Vec::new(), Vec::new());
            let mut left = lines / 2;
            for (j, lines) in pieces {
                if left >= lines.len() {
                    left -= lines.len();
                    first.push((j, lines));
                } else if left > 0 {
                    first.push((j, lines[..left].to_vec()));
                    second.push((j, lines[left..].to_vec()));
                    left = 0;
                } else {
                    second.push((j, lines));
                }
            }
            self.split_part(group, first, None, split, stats, io)?;
            return self.split_part(group, second, None, split, stats, io);
        };
        self.learn(part.ids.len() as f64 / keys.len().max(1) as f64);
        drop(keys);
        let (emission, emitters, surfels) = self.part_tables(&part);
        let gathered = {
            let pieces: Vec<Piece> = pieces
                .iter()
                .map(|(j, lines)| Piece {
                    direction: group[*j],
                    lines: lines[0]..lines[lines.len() - 1] + 1,
                    carried: &split.senders[*j],
                })
                .collect();
            gather_pieces(
                &self.gather_on(&part, &emission, &emitters, &surfels),
                &pieces,
            )
        };
        let mut term = [0u8; TERM_LEN];
        for ((j, _), light) in pieces.iter().zip(gathered) {
            stats.lines += light.lines;
            stats.line_surfels += light.line_surfels;
            split.counts[*j] += light.contributions.len() as u64;
            for &(member, side, sender, value, weight) in &light.contributions {
                let (group_id, sender_side) = light.senders[sender as usize].0;
                encode_term(
                    part.ids[member as usize],
                    side,
                    sender_key(group_id, sender_side),
                    &value,
                    weight,
                    &mut term,
                );
                split.kept.write(&term)?;
            }
            split.senders[*j] = light.senders;
        }
        split.parts += 1;
        tracing::debug!(
            pieces = pieces.len(),
            surfels = part.ids.len(),
            "direct-light pass: a part of a split group gathered"
        );
        Ok(())
    }

    /// Adds `terms` (in the order they were gathered) to the running sums and empties it.
    fn apply(&self, terms: &mut Vec<Term>, io: &mut IoCounters) -> Result<(), OocError> {
        terms.sort_by_key(|t| t.id);
        // The surfels named, each once, and where each one's terms begin.
        let mut ids = Vec::new();
        let mut starts = Vec::new();
        for (k, t) in terms.iter().enumerate() {
            if ids.last() != Some(&t.id) {
                ids.push(t.id);
                starts.push(k);
            }
        }
        starts.push(terms.len());
        let mut run = Vec::new();
        self.for_sums_in_runs_written(&ids, true, &mut run, io, |k, sum| {
            let (mut light, mut rescaled) = decode_sum(sum);
            for t in &terms[starts[k]..starts[k + 1]] {
                let side = t.side as usize;
                add_scaled(
                    &mut light[side],
                    &mut rescaled[side],
                    &t.light,
                    t.weight,
                    t.scale,
                );
            }
            encode_sum(&light, &rescaled, sum);
        })?;
        terms.clear();
        Ok(())
    }
}

/// A split group under way: its kept light, each direction's senders' sums so far and
/// contributions kept, and the parts taken.
struct Split {
    kept: SeqWriter,
    senders: Vec<Vec<((u32, usize), Sender)>>,
    counts: Vec<u64>,
    parts: u64,
}

/// One kept contribution of a split group, its sender's scale known.
struct Term {
    id: u64,
    side: u8,
    light: [f64; 3],
    weight: f64,
    scale: f64,
}

/// Runs the pass over `source` along `dense` within `plan`, writing its files into `dir`.
pub fn gather_direct_out_of_core(
    source: &dyn SurfelSource,
    dense: &DirectionSet,
    plan: &MemoryPlan,
    pool: &rayon::ThreadPool,
    dir: &Path,
    io: &mut IoCounters,
) -> Result<DirectFile, OocError> {
    let started = Instant::now();
    let info = source.info();
    let n = info.count;
    let emission_of = |material: [u32; 2]| {
        material.map(|m| info.materials[m as usize].emission.map(|e| e as f32))
    };
    // 1. Emitters and occupancy.
    let mut occupancy = Occupancy::new(info.grid.dims, plan.working / 8);
    let mut emitter_voxels: Vec<[i32; 3]> = Vec::new();
    for s in source.stream(plan.io_bytes as u64)? {
        let s = s?;
        occupancy.insert(s.voxel);
        if emits(&emission_of(s.material)) {
            emitter_voxels.push(s.voxel);
        }
    }
    io.read += n * crate::storage::RECORD_LEN as u64;
    let density = n as f64 / occupancy.voxels_marked().max(1) as f64;
    let fixed = occupancy.bytes() + emitter_voxels.len() as u64 * 12;
    let voxels: u64 = info.grid.dims.iter().map(|&d| d as u64).product();
    let room = plan
        .working
        .saturating_sub(fixed + 2 * plan.io_bytes as u64);
    // The gathering's voxel table may keep a bit per voxel where that takes a small share.
    let bitmap_bytes = crate::solve::direct::bitmap_bytes(voxels);
    let bitmap = voxels <= crate::solve::direct::MAX_BITMAP_VOXELS && bitmap_bytes <= room / 8;
    let room = room - if bitmap { bitmap_bytes } else { 0 };

    tracing::info!(
        directions = dense.len(),
        emitting_surfels = emitter_voxels.len(),
        room = format_bytes(room),
        "direct-light pass out of core"
    );
    let sum_path = dir.join("direct-sums.bin");
    let sums_file = RecordFile::create(&sum_path)?;
    sums_file.set_len(n * SUM_LEN as u64)?;
    let mut stats = DirectStats {
        directions: dense.len(),
        emitting_surfels: emitter_voxels.len(),
        ..Default::default()
    };
    let pass = Pass {
        source,
        dense,
        plan,
        pool,
        occupancy,
        emitter_voxels,
        density: std::cell::Cell::new(density),
        room,
        bitmap,
        cosine_sum: cosine_sums(&info.normals, dense),
        sums_file,
    };
    let groups: Vec<Vec<usize>> = (0..dense.len())
        .collect::<Vec<_>>()
        .chunks(DIRECTIONS_PER_GROUP)
        .map(<[usize]>::to_vec)
        .collect();
    warn_of_many_passes(&pass, &groups);
    let progress = crate::progress::bar(dense.len() as u64, "direct light");
    let mut parts = 0u64;
    let mut next = 0;
    // At most this many groups per part (halved when a part's surfels did not fit).
    let mut most = groups.len();
    while next < groups.len() {
        // 2. The groups of this part and the voxels of occupied bricks on their emitters' lines;
        // a group that does not fit a part alone is taken in parts of its directions.
        let mut keys: Vec<u64> = Vec::new();
        let mut which: Vec<usize> = Vec::new();
        let mut taken = 0;
        while next + taken < groups.len() && taken < most {
            let group = &groups[next + taken];
            let Some((mut merged, _)) = pass.listed(group) else {
                break;
            };
            merged.extend_from_slice(&keys);
            merged.sort_unstable();
            merged.dedup();
            if pass.part_bytes(merged.len(), merged.len() as f64 * pass.density.get()) > room {
                break;
            }
            keys = merged;
            which.extend_from_slice(group);
            taken += 1;
        }
        // 3. The part's surfels, in canonical order; too many for the estimate: fewer groups.
        let part = if taken == 0 {
            None
        } else {
            match pass.pick(&keys, io)? {
                Ok(part) => {
                    pass.learn(part.ids.len() as f64 / keys.len().max(1) as f64);
                    Some(part)
                }
                Err(overflow) => {
                    pass.learn(overflow.density);
                    None
                }
            }
        };
        drop(keys);
        let Some(part) = part else {
            if taken <= 1 {
                parts += pass.gather_split(&groups[next], dir, &mut stats, io)?;
                progress.inc(groups[next].len() as u64);
                stats.split_groups += 1;
                next += 1;
            } else {
                most = taken / 2;
                tracing::debug!(
                    groups = most,
                    "direct-light pass: a part's surfels did not fit, fewer groups"
                );
            }
            continue;
        };
        // 4. Its sums so far, the part's light added, written back.
        pass.gather_whole(&part, &which, next == 0, &progress, &mut stats, io)?;
        next += taken;
        parts += 1;
        tracing::debug!(
            part = parts,
            directions = which.len(),
            surfels = part.ids.len(),
            "direct-light pass: part gathered"
        );
    }
    progress.finish_and_clear();
    let Pass {
        cosine_sum,
        sums_file,
        ..
    } = pass;
    drop(sums_file);
    // 5. Each side's light over `S + shift`, in canonical order.
    let path = dir.join("direct.bin");
    let mut out = SeqWriter::create(&path, plan.io_bytes)?;
    let mut sums = SeqReader::<SUM_LEN>::open(&sum_path, plan.io_bytes)?;
    let mut record = [0u8; LIGHT32_LEN];
    for s in source.stream(plan.io_bytes as u64)? {
        let s = s?;
        let (mut light, shift) = decode_sum(&sums.expect_record()?);
        let norm = cosine_sum[s.normal_id as usize];
        for side in 0..2 {
            light[side]
                .iter_mut()
                .for_each(|v| *v /= norm + shift[side]);
        }
        encode_light32(&light, &mut record);
        out.write(&record)?;
    }
    io.read += n * (crate::storage::RECORD_LEN + SUM_LEN) as u64;
    io.written += out.finish()?;
    drop(sums);
    std::fs::remove_file(&sum_path).map_err(|e| OocError::io(&sum_path, "remove", e))?;
    stats.seconds = started.elapsed().as_secs_f64();
    stats.parts = parts;
    tracing::info!(
        directions = dense.len(),
        parts,
        split_groups = stats.split_groups,
        map = format_bytes(fixed),
        seconds = format!("{:.1}", stats.seconds),
        "direct-light pass done out of core"
    );
    Ok(DirectFile { path, stats })
}

/// Parts above which the pass warns that it will be long.
const MANY_PASSES: f64 = 100.0;

/// Warns when the parts of the pass, each reading the surfels on its lines (a sorted shard
/// set) or the whole scene (any other source, `outcore::pick`) and gathering them, will be
/// many: estimated from sample groups' lines against the room of a part. The answer does not
/// depend on the budget, so the pass is not cut short; the user is told what shortens it.
/// (While it runs, its progress is logged: `progress::bar`.)
fn warn_of_many_passes(pass: &Pass, groups: &[Vec<usize>]) {
    if groups.is_empty() {
        return;
    }
    // Three groups spread over the set (the first alone can mislead: the set's first
    // directions lie near one pole). A part holds whole groups where they fit, else the
    // lines of a group's directions in order, packed as the pass packs them.
    let room = pass.room.max(1) as f64;
    let sample: Vec<&Vec<usize>> = [0, groups.len() / 2, groups.len() - 1]
        .into_iter()
        .map(|g| &groups[g])
        .collect();
    let mut per_group = 0.0;
    let mut largest = 0;
    for group in &sample {
        // A group a part cannot hold is not listed whole (that would take more than the
        // budget): its lines are counted, direction by direction, for what it holds at most.
        let needed = match pass.listed(group) {
            Some((_, needed)) => needed,
            None => pass.counted(group),
        };
        largest = largest.max(needed);
        per_group += if needed as f64 <= room {
            needed as f64 / room
        } else {
            let mut parts = 0u64;
            // Counting only: nothing is read or gathered.
            let _ = pass.pack(group, |_, _| {
                parts += 1;
                Ok(())
            });
            parts as f64
        };
    }
    let passes = groups.len() as f64 * per_group / sample.len() as f64;
    if passes > MANY_PASSES {
        tracing::warn!(
            "the direct-light pass will take at least about {passes:.0} parts over the scene's {} \
             surfels: the lines of a group of {} dense directions through its emitters hold up \
             to about {} against the {} a part of --memory holds; a larger --memory or fewer \
             --direct-directions (now {}) shortens it",
            pass.source.info().count,
            DIRECTIONS_PER_GROUP,
            format_bytes(largest),
            format_bytes(pass.room),
            pass.dense.len()
        );
    }
}

/// What the lines through the emitters are walked in: the dense directions, the grid, the
/// emitters' voxels and the occupancy map.
struct EmitterLines<'a> {
    dense: &'a DirectionSet,
    dims: [u32; 3],
    emitter_voxels: &'a [[i32; 3]],
    occupancy: &'a Occupancy,
}

impl EmitterLines<'_> {
    /// Calls `f` with every occupied voxel on the lines through the emitters along the dense
    /// direction `k`, each once (distinct lines cross distinct voxels), line after line; stops
    /// after a line where `f` asked to (returned `false`).
    fn for_each_voxel(&self, k: usize, mut f: impl FnMut([i32; 3]) -> bool) {
        let vector = self.dense.directions[k].vector;
        let frame = LineFrame::new(vector, self.dims);
        let mut more = true;
        for line in emitter_lines(&frame, self.emitter_voxels) {
            for_each_voxel_on_line(&frame, self.dims, vector, line, |voxel| {
                if self.occupancy.contains(voxel) {
                    more &= f(voxel);
                }
            });
            if !more {
                return;
            }
        }
    }

    /// The occupied voxels on the lines along the dense direction `k`, sorted; `None` once
    /// they are more than `most`.
    fn of_direction(&self, k: usize, most: usize) -> Option<Vec<u64>> {
        let mut found = Vec::new();
        self.for_each_voxel(k, |voxel| {
            found.push(voxel_key(voxel));
            found.len() <= most
        });
        if found.len() > most {
            return None;
        }
        found.sort_unstable();
        Some(found)
    }

    /// The occupied voxels on the lines along the dense directions `which`, sorted, each once;
    /// `None` as soon as they are more than `most`.
    ///
    /// The directions are listed a few at a time (one a thread) and merged into the voxels so
    /// far, so that what is held stays within about `most` keys a thread and two more: listed
    /// whole and only then counted, a group of 32 directions through a building's lamps held
    /// 155 MB at once under `--memory 64MiB` (`docs/out-of-core.md`).
    fn voxels(&self, which: &[usize], pool: &rayon::ThreadPool, most: usize) -> Option<Vec<u64>> {
        let (mut keys, mut merged) = (Vec::new(), Vec::new());
        for directions in which.chunks(pool.current_num_threads().max(1)) {
            let lists: Option<Vec<Vec<u64>>> = pool.install(|| {
                directions
                    .par_iter()
                    .map(|&k| self.of_direction(k, most))
                    .collect()
            });
            for list in lists? {
                merge_distinct(&keys, &list, &mut merged);
                std::mem::swap(&mut keys, &mut merged);
                if keys.len() > most {
                    return None;
                }
            }
        }
        Some(keys)
    }

    /// The occupied voxels on the lines along the dense directions `which`, counted direction
    /// by direction (a voxel on the lines of several is counted in each): at least as many as
    /// [`EmitterLines::voxels`] lists, without holding them.
    fn count(&self, which: &[usize], pool: &rayon::ThreadPool) -> u64 {
        pool.install(|| {
            which
                .par_iter()
                .map(|&k| {
                    let mut count = 0u64;
                    self.for_each_voxel(k, |_| {
                        count += 1;
                        true
                    });
                    count
                })
                .sum()
        })
    }
}

/// The lines of `frame` through the emitters (at `emitter_voxels`), sorted, each once.
fn emitter_lines(frame: &LineFrame, emitter_voxels: &[[i32; 3]]) -> Vec<u64> {
    let mut lines: Vec<u64> = emitter_voxels
        .iter()
        .map(|&v| frame.line_index(v))
        .collect();
    lines.sort_unstable();
    lines.dedup();
    lines
}

/// The sorted distinct values of `a` and `b` (each sorted, distinct), into `out`.
fn merge_distinct(a: &[u64], b: &[u64], out: &mut Vec<u64>) {
    out.clear();
    out.reserve(a.len() + b.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        let (x, y) = (a[i], b[j]);
        out.push(x.min(y));
        i += (x <= y) as usize;
        j += (y <= x) as usize;
    }
    out.extend_from_slice(&a[i..]);
    out.extend_from_slice(&b[j..]);
}

/// Surfels whose running sums are read or written at once, at most (64 KiB).
const SUM_RUN: usize = 1024;

/// The runs of consecutive values in `ids` (sorted, distinct), each at most [`SUM_RUN`] long:
/// (place of its first in `ids`, length).
fn runs_of(ids: &[u64]) -> impl Iterator<Item = (usize, usize)> + '_ {
    let mut first = 0;
    std::iter::from_fn(move || {
        if first >= ids.len() {
            return None;
        }
        let mut end = first + 1;
        while end < ids.len() && end - first < SUM_RUN && ids[end] == ids[end - 1] + 1 {
            end += 1;
        }
        let run = (first, end - first);
        first = end;
        Some(run)
    })
}

fn encode_sum(light: &[[f64; 3]; 2], shift: &[f64; 2], out: &mut [u8; SUM_LEN]) {
    for (slot, v) in out
        .chunks_exact_mut(8)
        .zip(light.iter().flatten().chain(shift))
    {
        slot.copy_from_slice(&v.to_le_bytes());
    }
}

fn decode_sum(bytes: &[u8; SUM_LEN]) -> ([[f64; 3]; 2], [f64; 2]) {
    let v = |k: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&bytes[8 * k..8 * k + 8]);
        f64::from_le_bytes(b)
    };
    ([[v(0), v(1), v(2)], [v(3), v(4), v(5)]], [v(6), v(7)])
}

/// Bytes an entry of the set of a packed part's distinct voxels takes (key and hash table
/// overhead).
const DISTINCT_ENTRY_BYTES: f64 = 16.0;

/// Bytes of one kept contribution of a split group: the receiver's canonical index (u64), its
/// side (u8), the sender's plane group and side ([`sender_key`], u64), the light (f64 x 3) and
/// the weight (f64), little-endian.
const TERM_LEN: usize = 49;

fn encode_term(
    id: u64,
    side: u8,
    sender: u64,
    light: &[f64; 3],
    weight: f64,
    out: &mut [u8; TERM_LEN],
) {
    out[..8].copy_from_slice(&id.to_le_bytes());
    out[8] = side;
    out[9..17].copy_from_slice(&sender.to_le_bytes());
    for (slot, v) in out[17..]
        .chunks_exact_mut(8)
        .zip(light.iter().chain([&weight]))
    {
        slot.copy_from_slice(&v.to_le_bytes());
    }
}

fn decode_term(bytes: &[u8; TERM_LEN]) -> (u64, u8, u64, [f64; 3], f64) {
    let word = |at: usize| -> [u8; 8] { bytes[at..at + 8].try_into().expect("8 bytes") };
    let f = |at: usize| f64::from_le_bytes(word(at));
    (
        u64::from_le_bytes(word(0)),
        bytes[8],
        u64::from_le_bytes(word(9)),
        [f(17), f(25), f(33)],
        f(41),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merged_voxel_lists_are_sorted_and_distinct() {
        let mut out = vec![99];
        merge_distinct(&[1, 4, 6, 9], &[2, 4, 9, 10, 11], &mut out);
        assert_eq!(out, [1, 2, 4, 6, 9, 10, 11]);
        merge_distinct(&[], &[3, 5], &mut out);
        assert_eq!(out, [3, 5]);
        merge_distinct(&[3, 5], &[], &mut out);
        assert_eq!(out, [3, 5]);
    }

    #[test]
    fn runs_of_consecutive_surfels_are_cut_where_they_break_or_grow_too_long() {
        let ids: Vec<u64> = [3, 4, 5, 9, 11, 12]
            .into_iter()
            .chain(100..100 + SUM_RUN as u64 + 5)
            .collect();
        let runs: Vec<(usize, usize)> = runs_of(&ids).collect();
        assert_eq!(
            runs,
            [(0, 3), (3, 1), (4, 2), (6, SUM_RUN), (6 + SUM_RUN, 5)]
        );
        assert_eq!(runs_of(&[]).count(), 0);
    }

    #[test]
    fn kept_contributions_round_trip() {
        let mut bytes = [0u8; TERM_LEN];
        let light = [1.5, -2.25e-300, f64::MAX];
        encode_term(
            u64::MAX - 3,
            1,
            sender_key(77, 1),
            &light,
            0.125,
            &mut bytes,
        );
        let (id, side, sender, back, weight) = decode_term(&bytes);
        assert_eq!(
            (id, side, sender_of_key(sender)),
            (u64::MAX - 3, 1, (77, 1))
        );
        assert_eq!(back.map(f64::to_bits), light.map(f64::to_bits));
        assert_eq!(weight, 0.125);
    }
}

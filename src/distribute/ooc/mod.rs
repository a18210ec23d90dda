//! The data and hybrid modes out of core (`--distribute data|hybrid --memory SIZE`): every rank
//! holds only its share of the scene, in work files on its own disk, and its memory stays within
//! the budget.
//!
//! **Input.** Rank `r` reads its slice of the canonical stream: about `n r / P .. n (r + 1) / P`,
//! both ends moved to the next voxel boundary so that voxel-mates (for the coverage) stay
//! together. From a shard set it opens only the shards that hold its slice.
//!
//! **Held files** ([`held`]): the rank's surfels with their radiosity and gathered light, sorted
//! in the copy order of the current main axis `m`, `(x_m, x_v, x_u, id)`, with the row
//! histogram of that order: exactly what the band machinery of `outcore::band` reads.
//!
//! **Directions** are walked as the single-process out-of-core solver walks them
//! (`outcore::solver::walk_by_axis`): grouped by main axis, then by the slope of the lines along
//! `v`, on which the columns depend, so that few records move; every even iteration backwards
//! (`outcore::solver::walk_of_iteration`), so that it begins on the axis and with the
//! direction the iteration before ended on, where the held files are in order already
//! (`DataOocSweep::held_axis`): a re-sort fewer an iteration. For each direction, rank `r`
//! owns a contiguous range of line columns `j` (cut for equal surfels from the column histogram
//! added over ranks, in the first iteration, and remembered). The held records whose column is
//! now another rank's move there ([`route`]): in copy order, so the received runs are merged
//! and laid out around the kept records, which stay where they are; at a change of main axis
//! they are sorted instead. The direction is then solved band by band on the held
//! files (`outcore::band`); every line lies whole on one rank.
//!
//! **Runs of one slope** ([`runs_of`]): the directions after it in the walk with the same main
//! axis and slope along `v` put every surfel in the same column, so they have the same cuts and
//! nothing moves between them. One step gathers such a run: one routing, then passes over the
//! held files that read and write each band once for all the directions whose bands agree
//! (`outcore::solver::gathered_together`); the run's other steps do nothing. Every surfel adds
//! the same terms in the same order. The light between a run's steps cannot be saved, so every
//! group's runs are cut where another group's start, and checkpoints and stops inside an
//! iteration fall at those steps (`DataOocSweep::inside`).
//!
//! Every line is gathered from the same surfels in the same order as in the single-process
//! out-of-core solve, and every surfel adds its directions, and then its axes, in the same
//! order: the radiosity is that of `voxrad solve SET --memory SIZE` bit for bit (the stopping
//! rule's sums are added in another grouping).
//!
//! **Iteration end**: each rank updates `B` of its held surfels (their materials, normal and
//! area travel with them) with `solve::update`, as every loop; the stopping rule's sums are
//! added over ranks. A grey scene gathers one channel; the tail extrapolation adds its jump in
//! one more pass over the held files (the replaced radiosity waits in the earlier-axes slot).
//! **Output**: the `(id, B)` pairs go to rank 0 in bounded rounds, which places them in a
//! canonical radiosity file and streams the results from the source as the single-process path
//! does.
//!
//! **The direct-light pass** ([`direct`]): rank 0 runs the one-process out-of-core pass and
//! sends every rank its slice of the light, which then travels in the held records.
//!
//! **The loop** is the one of every path (`solve::iterate`, through [`DataOocSweep`]): a step
//! is one direction of every group.
//!
//! **Checkpoints** ([`DataOocCheckpoints`]): at a due iteration boundary the radiosity is
//! gathered to rank 0, which writes it as the single-process out-of-core solver does; on
//! resume rank 0 reads it and sends every rank its slice. Between any two steps (when one is
//! due, or on a stop signal, agreed on with `max_u64`) a checkpoint also holds every group's
//! light so far, by surfel id ([`within`]); a resume puts it back and goes on with the next
//! step, to the bytes of the uninterrupted run.
//!
//! **Hybrid** (`groups` > 1): every group holds the whole scene over its ranks and walks its
//! contiguous block of the directions (backwards in even iterations); at the end of an
//! iteration the groups route their surfels to the canonical slices (by id), and the update
//! adds the groups' light in walk order ([`Solver::add_groups`]) before it updates `B` in every
//! group (group 0 speaks for the sums and the results).
//!
//! **Memory**: as in `outcore` (one band, one sort piece, or one exchange round at a time, and
//! fixed I/O buffers), plus per direction its remembered cuts (`P + 1` numbers).

mod canonical;
mod direct;
pub mod held;
pub mod route;
mod slice;
mod summary;
mod within;

use super::data::PhaseSeconds;
use super::Comm;
use crate::checkpoint::{CheckpointFile, Saver, State};
use crate::geometry::directions::{Direction, DirectionSet};
use crate::geometry::lines::LineFrame;
use crate::outcore::band::{BandBuffers, BandTimes, CopyFiles, DirectionPass, StaticFile};
use crate::outcore::budget::MemoryPlan;
use crate::outcore::files::{
    decode_light32, decode_radiosity, encode_light32, encode_radiosity, IoCounters, SeqReader,
    GATHER_LEN, RADIOSITY_LEN, STATIC_LEN,
};
use crate::outcore::links::LinkStore;
use crate::outcore::solver::{gathered_together, v_slope, MOST_TOGETHER};
use crate::outcore::source::SurfelSource;
use crate::outcore::workset::AxisCopy;
use crate::outcore::OocError;
use crate::solve::iterate::{iterate, Start, Sweep};
use crate::solve::normalize::cosine_sums;
use crate::solve::{SolveOptions, SolveStats};
use crate::voxel::Surfel;
use held::{AxisKey, Held, HeldReader, HeldWriter, Wire, EARLIER_AT, GATHERED_AT};
use route::Router;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tempfile::TempDir;

/// The outcome on one rank: statistics (the same on every rank) and, on rank 0, the radiosity
/// in canonical order.
pub struct DataOocSolution {
    pub stats: SolveStats,
    pub voxels: u64,
    pub surfels: u64,
    pub bytes_read: u64,
    pub bytes_written: u64,
    pub bands: u64,
    pub setup_seconds: f64,
    work: TempDir,
    canonical: Option<PathBuf>,
    io_bytes: usize,
}

impl DataOocSolution {
    /// On rank 0: calls `f(surfel, radiosity)` for every surfel of `source` in canonical order.
    pub fn for_each<F>(&self, source: &dyn SurfelSource, mut f: F) -> Result<(), OocError>
    where
        F: FnMut(&Surfel, &[[f32; 3]; 2]) -> Result<(), OocError>,
    {
        let path = self.canonical.as_ref().ok_or_else(|| OocError::BadData {
            source_name: source.describe(),
            what: "only rank 0 holds the results".to_string(),
        })?;
        let mut radiosity = SeqReader::<RADIOSITY_LEN>::open(path, self.io_bytes)?;
        for s in source.stream(self.io_bytes as u64)? {
            let b = decode_radiosity(&radiosity.expect_record()?);
            f(&s?, &b)?;
        }
        Ok(())
    }

    /// The rank's work directory (removed when the solution is dropped).
    pub fn work_dir(&self) -> &Path {
        self.work.path()
    }
}

/// The checkpoints of a data-mode out-of-core solve: at iteration boundaries the radiosity is
/// gathered to canonical order on rank 0, which writes it (`Saver`); a resumed run starts from
/// one, which rank 0 reads and sends to the ranks in slices.
pub struct DataOocCheckpoints<'a> {
    pub saver: &'a mut Saver,
    /// On rank 0: the checkpoint to start from, opened and checked against the run.
    pub resume: Option<CheckpointFile>,
    /// On every rank: the state that checkpoint holds (`None`: start afresh).
    pub state: Option<State>,
}

/// Solves `source` over the ranks of `comm`, each within `budget` bytes, with its work files
/// in a new directory under `work_parent`: in the data mode (`groups` 1) or the hybrid mode
/// (`groups` groups of equal size, each taking a block of the directions with the whole scene
/// spread over its ranks).
#[allow(clippy::too_many_arguments)]
pub fn solve_data_out_of_core(
    source: &dyn SurfelSource,
    directions: &DirectionSet,
    options: &SolveOptions,
    comm: &dyn Comm,
    groups: usize,
    budget: u64,
    work_parent: &Path,
    checkpoints: Option<DataOocCheckpoints>,
) -> Result<DataOocSolution, OocError> {
    let threads = if options.threads == 0 {
        rayon::current_num_threads()
    } else {
        options.threads
    };
    crate::outcore::solver::one_malloc_arena();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| OocError::Threads {
            threads,
            message: e.to_string(),
        })?;
    let size = comm.size();
    if groups == 0 || size % groups != 0 {
        return Err(OocError::BadData {
            source_name: source.describe(),
            what: format!(
                "{size} ranks cannot form {groups} equal groups: give a --groups that divides \
                 the rank count"
            ),
        });
    }
    let group_index = comm.rank() / (size / groups);
    // Both splits are collective: every rank makes them, in this order.
    let group = comm.split(group_index);
    let peers = comm.split(group.rank());
    // The pool runs the threaded parts; every call of `comm` stays on this thread.
    let solver = Solver {
        source,
        directions,
        options,
        comm,
        group: group.as_ref(),
        peers: peers.as_ref(),
        groups,
        group_index,
        threads,
        pool: &pool,
        channels: std::cell::Cell::new(3),
        direct: std::cell::Cell::new(false),
        closed: std::cell::Cell::new(false),
    };
    solver.run(budget, work_parent, checkpoints)
}

struct Solver<'a> {
    source: &'a dyn SurfelSource,
    directions: &'a DirectionSet,
    options: &'a SolveOptions,
    /// Every rank.
    comm: &'a dyn Comm,
    /// This rank's group, which holds the whole scene over its ranks (the world in the data
    /// mode).
    group: &'a dyn Comm,
    /// The ranks at this rank's place in every group: they hold the same surfels at the end of
    /// an iteration and add their light.
    peers: &'a dyn Comm,
    groups: usize,
    /// This rank's group.
    group_index: usize,
    threads: usize,
    pool: &'a rayon::ThreadPool,
    /// Channels gathered, decided once the slices are read (see [`Solver::channels`]).
    channels: std::cell::Cell<usize>,
    /// The direct-light pass ran: the held records carry its light and the lines `B - E`.
    direct: std::cell::Cell<bool>,
    /// The scene's light is sealed in (`solve::closed`; rank 0 checks it on the whole source).
    closed: std::cell::Cell<bool>,
}

/// What one update of `B` found on this rank.
type Update = crate::solve::update::UpdateSums;

impl Solver<'_> {
    fn run(
        &self,
        budget: u64,
        work_parent: &Path,
        mut checkpoints: Option<DataOocCheckpoints>,
    ) -> Result<DataOocSolution, OocError> {
        let info = self.source.info();
        let dims = info.grid.dims;
        let (ranks, me) = (self.group.size(), self.comm.rank());
        // The readers of the held static and rest records' frames: the indexes of each set (of
        // each part, at most twice a rank's records, `held::MOST_SETS`: four shares), counted
        // as the one-process solver's three copies of four thirds of a share, and their
        // buffers.
        let framed = info.count.div_ceil(ranks as u64).div_ceil(3) * 4;
        let plan = MemoryPlan::new(budget, dims, self.threads, framed)?;
        // At a merge a rank holds its old and new held files and the received runs, about three
        // times its share; rank 0 also the canonical radiosity.
        let share = info.count.div_ceil(ranks as u64) * held::WIRE_LEN as u64;
        let canonical_bytes = if me == 0 {
            info.count * RADIOSITY_LEN as u64
        } else {
            0
        };
        crate::outcore::workset::check_free_space(work_parent, 3 * share + canonical_bytes)?;
        let work = tempfile::Builder::new()
            .prefix(&format!("{}{me}-", crate::checkpoint::RANK_WORK_DIR_PREFIX))
            .tempdir_in(work_parent)
            .map_err(|e| OocError::io(work_parent, "create a work directory in", e))?;
        let dir = work.path();
        let router = Router {
            comm: self.group,
            plan: &plan,
            dir,
        };
        let mut io = IoCounters::default();
        let started = Instant::now();
        let t = Instant::now();
        let cosine_sum = self
            .pool
            .install(|| cosine_sums(&info.normals, self.directions));
        let normalize_seconds = t.elapsed().as_secs_f64();
        let slice = self.read_slice(&plan, dir, &cosine_sum, &mut io)?;
        // Whether the scene is closed: rank 0 reads the whole source once, as for the direct
        // pass, and tells the others.
        let verdict = if me == 0 {
            crate::outcore::solver::closure_verdict(self.source, &plan, &mut io)?
        } else {
            crate::solve::enclosure::Verdict::default()
        };
        self.closed
            .set(self.comm.max_u64(u64::from(verdict.closed)) == 1);
        // Every group holds the whole scene.
        let mut counts = [slice.voxels as f64, slice.held.count as f64];
        self.group.sum_in_place(&mut counts);
        let [voxels, surfels] = counts.map(|c| c as u64);
        let any_light = self.comm.max_u64(slice.any_light as u64) == 1;
        // Grey decided on the materials the surfels use, as the one-process solvers decide it:
        // a caller's `grey` alone would solve a coloured scene in one channel.
        let coloured = self.comm.max_u64(slice.coloured as u64) == 1;
        self.channels
            .set(if self.options.grey && !coloured { 1 } else { 3 });
        let setup_seconds = started.elapsed().as_secs_f64();
        let mut held = slice.held;
        let mut generation = 0u64;
        let mut stats = SolveStats {
            directions: self.directions.len(),
            threads: self.threads,
            channels: self.channels(),
            normalize_seconds,
            ..Default::default()
        };
        // The direct light, once, before a checkpoint's radiosity is put in (the lines then
        // carry `B - E`), as the one-process out-of-core solver does it (`direct`).
        let mut emitting = [slice.emitting as f64];
        self.group.sum_in_place(&mut emitting);
        let shape = crate::solve::direct::Shape {
            emitting: emitting[0] as usize,
            surfels: surfels as usize,
            longest_axis: dims.into_iter().max().unwrap_or(0),
            directions: self.directions.len(),
        };
        if let Some(count) = self.options.direct.resolve(shape).filter(|_| any_light) {
            generation += 1;
            let (next, direct) =
                self.attach_direct(held, slice.first, count, generation, &router, &mut io)?;
            held = next;
            stats.direct = Some(direct);
            self.direct.set(true);
        }
        let d_count = self.directions.len();
        let steps = d_count.div_ceil(self.groups);
        let mut start = Start::fresh();
        if let Some(c) = checkpoints.as_mut() {
            if let Some(state) = c.state.take() {
                let file = c.resume.take();
                held = self.restore(
                    held,
                    slice.first,
                    (file.as_ref(), state.extrapolation.chebyshev.is_some()),
                    &mut generation,
                    &router,
                    &mut io,
                )?;
                let inside = self.continues_inside(&state, steps);
                if let Some(done) = inside {
                    held = self.restore_inside(
                        held,
                        slice.first,
                        file.as_ref(),
                        &mut generation,
                        &router,
                        &mut io,
                    )?;
                    if me == 0 {
                        tracing::info!(
                            iteration = state.iteration + 1,
                            within = done,
                            "continuing inside an iteration from the checkpoint's partial sums"
                        );
                    }
                }
                let within = inside.unwrap_or(0) as usize;
                start = Start::resumed(&state, c.saver.path(), within, &mut stats);
            }
        }

        // The single-process out-of-core solver's order of odd iterations (the same answer bit
        // for bit), of which a group takes its contiguous block (all of it in the data mode),
        // and walks it backwards in even iterations, as that solver does
        // (`outcore::solver::walk_of_iteration`): a group keeps its directions (and their
        // links). Every group's, for where the light of any can be saved
        // (`DataOocSweep::inside`).
        let by_axis = crate::outcore::solver::walk_by_axis(self.directions);
        let walk: Vec<(usize, usize)> = crate::outcore::solver::walk_of_iteration(&by_axis, 1)
            .into_iter()
            .flat_map(|(m, axis)| axis.into_iter().map(move |d| (m, d)))
            .collect();
        let walks = [false, true].map(|backwards| {
            (0..self.groups)
                .map(|g| {
                    let mut block =
                        walk[d_count * g / self.groups..d_count * (g + 1) / self.groups].to_vec();
                    if backwards {
                        block.reverse();
                    }
                    walk_steps(&block)
                })
                .collect::<Vec<Vec<WalkStep>>>()
        });
        let starts = self.slice_starts(slice.first);
        // The links files' allowance: the ranks of one node share its disk, and a merge adds
        // about two shares to the held files on it now (see the check above). Rank 0 writes the
        // checkpoints, from arrays it first gathers in its work directory: on its node their
        // room is set aside before the links' (two checkpoints where `--out` shares that disk,
        // and the gathered arrays).
        let mates = crate::solve::links::node_mates(self.comm);
        let checkpoint_room = match (me, checkpoints.as_ref()) {
            (0, Some(c)) => {
                use crate::outcore::workset::{checkpoint_bytes_per_surfel, checkpoint_growth};
                let per_surfel = checkpoint_bytes_per_surfel(2 * self.groups as u64);
                checkpoint_growth(c.saver.path(), dir, surfels, per_surfel) + surfels * per_surfel
            }
            _ => 0,
        };
        let checkpoint_room = self.comm.max_u64(checkpoint_room);
        let still_needed = 2 * share
            + canonical_bytes
            + match mates.with_rank_0 {
                true => checkpoint_room.div_ceil(mates.count as u64),
                false => 0,
            };
        if me == 0 && checkpoint_room > 0 {
            let needed = still_needed * mates.count as u64;
            match crate::outcore::workset::free_bytes(dir) {
                Some(free) if free < needed => tracing::warn!(
                    free = crate::outcore::budget::format_bytes(free),
                    needed = crate::outcore::budget::format_bytes(needed),
                    "the work files of this node's ranks and two checkpoints do not fit on the \
                     disk: checkpoints that do not fit are not written, and the solve goes on \
                     without them"
                ),
                _ => {}
            }
        }
        let links_allowance = crate::outcore::links::allowance(
            dir,
            self.options.links_disk,
            still_needed,
            mates.count as u64,
        );
        let links = LinkStore::new(dir, d_count, links_allowance, surfels, plan.io_bytes);
        let mut sweep = DataOocSweep {
            solver: self,
            router: &router,
            dir,
            plan: &plan,
            cosine_sum: &cosine_sum,
            largest_share: held.count,
            held: Some(held),
            generation,
            walk: Vec::new(),
            runs: Vec::new(),
            inside: Vec::new(),
            walks,
            backwards: false,
            steps,
            starts,
            remembered: vec![None; d_count],
            imbalance: vec![0.0; d_count],
            moved: vec![0.0; d_count],
            quiet: [vec![None; d_count], vec![None; d_count]],
            quiet_steps_skipped: 0,
            histogram: Vec::new(),
            links,
            times: BandTimes::default(),
            seconds: PhaseSeconds::default(),
            io,
            last: Update::default(),
            scales: crate::solve::closed::Scales::ONE,
            earlier_any: false,
            pending: false,
            held_axis: None,
            surfels,
        };
        let saver = checkpoints.map(|c| c.saver);
        iterate(
            &mut sweep,
            self.options,
            self.comm,
            saver,
            start,
            any_light,
            &mut stats,
        )?;
        let DataOocSweep {
            held,
            moved,
            imbalance,
            times,
            mut seconds,
            mut io,
            last,
            largest_share,
            links,
            scales,
            quiet_steps_skipped,
            ..
        } = sweep;
        stats.closure = Some(crate::solve::stats::ClosureStats {
            verdict: crate::solve::enclosure::Verdict {
                closed: self.closed.get(),
                ..verdict
            },
            scales,
        });
        stats.links = Some(links.stats(self.comm));
        let held = held.expect("held files between steps");
        // Group 0 speaks for every surfel once.
        let mut energy = [last.emitted, last.absorbed, last.absorbed_direct].concat();
        if self.group_index != 0 {
            energy.fill(0.0);
        }
        self.comm.sum_in_place(&mut energy);
        stats.emitted_power.copy_from_slice(&energy[..3]);
        for ch in 0..3 {
            // As every loop: the direct light's power after the reflected one's.
            stats.absorbed_power[ch] = energy[3 + ch] + energy[6 + ch];
        }
        // A band's reading counts with its dispatch, writing its light with its propagation.
        seconds.dispatch = times.dispatch + times.read;
        seconds.propagate = times.propagate + times.write;
        stats.dispatch_seconds = times.dispatch;
        stats.propagate_seconds = times.propagate;
        stats.reduce_seconds = seconds.reduce;

        let t = Instant::now();
        let canonical = self.gather_results(&held, surfels, (dir, &plan), true, &mut io)?;
        held.remove()?;
        seconds.reduce += t.elapsed().as_secs_f64();

        let tally = summary::Tally {
            moved,
            imbalance,
            seconds,
            io,
            largest_share,
            bands: times.bands,
            joint: (times.joint_passes, times.joint_directions),
            quiet_steps_skipped,
        };
        let totals = self.summarize(&tally, surfels, stats.iterations);
        stats.data = Some(totals.data);
        // The held files went above; the rest (links, direct light) go too before the outputs
        // are written, as one process does: rank 0 keeps the answer in canonical order.
        crate::outcore::files::remove_all_but(work.path(), canonical.as_deref());
        Ok(DataOocSolution {
            stats,
            voxels,
            surfels,
            bytes_read: totals.bytes_read,
            bytes_written: totals.bytes_written,
            bands: totals.bands,
            setup_seconds,
            work,
            canonical,
            io_bytes: plan.io_bytes,
        })
    }

    /// The steps of its iteration that a checkpoint's `state` holds, when this solve can
    /// continue inside that iteration: a mid-iteration checkpoint of the data or hybrid mode out
    /// of core with as many groups (any rank count). Else the iteration starts again from its
    /// beginning (the same radiosity, so the same answer), said on rank 0.
    fn continues_inside(&self, state: &State, steps: usize) -> Option<u64> {
        let done = state.within?;
        let ours = state.axis_in_progress
            && state.data_groups == self.groups as u32
            && (done as usize) < steps;
        if !ours && self.comm.rank() == 0 {
            let layout = match (state.data_groups, state.axis_in_progress) {
                (0, _) => "by directions, in one process".to_string(),
                (1, true) => "in the data mode out of core".to_string(),
                (g, true) => format!("in the hybrid mode out of core, {g} groups"),
                (g, false) => format!("in the data or hybrid mode, {g} group(s)"),
            };
            tracing::info!(
                "the checkpoint is {done} steps into iteration {} (written {layout}); this \
                 solve ({} group(s) out of core) cannot continue inside it, so that iteration \
                 starts from its beginning",
                state.iteration + 1,
                self.groups
            );
        }
        ours.then_some(done)
    }

    /// Surfels per line column of `frame`, added over ranks: from `rows`, the held files' row
    /// histogram, where they are in the copy order of `frame`'s main axis (a column holds
    /// whole rows of each layer), else from their static records.
    fn column_load(
        &self,
        held: &Held,
        frame: &LineFrame,
        rows: Option<&[u32]>,
        plan: &MemoryPlan,
        io: &mut IoCounters,
    ) -> Result<Vec<f64>, OocError> {
        let mut load = vec![0.0f64; frame.nj as usize];
        if let Some(histogram) = rows {
            let per_layer = self.source.info().grid.dims[frame.v] as usize;
            for (layer, counts) in histogram.chunks(per_layer.max(1)).enumerate() {
                let shift = frame.layer_shift(layer).1 as usize;
                for (row, &count) in counts.iter().enumerate() {
                    load[row + shift] += count as f64;
                }
            }
            self.group.sum_in_place(&mut load);
            return Ok(load);
        }
        let statics = held.open_files()?.statics;
        let chunk = (plan.io_bytes / STATIC_LEN).max(1) as u64;
        let mut bytes = Vec::new();
        let mut at = 0u64;
        while at < held.count {
            let records = chunk.min(held.count - at);
            bytes.resize(records as usize * STATIC_LEN, 0);
            statics.read(at, &mut bytes, io)?;
            for r in bytes.chunks_exact(STATIC_LEN) {
                let v = held::voxel(r);
                let j = v[frame.v] as u64 + frame.layer_shift(v[frame.main] as usize).1;
                load[j as usize] += 1.0;
            }
            at += records;
        }
        self.group.sum_in_place(&mut load);
        Ok(load)
    }

    /// Directions `run` (of one slope along `v`, in walk order) over the held files, band by
    /// band (`outcore::band`), with their partner links in `links`: in as few passes as their
    /// bands and links allow (`outcore::solver::gathered_together`), each band read and written
    /// once for all the directions of a pass. `first`: the run starts the axis (its first pass
    /// reads no earlier light).
    #[allow(clippy::too_many_arguments)]
    fn solve_run(
        &self,
        held: &Held,
        histogram: &[u32],
        key: AxisKey,
        run: &[usize],
        links: &mut LinkStore,
        first: bool,
        plan: &MemoryPlan,
        io: &mut IoCounters,
        times: &mut BandTimes,
    ) -> Result<(), OocError> {
        let rows = key.rows();
        let mut layer_start = Vec::with_capacity(key.layers() + 1);
        let mut start = 0u64;
        layer_start.push(0);
        for layer in histogram.chunks(rows.max(1)).take(key.layers()) {
            start += layer.iter().map(|&h| h as u64).sum::<u64>();
            layer_start.push(start);
        }
        let copy = AxisCopy {
            main: key.main,
            u: key.u,
            v: key.v,
            layers: key.layers(),
            rows,
            // Opened below from the held files, which may lie in several sets.
            statics: PathBuf::new(),
            statics_index: PathBuf::new(),
            radiosity: PathBuf::new(),
            ids: PathBuf::new(),
            positions: PathBuf::new(),
            histogram: PathBuf::new(),
            layer_start,
        };
        let held::HeldFiles {
            statics,
            radiosity,
            gathered,
            ..
        } = held.open_files()?;
        let files = CopyFiles {
            statics: StaticFile::Runs(statics),
            radiosity,
            gathered,
            previous: None,
        };
        let mut pass = DirectionPass {
            copy: &copy,
            files: &files,
            histogram,
            dims: self.source.info().grid.dims,
            plan,
            threads: self.threads,
            channels: self.channels(),
            first,
            // The ranks agree on stops between steps: a direction is never left half done.
            stops_on_signal: false,
        };
        // Fresh band arrays: they must not hold their memory through the next merge.
        let mut buffers = BandBuffers::default();
        let mut k = 0;
        while k < run.len() {
            let together = gathered_together(&pass, self.directions, run, k, links);
            links.begin_together(&together)?;
            let ds: Vec<&Direction> = together
                .iter()
                .map(|&d| &self.directions.directions[d])
                .collect();
            self.pool.install(|| {
                pass.run_together(&ds, &mut links.band_links(), &mut buffers, io, times)
            })?;
            // The ranks stop between steps only: a direction is always gathered whole.
            links.end(true);
            times.joint_passes += (together.len() > 1) as u64;
            times.joint_directions += (together.len() - 1) as u64;
            pass.first = false;
            k += together.len();
        }
        Ok(())
    }

    /// `B = E + rho H / S(n)` on the held surfels, after adding the last axis's light to the
    /// earlier ones (`fold`: `Some(first)` when an axis is pending, `first` when it is the only
    /// one; in the hybrid mode, every group's, see [`Solver::add_groups`], in the order of
    /// the walk, `backwards` or not). Writes new held files (generation `generation`) with the
    /// light cleared.
    #[allow(clippy::too_many_arguments)]
    fn update(
        &self,
        held: Held,
        generation: u64,
        dir: &Path,
        plan: &MemoryPlan,
        cosine_sum: &[f64],
        (fold, backwards): (Option<bool>, bool),
        (scales, omega): (&crate::solve::closed::Scales, f64),
        io: &mut IoCounters,
    ) -> Result<(Held, Update), OocError> {
        let info = self.source.info();
        let area_unit = info.grid.voxel_size * info.grid.voxel_size;
        let mut reader = HeldReader::consuming(&held, plan.io_bytes)?;
        let mut writer = HeldWriter::create(dir, generation, plan.io_bytes, None, held.direct)?;
        let mut result = Update::default();
        let groups = self.peers.size();
        // Records in memory at once: a quarter of the working memory, with their light (in the
        // hybrid mode, every group's two parts).
        let light_len = match groups {
            1 => GATHER_LEN,
            g => 2 * g * GATHER_LEN,
        };
        let chunk = (plan.working / 4 / (held::WIRE_LEN + light_len) as u64).max(1) as usize;
        let mut records: Vec<Wire> = Vec::with_capacity(chunk.min(held.count as usize));
        let mut light: Vec<f64> = Vec::new();
        loop {
            records.clear();
            while records.len() < chunk {
                let Some(mut w) = reader.next(io)? else {
                    break;
                };
                if let (Some(first), 1) = (fold, groups) {
                    fold_axis(&mut w, first);
                }
                records.push(w);
            }
            if records.is_empty() {
                break;
            }
            if groups > 1 {
                // The parts this group holds: without an axis pending, the earlier field holds
                // every axis it did (zeros if none).
                let parts = match fold {
                    Some(first) => (!first, true),
                    None => (true, false),
                };
                self.add_groups(&mut records, &mut light, backwards, parts);
            }
            for w in records.iter_mut() {
                let previous = decode_radiosity(&w[held::RADIOSITY_AT..]);
                let (normal_id, area, material) = held::scene_data(w);
                // The update of every loop (`solve::update`), term by term.
                let sides = material.map(|m| &info.materials[m as usize]);
                let (h, norm) = (
                    decode_light32(&w[EARLIER_AT..]),
                    cosine_sum[normal_id as usize],
                );
                let direct = self.direct().then(|| decode_light32(&w[held::DIRECT_AT..]));
                // The Chebyshev semi-iteration's radiosity before last.
                let older = (omega != 1.0).then(|| decode_radiosity(&w[held::OLDER_AT..]));
                let b_new = crate::solve::update::update_surfel(
                    &sides.map(|m| m.emission.map(|e| e as f32)),
                    &sides.map(|m| m.reflectance),
                    h,
                    direct.as_ref(),
                    self.channels(),
                    &previous,
                    older.as_ref().map(|o| (o, omega)),
                    norm,
                    area as f64,
                    scales,
                    &mut result,
                );
                crate::solve::update::add_power(
                    sides,
                    h,
                    direct.as_ref(),
                    self.channels(),
                    norm,
                    area as f64,
                    area_unit,
                    scales,
                    &mut result,
                );
                encode_radiosity(&b_new, &mut w[held::RADIOSITY_AT..]);
                canonical::carry(w, info, self.direct());
                w[GATHERED_AT..held::SCENE_AT].fill(0);
                if self.options.accelerate {
                    // Kept for the tail extrapolation and the Chebyshev semi-iteration.
                    encode_radiosity(&previous, &mut w[held::OLDER_AT..]);
                }
                writer.write(w)?;
            }
        }
        drop(reader);
        held.remove()?;
        let (held, _) = writer.finish(io)?;
        Ok((held, result))
    }

    /// The hybrid mode's light of `records`: every group's rank at this place holds the same
    /// surfels in the same order now (`DataOocSweep::end`), each with the light of its group's
    /// directions in two parts, its earlier axes' (folded) and its last axis's (not yet). Every
    /// group's parts go to every group, each in slots of its own (zeros elsewhere, so that the
    /// sum over groups moves them exactly); every rank then folds them in the order of the walk
    /// (the groups in turn, backwards where the walk is, each group's earlier axes before its
    /// last), with `fold_axis`'s rounding, into the earlier axes' field. Where every group's
    /// directions begin on a main axis and span at most two, this adds the axes as one
    /// process adds them: the same bits. `(earlier, last)`: which parts this group has.
    fn add_groups(
        &self,
        records: &mut [Wire],
        light: &mut Vec<f64>,
        backwards: bool,
        (earlier, last): (bool, bool),
    ) {
        const PARTS: usize = 12;
        let groups = self.peers.size();
        let me = self.group_index;
        light.clear();
        light.resize(records.len() * groups * PARTS, 0.0);
        for (w, slots) in records.iter().zip(light.chunks_exact_mut(groups * PARTS)) {
            let ours = &mut slots[me * PARTS..(me + 1) * PARTS];
            for (has, at, slots) in [(earlier, EARLIER_AT, 0..6), (last, GATHERED_AT, 6..12)] {
                if has {
                    let part = decode_light32(&w[at..]);
                    for (slot, &value) in ours[slots].iter_mut().zip(part.iter().flatten()) {
                        *slot = value;
                    }
                }
            }
        }
        self.peers.sum_in_place(light);
        for (w, slots) in records.iter_mut().zip(light.chunks_exact(groups * PARTS)) {
            let mut sum = [[0.0f64; 3]; 2];
            for g in 0..groups {
                let g = if backwards { groups - 1 - g } else { g };
                for part in slots[g * PARTS..(g + 1) * PARTS].chunks_exact(6) {
                    // Rounded to f32 at each fold, as `fold_axis` rounds (adding a zero part
                    // changes nothing).
                    for (t, &v) in sum.iter_mut().flatten().zip(part) {
                        *t = (*t + v) as f32 as f64;
                    }
                }
            }
            encode_light32(&sum, &mut w[EARLIER_AT..]);
        }
    }

    /// A closed scene's scales for the update of `held` (`solve::closed`): its light folded as
    /// the update folds it, the sums added over every rank (collective). In the hybrid mode the
    /// ranks of every group hold the same surfels, each with its group's light: every rank adds
    /// what its surfels gathered, group 0 alone what they sent, emit and took from the direct
    /// pass.
    fn closure_scales(
        &self,
        held: &Held,
        plan: &MemoryPlan,
        cosine_sum: &[f64],
        fold: Option<bool>,
        io: &mut IoCounters,
    ) -> Result<crate::solve::closed::Scales, OocError> {
        let info = self.source.info();
        let mut sums = crate::solve::closed::ClosureSums::new(&info.materials);
        let mut reader = HeldReader::open(held, plan.io_bytes)?;
        while let Some(mut w) = reader.next(io)? {
            if let Some(first) = fold {
                fold_axis(&mut w, first);
            }
            let (normal_id, area, material) = held::scene_data(&w);
            let (h, norm) = (
                decode_light32(&w[EARLIER_AT..]),
                cosine_sum[normal_id as usize],
            );
            if self.group_index != 0 {
                sums.add_gathered(&h, self.channels(), norm, area as f64);
                continue;
            }
            let emission = material.map(|m| info.materials[m as usize].emission.map(|e| e as f32));
            let previous = decode_radiosity(&w[held::RADIOSITY_AT..]);
            let direct = self.direct().then(|| decode_light32(&w[held::DIRECT_AT..]));
            sums.add(
                &emission,
                &crate::solve::update::carried(&previous, &emission, self.direct()),
                &h,
                direct.as_ref(),
                self.channels(),
                norm,
                area as f64,
            );
        }
        sums.add_over(self.comm);
        Ok(sums.scales(self.channels()))
    }

    /// Channels gathered: 1 for a grey scene (asked for by `options.grey` and checked on the
    /// materials the surfels use when the slices are read), else 3.
    fn channels(&self) -> usize {
        self.channels.get()
    }

    /// Whether the direct-light pass ran (see [`Solver::attach_direct`]).
    fn direct(&self) -> bool {
        self.direct.get()
    }

    /// Adds the geometric tail `factor * (B - B_previous)` to the held surfels' radiosity with
    /// `accelerate::extrapolate`'s rules (the previous radiosity was kept in the older field
    /// by [`Solver::update`]). Writes new held files (generation `generation`).
    fn extrapolate(
        &self,
        held: Held,
        generation: u64,
        dir: &Path,
        plan: &MemoryPlan,
        factor: f64,
        io: &mut IoCounters,
    ) -> Result<Held, OocError> {
        let info = self.source.info();
        let mut reader = HeldReader::consuming(&held, plan.io_bytes)?;
        let mut writer = HeldWriter::create(dir, generation, plan.io_bytes, None, held.direct)?;
        while let Some(mut w) = reader.next(io)? {
            let mut b = [decode_radiosity(&w[held::RADIOSITY_AT..])];
            let previous = [decode_radiosity(&w[held::OLDER_AT..])];
            let (_, _, material) = held::scene_data(&w);
            let emission =
                [material.map(|m| info.materials[m as usize].emission.map(|e| e as f32))];
            crate::solve::accelerate::extrapolate(&mut b, &previous, &emission, factor);
            encode_radiosity(&b[0], &mut w[held::RADIOSITY_AT..]);
            canonical::carry(&mut w, info, self.direct());
            writer.write(&w)?;
        }
        drop(reader);
        held.remove()?;
        let (held, _) = writer.finish(io)?;
        Ok(held)
    }
}

/// The steps of a walk of `(main axis, direction)`, each knowing whether it starts or ends its
/// axis.
fn walk_steps(walk: &[(usize, usize)]) -> Vec<WalkStep> {
    walk.iter()
        .enumerate()
        .map(|(k, &(main, direction))| WalkStep {
            main,
            first: k == 0 || walk[k - 1].0 != main,
            last: walk.get(k + 1).is_none_or(|next| next.0 != main),
            direction,
        })
        .collect()
}

/// One step of the walk: a direction, its main axis, and whether it starts or ends the axis.
#[derive(Clone, Copy)]
struct WalkStep {
    main: usize,
    first: bool,
    last: bool,
    direction: usize,
}

/// The data mode out of core as the iteration loop drives it: this rank's held files (a store
/// on disk), line columns dealt over the ranks per direction.
struct DataOocSweep<'s, 'a> {
    solver: &'s Solver<'a>,
    router: &'s Router<'s>,
    dir: &'s Path,
    plan: &'s MemoryPlan,
    cosine_sum: &'s [f64],
    /// The held files (taken while a step or the update rewrites them).
    held: Option<Held>,
    /// Numbers the held files' generations.
    generation: u64,
    /// This group's directions in this iteration.
    walk: Vec<WalkStep>,
    /// Every group's directions, in odd and in even iterations
    /// (`outcore::solver::walk_of_iteration`).
    walks: [Vec<Vec<WalkStep>>; 2],
    /// This iteration walks backwards (the second of `walks`).
    backwards: bool,
    /// By step of this iteration, the steps of this group's run of directions that start
    /// there (0: inside a run, gathered at its start; see [`runs_of`]).
    runs: Vec<usize>,
    /// By steps done, whether some group is inside a run then: its light holds later
    /// directions, and cannot be saved there (the same on every rank).
    inside: Vec<bool>,
    /// Steps of an iteration: one direction of every group each (a group with one direction
    /// fewer idles in the last).
    steps: usize,
    /// The first canonical index of every rank's slice in the group.
    starts: Vec<u64>,
    /// Each direction's column cuts, found in the first iteration.
    remembered: Vec<Option<Vec<u64>>>,
    imbalance: Vec<f64>,
    moved: Vec<f64>,
    /// By direction, in odd and in even iterations: whether its step moved no record on any
    /// rank, where it ran on held files in the order of the step before (inside an axis, or
    /// on the axis the iteration before ended on), as found the first time (none: not known
    /// yet). Which records a rank holds after a step depends on that step's column cuts
    /// alone, and the cuts are remembered, so such a step moves nothing in every later
    /// iteration of the same walk either, and is skipped without reading the held files to
    /// find out.
    quiet: [Vec<Option<bool>>; 2],
    quiet_steps_skipped: u64,
    /// The row histogram of the held files' order.
    histogram: Vec<u32>,
    /// Each direction's partner links on this rank, in files (`outcore::links`): the rank's
    /// held surfels of a direction, and their order, are the same in every iteration once its
    /// column cuts are remembered.
    links: LinkStore,
    times: BandTimes,
    seconds: PhaseSeconds,
    io: IoCounters,
    /// The last update's sums on this rank (its energy).
    last: Update,
    /// The scales of the last update (a closed scene's; else 1), the same on every rank.
    scales: crate::solve::closed::Scales,
    largest_share: u64,
    /// `earlier` holds the light of an axis done this iteration.
    earlier_any: bool,
    /// `gathered` holds the light of an axis done, not yet added to `earlier` (that happens
    /// when the next axis starts, or at the update).
    pending: bool,
    /// The main axis in whose copy order the held files are: the last step's (a step on that
    /// axis then merges what moves, inside an axis or at the start of an iteration that begins
    /// on the axis the one before ended on). `None` after a resume or the hybrid mode's
    /// update (canonical order): they are sorted again.
    held_axis: Option<usize>,
    surfels: u64,
}

impl DataOocSweep<'_, '_> {
    fn held(&self) -> &Held {
        self.held.as_ref().expect("held files between steps")
    }

    fn take_held(&mut self) -> Held {
        self.held.take().expect("held files between steps")
    }
}

impl Sweep for DataOocSweep<'_, '_> {
    type Error = OocError;

    fn steps(&self) -> usize {
        self.steps
    }

    fn updates(&self) -> u64 {
        self.surfels * self.solver.directions.len() as u64
    }

    fn begin(&mut self, iteration: usize, from: usize) -> Result<(), OocError> {
        self.backwards = crate::outcore::solver::walks_backwards(iteration);
        let walks = &self.walks[self.backwards as usize];
        self.walk = walks[self.solver.group_index].clone();
        // From a mid-iteration checkpoint (`from` > 0) the sum of the axes done is whole in
        // `earlier` (`within`), and the held files are in canonical order.
        self.earlier_any = within::axes_done(&self.walk, from);
        self.pending = false;
        if from > 0 {
            self.held_axis = None;
        }
        // Runs from where this iteration starts, on every rank for every group alike. A run
        // is cut where another group's starts, so that the groups' light can be saved
        // together there (a checkpoint, or a stop, inside the iteration).
        let directions = self.solver.directions;
        let runs: Vec<Vec<usize>> = walks
            .iter()
            .map(|walk| runs_of(walk, from, directions))
            .collect();
        let mut starts = vec![false; self.steps + 1];
        for (k, start) in starts.iter_mut().enumerate() {
            *start = runs.iter().any(|r| r.get(k).is_some_and(|&len| len > 0));
        }
        self.inside = vec![false; self.steps + 1];
        for (g, mut group_runs) in runs.into_iter().enumerate() {
            cut_at(&mut group_runs, &starts);
            for (k, &len) in group_runs.iter().enumerate() {
                for done in k + 1..k + len {
                    self.inside[done] = true;
                }
            }
            if g == self.solver.group_index {
                self.runs = group_runs;
            }
        }
        Ok(())
    }

    fn step(&mut self, step: usize) -> Result<bool, OocError> {
        let solver = self.solver;
        let ranks = solver.group.size();
        let dims = solver.source.info().grid.dims;
        let Some(&WalkStep {
            main,
            first,
            direction: d,
            ..
        }) = self.walk.get(step)
        else {
            return Ok(true);
        };
        let run_len = self.runs[step];
        if run_len == 0 {
            // Gathered with the directions before it, at the start of their run.
            return Ok(true);
        }
        let run: Vec<usize> = self.walk[step..step + run_len]
            .iter()
            .map(|s| s.direction)
            .collect();
        let last = self.walk[step + run_len - 1].last;
        let key = AxisKey::new(main, dims);
        let direction = &solver.directions.directions[d];
        let frame = LineFrame::new(direction.vector, dims);
        let t = Instant::now();
        if self.remembered[d].is_none() {
            let held = self.held.as_ref().expect("held files between steps");
            // Inside an axis the held files are in its copy order: their row histogram holds
            // the load (the same counts as their records, without reading them).
            let rows = (self.held_axis == Some(main)).then_some(self.histogram.as_slice());
            let load = solver.column_load(held, &frame, rows, self.plan, &mut self.io)?;
            let cuts = cut_columns(&load, ranks);
            self.imbalance[d] = imbalance_of(&load, &cuts);
            self.remembered[d] = Some(cuts);
        }
        // The run's later directions have the same columns, so the same cuts: each rank holds
        // their lines whole once it holds the first one's, and nothing moves between them.
        for &later in &run[1..] {
            if self.remembered[later].is_none() {
                self.remembered[later] = self.remembered[d].clone();
                self.imbalance[later] = self.imbalance[d];
            }
            debug_assert!(self.remembered[later] == self.remembered[d]);
        }
        self.seconds.balance += t.elapsed().as_secs_f64();
        let cuts = self.remembered[d].as_deref().expect("just cut");
        let owner = |w: &Wire| {
            let v = held::voxel(w);
            let j = v[frame.v] as u64 + frame.layer_shift(v[frame.main] as usize).1;
            cuts[1..ranks].partition_point(|&c| c <= j)
        };
        // The rows `v` of a layer whose column `j = v + shift` is this rank's: `owner` names
        // this rank for exactly these.
        let me = solver.group.rank();
        let (first_column, end_column) = (
            if me == 0 { 0 } else { cuts[me] },
            if me + 1 == ranks {
                u64::MAX
            } else {
                cuts[me + 1]
            },
        );
        let kept_rows = |layer: usize| {
            let shift = frame.layer_shift(layer).1;
            (
                first_column.saturating_sub(shift),
                end_column.saturating_sub(shift),
            )
        };
        let fold = first && self.pending;
        let first_fold = !self.earlier_any;
        let mut transform = |w: &mut Wire| {
            if fold {
                fold_axis(w, first_fold);
            }
        };
        // On held files in this axis's order, left by the step before (inside the axis, or
        // the iteration before's last): a merge, and a step that moved nothing before moves
        // nothing again (see `quiet`). The same on every rank. (No axis's light is folded
        // there: that happens at a change of axis.)
        let steady = self.held_axis == Some(main);
        debug_assert!(
            !(steady && fold),
            "a fold on held files in its axis's order"
        );
        let quiet = &mut self.quiet[self.backwards as usize];
        let held = self.held.take().expect("held files between steps");
        let (next, rows, sent) = if steady && quiet[d] == Some(true) {
            self.quiet_steps_skipped += 1;
            (held, std::mem::take(&mut self.histogram), 0)
        } else {
            self.generation += 1;
            let moved = self.router.redistribute(
                held,
                self.generation,
                key,
                steady,
                std::mem::take(&mut self.histogram),
                &owner,
                Some(&kept_rows),
                &mut transform,
                &mut self.io,
                &mut self.seconds,
            )?;
            if steady && quiet[d].is_none() {
                // Collective: every rank is here at this step.
                quiet[d] = Some(self.router.comm.max_u64(moved.2) == 0);
            }
            moved
        };
        if fold {
            self.earlier_any = true;
            self.pending = false;
        }
        self.held_axis = Some(main);
        self.largest_share = self.largest_share.max(next.count);
        self.held = Some(next);
        self.histogram = rows;
        self.moved[d] += sent as f64;
        solver.solve_run(
            self.held.as_ref().expect("held files between steps"),
            &self.histogram,
            key,
            &run,
            &mut self.links,
            first,
            self.plan,
            &mut self.io,
            &mut self.times,
        )?;
        if last {
            self.pending = true;
        }
        Ok(true)
    }

    fn can_save_within(&self, done: usize) -> bool {
        // After the last step the iteration's boundary is next; inside a run, the light holds
        // its later directions already.
        done < self.steps && !self.inside[done]
    }

    fn save_within(
        &mut self,
        saver: &mut Saver,
        state: State,
        done: usize,
    ) -> Result<(), crate::checkpoint::CheckpointError> {
        self.save_inside(saver, state, done)
    }

    fn save_boundary(
        &mut self,
        saver: &mut Saver,
        state: State,
    ) -> Result<(), crate::checkpoint::CheckpointError> {
        // Collective: every rank sends its radiosity, rank 0 writes.
        let mut io = IoCounters::default();
        let chebyshev = state.extrapolation.chebyshev.is_some();
        let mut gather = || -> Result<_, OocError> {
            let radiosity = self.solver.gather_results(
                self.held(),
                self.surfels,
                (self.dir, self.plan),
                false,
                &mut io,
            )?;
            // While Chebyshev runs, also the radiosity before last (every rank has the state).
            let older = match chebyshev {
                true => self.solver.gather_older(
                    self.held(),
                    self.surfels,
                    "older-canonical.bin",
                    (self.dir, self.plan),
                    &mut io,
                )?,
                false => None,
            };
            Ok((radiosity, older))
        };
        let gathered = gather();
        self.io.read += io.read;
        self.io.written += io.written;
        let (canonical, older) = gathered.map_err(|e| crate::checkpoint::CheckpointError::Io {
            path: saver.path().to_path_buf(),
            action: "gather the radiosity of every rank for",
            source: std::io::Error::other(e.to_string()),
        })?;
        let files: Vec<&Path> = canonical
            .iter()
            .chain(&older)
            .map(PathBuf::as_path)
            .collect();
        let result = canonical::save(saver, state, &files, self.plan);
        // In the checkpoint now: they would lie on rank 0's disk until the next one.
        for path in &files {
            let _ = std::fs::remove_file(path);
        }
        result
    }

    fn end(&mut self, omega: f64) -> Result<[f64; 4], OocError> {
        let t = Instant::now();
        if self.solver.groups > 1 {
            // The hybrid mode: every group brings its surfels to the canonical slices, sorted
            // by id, so that the update can add the groups' light surfel by surfel.
            let starts = &self.starts;
            let owner = |w: &Wire| starts[1..].partition_point(|&s| s <= held::id(w) as u64);
            self.generation += 1;
            let held = self.held.take().expect("held files between steps");
            let (next, _, _) = self.router.redistribute(
                held,
                self.generation,
                AxisKey::canonical(),
                false,
                Vec::new(),
                &owner,
                None,
                &mut |_| {},
                &mut self.io,
                &mut self.seconds,
            )?;
            self.held = Some(next);
            self.held_axis = None;
        }
        self.generation += 1;
        let fold = self.pending.then_some(!self.earlier_any);
        let held = self.take_held();
        if self.solver.closed.get() {
            self.scales = self.solver.closure_scales(
                &held,
                self.plan,
                self.cosine_sum,
                fold,
                &mut self.io,
            )?;
        }
        let (next, result) = self.solver.update(
            held,
            self.generation,
            self.dir,
            self.plan,
            self.cosine_sum,
            (fold, self.backwards),
            (&self.scales, omega),
            &mut self.io,
        )?;
        self.held = Some(next);
        // Group 0 speaks for every surfel once.
        let mut sums = [result.change, result.total, result.falling, result.residual];
        if self.solver.group_index != 0 {
            sums.fill(0.0);
        }
        self.solver.comm.sum_in_place(&mut sums);
        self.last = result;
        self.seconds.reduce += t.elapsed().as_secs_f64();
        Ok(sums)
    }

    fn keeps_older(&self) -> bool {
        self.solver.options.accelerate
    }

    fn extrapolate(&mut self, factor: f64) -> Result<(), OocError> {
        let t = Instant::now();
        self.generation += 1;
        let held = self.take_held();
        let next = self.solver.extrapolate(
            held,
            self.generation,
            self.dir,
            self.plan,
            factor,
            &mut self.io,
        )?;
        self.held = Some(next);
        self.seconds.reduce += t.elapsed().as_secs_f64();
        Ok(())
    }
}

/// The runs of `walk` from step `from` on: by step, how many steps from there have lines of
/// one slope along `v` on one main axis (at most `MOST_TOGETHER`), gathered together at the
/// run's first step; 0 inside a run, and before `from`. Such directions put every surfel in
/// the same line column, so the same column cuts serve them all, and a rank that holds the
/// first one's lines holds theirs.
fn runs_of(walk: &[WalkStep], from: usize, directions: &DirectionSet) -> Vec<usize> {
    let slope = |s: &WalkStep| v_slope(directions.directions[s.direction].vector);
    let mut runs = vec![0; walk.len()];
    let mut k = from;
    while k < walk.len() {
        let (b, c) = slope(&walk[k]);
        let mut end = k + 1;
        while end < walk.len() && end - k < MOST_TOGETHER && walk[end].main == walk[k].main && {
            let (b2, c2) = slope(&walk[end]);
            b2 * c == b * c2
        } {
            end += 1;
        }
        runs[k] = end - k;
        k = end;
    }
    runs
}

/// Cuts the runs `runs` (as [`runs_of`] gives them) at every step `k` where `starts[k]`.
fn cut_at(runs: &mut [usize], starts: &[bool]) {
    let mut k = 0;
    while k < runs.len() {
        let len = runs[k];
        if len == 0 {
            k += 1;
            continue;
        }
        if let Some(cut) = (k + 1..k + len).find(|&s| starts[s]) {
            runs[k] = cut - k;
            runs[cut] = k + len - cut;
        }
        k += runs[k];
    }
}

/// Adds the light gathered by the axis just done to that of the earlier axes (`first`: there
/// were none; the sum starts with this axis), as `outcore::solver` folds its axes. The axis's
/// field is cleared: the next axis's first pass writes it without reading it, and a record
/// rewritten in between (at the re-sort of a change of axis) so takes no disk there (its
/// file's blocks of zeros are holes, `outcore::files::SeqWriter`).
fn fold_axis(w: &mut Wire, first: bool) {
    let mut sum = decode_light32(&w[GATHERED_AT..]);
    if !first {
        let before = decode_light32(&w[EARLIER_AT..]);
        for (t, b) in sum.iter_mut().flatten().zip(before.iter().flatten()) {
            *t += *b;
        }
    }
    encode_light32(&sum, &mut w[EARLIER_AT..]);
    w[GATHERED_AT..EARLIER_AT].fill(0);
}

/// Cuts columns into `ranks` contiguous ranges of about equal `load`: `ranks + 1` bounds, rank
/// `r` owning `cuts[r]..cuts[r + 1]`.
fn cut_columns(load: &[f64], ranks: usize) -> Vec<u64> {
    let total: f64 = load.iter().sum();
    let mut cuts = Vec::with_capacity(ranks + 1);
    cuts.push(0u64);
    let (mut j, mut before) = (0usize, 0.0f64);
    for r in 1..ranks {
        let target = total * r as f64 / ranks as f64;
        // Advance while taking the next column brings the prefix closer to the target.
        while j < load.len() && (before + load[j] - target).abs() <= (before - target).abs() {
            before += load[j];
            j += 1;
        }
        cuts.push(j as u64);
    }
    cuts.push(load.len() as u64);
    cuts
}

/// The largest rank's load over the mean (1 is perfect; 1 when there is nothing).
fn imbalance_of(load: &[f64], cuts: &[u64]) -> f64 {
    let ranks = cuts.len() - 1;
    let total: f64 = load.iter().sum();
    if total == 0.0 {
        return 1.0;
    }
    let largest = cuts
        .windows(2)
        .map(|c| load[c[0] as usize..c[1] as usize].iter().sum::<f64>())
        .fold(0.0, f64::max);
    largest / (total / ranks as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use held::WIRE_LEN;

    #[test]
    fn columns_are_cut_for_equal_load() {
        let load = [1.0, 1.0, 1.0, 1.0, 4.0, 0.0, 2.0, 2.0];
        let cuts = cut_columns(&load, 3);
        assert_eq!(cuts.len(), 4);
        assert_eq!((cuts[0], cuts[3]), (0, 8));
        assert!(cuts.windows(2).all(|c| c[0] <= c[1]));
        assert!(imbalance_of(&load, &cuts) <= 1.25, "{cuts:?}");
        assert_eq!(cut_columns(&load, 1), vec![0, 8]);
        assert_eq!(imbalance_of(&[0.0; 4], &[0, 2, 4]), 1.0);
    }

    #[test]
    fn runs_hold_directions_of_one_slope_on_one_axis_and_are_cut_where_others_start() {
        let directions = DirectionSet::cube(2);
        let walk: Vec<WalkStep> = crate::outcore::solver::walk_by_axis(&directions)
            .into_iter()
            .enumerate()
            .flat_map(|(main, axis)| {
                let n = axis.len();
                axis.into_iter()
                    .enumerate()
                    .map(move |(k, direction)| WalkStep {
                        main,
                        first: k == 0,
                        last: k + 1 == n,
                        direction,
                    })
            })
            .collect();
        let runs = runs_of(&walk, 0, &directions);
        let slope = |k: usize| {
            let (b, c) = v_slope(directions.directions[walk[k].direction].vector);
            (walk[k].main, b as f64 / c as f64)
        };
        // Every step in exactly one run; a run's steps share an axis and a slope, and the
        // next run's first step does not continue it.
        let mut k = 0;
        let mut count = 0;
        while k < walk.len() {
            let len = runs[k];
            assert!((1..=MOST_TOGETHER).contains(&len), "{runs:?}");
            assert!((k + 1..k + len).all(|s| runs[s] == 0 && slope(s) == slope(k)));
            let end = k + len;
            assert!(end == walk.len() || slope(end) != slope(k) || len == MOST_TOGETHER);
            count += 1;
            k = end;
        }
        assert!(count < walk.len(), "some run holds several directions");
        // From a resumed step on, runs start there; before it, none.
        let from = 5;
        let resumed = runs_of(&walk, from, &directions);
        assert!(resumed[..from].iter().all(|&len| len == 0) && resumed[from] > 0);
        // Cut where another group's runs start: no run then holds such a step after its first.
        let mut starts = vec![false; walk.len() + 1];
        for s in (0..walk.len()).step_by(3) {
            starts[s] = true;
        }
        let mut cut = runs.clone();
        cut_at(&mut cut, &starts);
        let mut k = 0;
        while k < walk.len() {
            assert!(cut[k] > 0 && (k + 1..k + cut[k]).all(|s| !starts[s] && cut[s] == 0));
            k += cut[k];
        }
        assert_eq!(cut.iter().sum::<usize>(), walk.len());
    }

    #[test]
    fn axes_fold_as_the_single_process_solver_folds_them() {
        let mut w = [0u8; WIRE_LEN];
        encode_light32(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], &mut w[GATHERED_AT..]);
        fold_axis(&mut w, true);
        assert_eq!(decode_light32(&w[EARLIER_AT..])[1], [4.0, 5.0, 6.0]);
        encode_light32(&[[0.5; 3], [0.25; 3]], &mut w[GATHERED_AT..]);
        fold_axis(&mut w, false);
        assert_eq!(
            decode_light32(&w[EARLIER_AT..]),
            [[1.5, 2.5, 3.5], [4.25, 5.25, 6.25]]
        );
        assert!(w[GATHERED_AT..EARLIER_AT].iter().all(|&b| b == 0));
    }
}

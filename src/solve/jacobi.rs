//! The in-memory solver: every surfel and its light in RAM, Jacobi sweeps over all line
//! directions on one process or with the directions dealt over the ranks (`InMemory`, a sweep
//! of the one iteration loop, `iterate`), and the energy balance of the last gather.
//!
//! One iteration gathers, for every surfel side, `H = sum over s of B_prev(partner) cos W(s) / pi`
//! over all directions (accumulated in f64, in direction order), then sets
//! `B = E + rho * H / S(n)` (see `normalize`). Radiosity is stored in f32 between iterations.
//! The stopping rule, stop signals and checkpoints are the loop's (`iterate`); here a
//! checkpoint inside an iteration holds each rank's sums by surfel id. A direction's first
//! gather writes its partner links down; where they fit the budget (`links`), later iterations
//! replay them instead of dispatching and searching again, to the same bits.

use super::dispatch::{dispatch, Lines, OrderedEntry};
use super::iterate::{iterate, Start, Sweep};
use super::kept_links::{Blocks, KeptLinks, BLOCK_STEPS};
use super::light_sum::LightSum;
use super::links::{gather_and_record, record_links};
use super::normalize::cosine_sums;
use super::propagate::{
    gather_lines, prop_surfels, DirectionInput, LineScratch, PropSurfel, Record,
};
use super::update::{Gathered, Radiosity};
use super::{Solution, SolveStats};
use crate::checkpoint::{CheckpointError, Interruption, Loaded, Saver, State};
use crate::comm::{Comm, SingleProcess};
use crate::geometry::directions::DirectionSet;
use crate::geometry::lines::LineFrame;
use crate::geometry::order;
use crate::voxel::SurfelSet;
use rayon::prelude::*;
use std::time::Instant;

/// How to solve.
#[derive(Clone, Debug)]
pub struct SolveOptions {
    /// Approximate number of line directions (the cube set closest to it is used).
    pub directions: usize,
    /// Largest number of iterations.
    pub max_iterations: usize,
    /// Stop when the estimated relative error left is below this; `None` runs `max_iterations`.
    pub tolerance: Option<f64>,
    /// Worker threads (0: all cores).
    pub threads: usize,
    /// Solve one channel and copy it to the other two. Honoured only when the scene is grey
    /// (`effects::is_grey`); a coloured scene is always solved in three channels.
    pub grey: bool,
    /// Extrapolate the geometric tail of the iterations (see `accelerate`).
    pub accelerate: bool,
    /// With `accelerate`: run the Chebyshev semi-iteration where the tail extrapolation finds
    /// no geometric tail (see `accelerate`); every solve path keeps what it needs.
    pub chebyshev: bool,
    /// Gather the emitters' own light once with a dense direction set (see `direct`).
    pub direct: super::direct::DirectPass,
    /// Bytes of partner links that may be kept between iterations (see `links`); a direction
    /// whose links do not fit is searched again in every iteration. `None`: 4 GiB, at most a
    /// quarter of the memory available once the solver's arrays are made.
    pub links_memory: Option<u64>,
    /// Out of core: bytes of disk the partner links may take in work files (see
    /// `outcore::links`); a direction whose links do not fit is searched again in every
    /// iteration. `None`: half of what is free once the work files are made.
    pub links_disk: Option<u64>,
}

/// The default of [`SolveOptions::links_memory`]: 4 GiB (the Cornell box at resolution 256 with
/// 589 directions keeps 3.1 GB).
pub const DEFAULT_LINKS_MEMORY: u64 = 4 << 30;

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            directions: 1000,
            max_iterations: 1000,
            tolerance: Some(1e-4),
            threads: 0,
            grey: false,
            accelerate: false,
            chebyshev: false,
            direct: super::direct::DirectPass::Off,
            links_memory: None,
            links_disk: None,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SolveError {
    #[error("could not start {threads} worker threads: {message}")]
    Threads { threads: usize, message: String },
    #[error("{ranks} ranks cannot form {groups} equal groups: give a --groups that divides the rank count")]
    Groups { groups: usize, ranks: usize },
    #[error("{0}")]
    Interrupted(Interruption),
}

impl From<Interruption> for SolveError {
    fn from(i: Interruption) -> Self {
        SolveError::Interrupted(i)
    }
}

/// The checkpoints of one solve: where they go, and the one it starts from.
pub struct Checkpoints<'a> {
    pub saver: &'a mut Saver,
    /// Checked against the run already (`checkpoint::load_shared`).
    pub resume: Option<Loaded>,
}

/// Solves the radiosity of `set` with the cube direction set closest to `options.directions`.
pub fn solve(set: &SurfelSet, options: &SolveOptions) -> Result<Solution, SolveError> {
    let directions = DirectionSet::with_count(options.directions);
    solve_with(set, &directions, options)
}

/// Solves with an explicit direction set.
pub fn solve_with(
    set: &SurfelSet,
    directions: &DirectionSet,
    options: &SolveOptions,
) -> Result<Solution, SolveError> {
    solve_distributed(set, directions, options, &SingleProcess)
}

/// Solves on the processes of `comm`, directions dealt out to ranks (`distribute`); every rank
/// returns the same radiosity. The iteration loop and every call on `comm` run on the calling
/// thread (MPI wants its calls from the main thread); the worker threads only run the
/// directions' dispatch and propagation.
pub fn solve_distributed(
    set: &SurfelSet,
    directions: &DirectionSet,
    options: &SolveOptions,
    comm: &dyn Comm,
) -> Result<Solution, SolveError> {
    run_in_pool(set, directions, options, comm, None)
}

/// As [`solve_distributed`], saving checkpoints at iteration boundaries and starting from
/// `checkpoints.resume` if given; stops between directions on SIGTERM or SIGINT (once
/// `crate::interrupt::install` was called) with [`SolveError::Interrupted`].
pub fn solve_checkpointed(
    set: &SurfelSet,
    directions: &DirectionSet,
    options: &SolveOptions,
    comm: &dyn Comm,
    checkpoints: Checkpoints,
) -> Result<Solution, SolveError> {
    run_in_pool(set, directions, options, comm, Some(checkpoints))
}

fn run_in_pool(
    set: &SurfelSet,
    directions: &DirectionSet,
    options: &SolveOptions,
    comm: &dyn Comm,
    checkpoints: Option<Checkpoints>,
) -> Result<Solution, SolveError> {
    let (threads, pool) = worker_pool(options)?;
    run(set, directions, options, threads, &pool, comm, checkpoints)
}

/// The pool of `options.threads` workers (0: one per core) the directions run on.
pub(crate) fn worker_pool(
    options: &SolveOptions,
) -> Result<(usize, rayon::ThreadPool), SolveError> {
    let threads = if options.threads == 0 {
        rayon::current_num_threads()
    } else {
        options.threads
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| SolveError::Threads {
            threads,
            message: e.to_string(),
        })?;
    Ok((threads, pool))
}

/// Emission `E` (f32, as radiosity is stored) and reflectance of every surfel, by side.
pub(crate) type MaterialTables = (Vec<[[f32; 3]; 2]>, Vec<[[f64; 3]; 2]>);

/// The [`MaterialTables`] of `set`.
pub(crate) fn material_tables(set: &SurfelSet) -> MaterialTables {
    let emission = set
        .surfels
        .iter()
        .map(|s| {
            s.material
                .map(|m| set.materials[m as usize].emission.map(|e| e as f32))
        })
        .collect();
    let reflectance = set
        .surfels
        .iter()
        .map(|s| s.material.map(|m| set.materials[m as usize].reflectance))
        .collect();
    (emission, reflectance)
}

fn run(
    set: &SurfelSet,
    directions: &DirectionSet,
    options: &SolveOptions,
    threads: usize,
    pool: &rayon::ThreadPool,
    comm: &dyn Comm,
    mut checkpoints: Option<Checkpoints>,
) -> Result<Solution, SolveError> {
    let n = set.surfels.len();
    let started = Instant::now();
    let cosine_sum = pool.install(|| cosine_sums(&set.normals, directions));
    let normalize_seconds = started.elapsed().as_secs_f64();

    let surfels = prop_surfels(set);
    let (emission, reflectance) = material_tables(set);
    // The direct light, once (see `direct`); the iterations then gather only `B - E`.
    let direct = options
        .direct
        .directions_for(set, directions.len())
        .map(|dense| {
            super::direct::gather_direct(
                set,
                &surfels,
                &emission,
                &dense,
                super::direct::SenderBalance::PerDirection,
                comm,
                pool,
            )
        });
    let channels = if options.grey && super::effects::is_grey(set) {
        1
    } else {
        3
    };
    let verdict = super::enclosure::Enclosure::verdict_of_set(set);
    let mut stats = SolveStats {
        channels,
        directions: directions.len(),
        threads,
        normalize_seconds,
        ..Default::default()
    };
    let any_light = emission
        .iter()
        .any(|e| e.iter().flatten().any(|&v| v > 0.0));
    // This rank's directions (all of them on one process).
    let mine = crate::comm::dealt(directions.len(), comm.rank(), comm.size());
    let count = mine.len();
    let mut sweep = InMemory {
        set,
        directions,
        threads,
        pool,
        comm,
        mine,
        frames: directions
            .directions
            .iter()
            .map(|d| LineFrame::new(d.vector, set.grid.dims))
            .collect(),
        // The four lexicographic orders, sorted once.
        orders: pool.install(|| super::dispatch::lexicographic_orders(set)),
        surfels,
        radiosity: emission.clone(),
        emission,
        reflectance,
        cosine_sum,
        direct,
        channels,
        accelerate: options.accelerate,
        acc: vec![[[0f64; 3]; 2]; n],
        reflected: Vec::new(),
        previous: if options.accelerate {
            vec![[[0f32; 3]; 2]; n]
        } else {
            Vec::new()
        },
        lines: Lines::default(),
        seconds: [0.0; 3],
        links: KeptLinks::new(
            count,
            super::links::rank_budget(options.links_memory, n, comm),
        ),
        closed: verdict.closed,
        scales: super::closed::Scales::ONE,
    };
    let mut start = Start::fresh();
    if let Some(mut loaded) = checkpoints.as_mut().and_then(|c| c.resume.take()) {
        // A mid-iteration checkpoint resumed from: the steps done and this rank's sums.
        let within = loaded.take_within(0, comm.size());
        // The boundary the checkpoint holds, exactly as the interrupted run had it.
        assert_eq!(
            loaded.radiosity.len(),
            n,
            "a checkpoint is checked against the scene"
        );
        sweep.radiosity = std::mem::take(&mut loaded.radiosity);
        if let Some(older) = loaded.older.take() {
            // The Chebyshev semi-iteration's next update mixes with it.
            assert_eq!(older.len(), n, "a checkpoint is checked against the scene");
            sweep.previous = older;
        }
        if loaded.state.ranks as usize != comm.size() {
            // Valid, but the sums across ranks are grouped differently from here on.
            tracing::info!(
                "the checkpoint was written by {} rank(s), this solve has {}: the result may \
                 differ from an uninterrupted run in the last bits",
                loaded.state.ranks,
                comm.size()
            );
        }
        let done = match within {
            Some((done, sums)) => {
                assert_eq!(sums.len(), n, "a checkpoint is checked against the scene");
                tracing::info!(
                    iteration = loaded.state.iteration + 1,
                    within = done,
                    "continuing inside an iteration from the checkpoint's partial sums"
                );
                sweep.acc = sums;
                done as usize
            }
            None => 0,
        };
        start = Start::resumed(&loaded.state, &loaded.path, done, &mut stats);
    }
    let saver = checkpoints.map(|c| c.saver);
    iterate(
        &mut sweep, options, comm, saver, start, any_light, &mut stats,
    )?;
    [
        stats.dispatch_seconds,
        stats.propagate_seconds,
        stats.reduce_seconds,
    ] = sweep.seconds;
    // Over every rank (the directions mode deals the directions): each keeps its own.
    let (kept, bytes) = sweep.links.held();
    let mut sums = [kept as f64, count as f64, bytes as f64];
    comm.sum_in_place(&mut sums);
    let [kept_directions, directions, bytes] = sums.map(|v| v as usize);
    stats.links = Some(super::stats::LinkStats {
        kept_directions,
        directions,
        bytes: bytes as u64,
        bytes_per_surfel_direction: bytes as f64 / (n * kept_directions).max(1) as f64,
        kept_in: if kept_directions > 0 {
            "memory"
        } else {
            "none"
        }
        .to_string(),
    });
    let InMemory {
        mut radiosity,
        mut acc,
        cosine_sum,
        direct,
        scales,
        ..
    } = sweep;
    stats.closure = Some(super::stats::ClosureStats { verdict, scales });
    if channels == 1 {
        for (b, a) in radiosity.iter_mut().zip(acc.iter_mut()) {
            for side in 0..2 {
                b[side] = [b[side][0]; 3];
                a[side] = [a[side][0]; 3];
            }
        }
    }
    if comm.size() > 1 {
        // Each rank fills its own slot; the sum hands every rank the whole table.
        let mut table = vec![0.0; 3 * comm.size()];
        table[3 * comm.rank()..3 * comm.rank() + 3].copy_from_slice(&[
            stats.dispatch_seconds,
            stats.propagate_seconds,
            stats.reduce_seconds,
        ]);
        comm.sum_in_place(&mut table);
        stats.per_rank_seconds = table.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
    }
    energy(set, &acc, &cosine_sum, direct.as_ref(), &scales, &mut stats);
    if let Some(d) = direct {
        stats.direct = Some(d.stats);
    }
    Ok(Solution { radiosity, stats })
}

/// The in-memory store (every surfel and its light in RAM, by id) with one process or the
/// directions dealt over the ranks: a step is one direction per rank, and the end of an
/// iteration sums the ranks' light before every rank updates every surfel.
struct InMemory<'a> {
    set: &'a SurfelSet,
    directions: &'a DirectionSet,
    threads: usize,
    pool: &'a rayon::ThreadPool,
    comm: &'a dyn Comm,
    mine: Vec<usize>,
    frames: Vec<LineFrame>,
    orders: Vec<Vec<OrderedEntry>>,
    surfels: Vec<PropSurfel>,
    emission: Vec<Radiosity>,
    reflectance: Vec<Gathered>,
    cosine_sum: Vec<f64>,
    direct: Option<super::direct::DirectLight>,
    channels: usize,
    accelerate: bool,
    radiosity: Vec<Radiosity>,
    /// The light gathered this iteration, by surfel.
    acc: Vec<Gathered>,
    /// What the lines carry with the direct pass: `B - E`.
    reflected: Vec<Radiosity>,
    /// The radiosity the last update replaced (for the tail extrapolation, and the value before
    /// last for the Chebyshev semi-iteration); kept whenever `accelerate` is.
    previous: Vec<Radiosity>,
    lines: Lines,
    /// Dispatch, propagation and reduction seconds.
    seconds: [f64; 3],
    /// This rank's directions' links, once their first gather kept them.
    links: KeptLinks,
    /// The scene's light is sealed in: each update scales the light by `scales` (`closed`).
    closed: bool,
    scales: super::closed::Scales,
}

/// What the lines carry, by surfel (`update::carried` for one): `B - E` where the direct pass
/// gathered the emitters' light, else `B`.
fn carried_light<'a>(
    direct: &Option<super::direct::DirectLight>,
    reflected: &'a [Radiosity],
    radiosity: &'a [Radiosity],
) -> &'a [Radiosity] {
    if direct.is_some() {
        reflected
    } else {
        radiosity
    }
}

impl InMemory<'_> {
    /// Gathers this rank's direction `k` at step `step`: a replay of its kept links, or a
    /// search that writes them down (only that, where the run is left to one replay).
    fn gather_step(&mut self, step: usize, k: usize) {
        let (d, frame) = (&self.directions.directions[k], &self.frames[k]);
        let (orders, lines, acc, threads) =
            (&self.orders, &mut self.lines, &mut self.acc, self.threads);
        let input = DirectionInput {
            unit: d.unit,
            weight: d.solid_angle / std::f64::consts::PI,
            surfels: &self.surfels,
            radiosity: carried_light(&self.direct, &self.reflected, &self.radiosity),
            channels: self.channels,
        };
        let t0 = Instant::now();
        let kept = &mut self.links;
        // The first gather of a direction writes its links down while they may still be kept;
        // in a run of directions that can be replayed as one block, it only writes them down.
        // Any other step first gathers the steps waiting for such a replay: each side's terms
        // are added in step order.
        let defer = kept.defers(step);
        if !defer {
            self.pool
                .install(|| kept.settle(input.radiosity, input.channels, acc));
        }
        if self
            .pool
            .install(|| kept.replay(step, input.radiosity, input.channels, acc))
        {
            // Visibility known: a streaming gather.
            self.seconds[1] += t0.elapsed().as_secs_f64();
            return;
        }
        let record = kept.should_record(step);
        let t1 = self.pool.install(|| {
            dispatch(&orders[order::order_of(d.vector)], frame, threads, lines);
            let t1 = Instant::now();
            if defer {
                let links = record_links(lines, &input, threads, kept.spare_words());
                kept.keep_deferred(step, links, input.radiosity, input.channels, acc);
            } else if record {
                kept.keep(step, gather_and_record(lines, &input, acc, threads));
            } else {
                gather_all_lines(lines, &input, acc, threads);
            }
            t1
        });
        self.seconds[0] += (t1 - t0).as_secs_f64();
        self.seconds[1] += t1.elapsed().as_secs_f64();
    }

    /// The end of run `b` (`kept_links::KeptLinks::finish_run`): its steps waiting are
    /// replayed as one block where every rank can make it, else apart.
    fn finish_run(&mut self, b: usize) {
        let Some(fuse) = self.links.agree_on_run(b, self.acc.len(), self.comm) else {
            return;
        };
        let t = Instant::now();
        let input = carried_light(&self.direct, &self.reflected, &self.radiosity);
        let (kept, acc) = (&mut self.links, &mut self.acc);
        self.pool
            .install(|| kept.finish_run(b, fuse, input, self.channels, acc));
        self.seconds[1] += t.elapsed().as_secs_f64();
    }
}

impl Sweep for InMemory<'_> {
    type Error = SolveError;

    fn steps(&self) -> usize {
        // One direction per rank each, the same count on every rank (a rank dealt one
        // direction fewer idles in the last step).
        self.directions.len().div_ceil(self.comm.size())
    }

    fn updates(&self) -> u64 {
        (self.set.surfels.len() * self.directions.len()) as u64
    }

    fn begin(&mut self, _iteration: usize, from: usize) -> Result<(), SolveError> {
        if from == 0 {
            self.acc.iter_mut().for_each(|a| *a = [[0.0; 3]; 2]);
        }
        // On several ranks, blocks of links only where every rank kept every direction's:
        // then the steps at which the light can be saved are the same on every rank
        // (`kept_links`).
        let blocks = if self.comm.size() == 1 {
            Blocks::WhereWhole
        } else if self.comm.max_u64(u64::from(!self.links.all_kept())) == 0 {
            Blocks::Uniform
        } else {
            Blocks::Off
        };
        self.links.begin_iteration(blocks);
        if let Some(d) = &self.direct {
            d.reflected(&self.radiosity, &self.emission, &mut self.reflected);
        }
        Ok(())
    }

    fn step(&mut self, step: usize) -> Result<bool, SolveError> {
        if let Some(&k) = self.mine.get(step) {
            self.gather_step(step, k);
        }
        // Every rank ends a run at the same steps (a rank dealt fewer steps too).
        if (step + 1) % BLOCK_STEPS == 0 || step + 1 == self.steps() {
            self.finish_run(step / BLOCK_STEPS);
        }
        Ok(true)
    }

    fn settle(&mut self) {
        let input = carried_light(&self.direct, &self.reflected, &self.radiosity);
        let (kept, acc) = (&mut self.links, &mut self.acc);
        self.pool.install(|| kept.settle(input, self.channels, acc));
    }

    fn can_save_within(&self, done: usize) -> bool {
        self.links.can_save_within(done)
    }

    fn save_within(
        &mut self,
        saver: &mut Saver,
        state: State,
        done: usize,
    ) -> Result<(), CheckpointError> {
        let arrays = (&self.radiosity[..], Some(&self.previous[..]));
        saver.save_within(self.comm, state, done as u64, arrays, &self.acc)
    }

    fn save_boundary(&mut self, saver: &mut Saver, state: State) -> Result<(), CheckpointError> {
        saver.save_memory(state, &self.radiosity, Some(&self.previous))
    }

    fn keeps_older(&self) -> bool {
        self.accelerate
    }

    fn end(&mut self, omega: f64) -> Result<[f64; 4], SolveError> {
        // Every run of deferred steps ends within the iteration; nothing is left for later.
        self.settle();
        if self.comm.size() > 1 {
            let t = Instant::now();
            let mut flat: Vec<f64> = self.acc.iter().flatten().flatten().copied().collect();
            self.comm.sum_in_place(&mut flat);
            for (a, v) in self.acc.iter_mut().flatten().flatten().zip(&flat) {
                *a = *v;
            }
            self.seconds[2] += t.elapsed().as_secs_f64();
        }
        if self.closed {
            let mut sums = super::closed::ClosureSums::new(&self.set.materials);
            for (k, s) in self.set.surfels.iter().enumerate() {
                sums.add(
                    &self.emission[k],
                    &super::update::carried(
                        &self.radiosity[k],
                        &self.emission[k],
                        self.direct.is_some(),
                    ),
                    &self.acc[k],
                    super::update::direct_of(self.direct.as_ref(), k),
                    self.channels,
                    self.cosine_sum[s.normal_id as usize],
                    s.area as f64,
                );
            }
            self.scales = sums.scales(self.channels);
        }
        // B = E + rho H / S, and the change it makes; the value it replaces is kept.
        let chebyshev = omega != 1.0;
        debug_assert!(!chebyshev || self.accelerate);
        let mut sums = super::update::UpdateSums::default();
        for (k, s) in self.set.surfels.iter().enumerate() {
            let current = self.radiosity[k];
            let older = chebyshev.then(|| (&self.previous[k], omega));
            let updated = super::update::update_surfel(
                &self.emission[k],
                &self.reflectance[k],
                self.acc[k],
                super::update::direct_of(self.direct.as_ref(), k),
                self.channels,
                &current,
                older,
                self.cosine_sum[s.normal_id as usize],
                s.area as f64,
                &self.scales,
                &mut sums,
            );
            self.radiosity[k] = updated;
            if self.accelerate {
                self.previous[k] = current;
            }
        }
        Ok([sums.change, sums.total, sums.falling, sums.residual])
    }

    fn extrapolate(&mut self, factor: f64) -> Result<(), SolveError> {
        super::accelerate::extrapolate(&mut self.radiosity, &self.previous, &self.emission, factor);
        Ok(())
    }
}

/// Runs `gather_line` over all lines, spread over `threads` in contiguous line ranges of about
/// equal surfel counts.
pub(crate) fn gather_all_lines<A: LightSum>(
    lines: &Lines,
    input: &DirectionInput,
    acc: &mut [A],
    threads: usize,
) {
    gather_pieces::<(), A, true>(lines, input, acc, threads);
}

/// Gathers direction `input` along `lines` into `acc` in [`line_pieces`] spread over the
/// threads; returns what each piece's `R` recorded, in piece order. Without `ADD`, only
/// records (`acc` is not touched and may be empty).
pub(crate) fn gather_pieces<R: Record + Default + Send, A: LightSum, const ADD: bool>(
    lines: &Lines,
    input: &DirectionInput,
    acc: &mut [A],
    threads: usize,
) -> Vec<R> {
    let bounds = line_pieces(lines, threads);
    let acc_ptr = AccPtr(acc.as_mut_ptr());
    bounds
        .par_windows(2)
        .map(|w| {
            let mut scratch = LineScratch::default();
            let mut record = R::default();
            record.expect((lines.starts[w[1]] - lines.starts[w[0]]) as usize);
            // SAFETY: with `ADD`, `acc` has one entry per surfel; each surfel lies on exactly
            // one line of this direction and line ranges are disjoint, so no entry is touched
            // by two threads. Without, `acc` is not touched.
            let range = w[0]..w[1];
            unsafe {
                gather_lines::<R, A, ADD>(
                    lines,
                    range,
                    input,
                    &mut scratch,
                    acc_ptr.get(),
                    &mut record,
                )
            };
            record
        })
        .collect()
}

/// The lines of a direction cut into about `8 threads` pieces of about equal surfels, as
/// bounds: piece `p` is lines `bounds[p]..bounds[p + 1]`.
pub(crate) fn line_pieces(lines: &Lines, threads: usize) -> Vec<usize> {
    let line_count = lines.line_count();
    let total = lines.members.len();
    let pieces = (threads * 8).max(1);
    let mut bounds = vec![0usize];
    for p in 1..pieces {
        let target = (total * p / pieces) as u32;
        let at = lines
            .starts
            .partition_point(|&s| s < target)
            .min(line_count);
        if at > *bounds.last().unwrap_or(&0) {
            bounds.push(at);
        }
    }
    bounds.push(line_count);
    bounds
}

#[derive(Clone, Copy)]
pub(crate) struct AccPtr<A>(pub(crate) *mut A);
// SAFETY: shared only for writes at disjoint indices (see `gather_pieces` and
// `links::DirectionLinks::replay`).
unsafe impl<A> Send for AccPtr<A> {}
unsafe impl<A> Sync for AccPtr<A> {}
impl<A> AccPtr<A> {
    pub(crate) fn get(self) -> *mut A {
        self.0
    }
}

/// Emitted and absorbed power (world units) from the final gather and the direct light, as
/// every loop adds it up (`update::add_power`).
fn energy(
    set: &SurfelSet,
    acc: &[[[f64; 3]; 2]],
    cosine_sum: &[f64],
    direct: Option<&super::direct::DirectLight>,
    scales: &super::closed::Scales,
    stats: &mut SolveStats,
) {
    let area_unit = set.grid.voxel_size * set.grid.voxel_size;
    let mut sums = super::update::UpdateSums::default();
    for (k, s) in set.surfels.iter().enumerate() {
        super::update::add_power(
            s.material.map(|m| &set.materials[m as usize]),
            acc[k],
            super::update::direct_of(direct, k),
            3,
            cosine_sum[s.normal_id as usize],
            s.area as f64,
            area_unit,
            scales,
            &mut sums,
        );
    }
    stats.emitted_power = sums.emitted;
    for ch in 0..3 {
        stats.absorbed_power[ch] = sums.absorbed[ch] + sums.absorbed_direct[ch];
    }
}

//! The iteration loop: Jacobi sweeps over all line directions, the stopping rule, energy.
//!
//! One iteration gathers, for every surfel side, `H = sum over s of B_prev(partner) cos W(s) / pi`
//! over all directions (accumulated in f64, in direction order), then sets
//! `B = E + rho * H / S(n)` (see `normalize`). Radiosity is stored in f32 between iterations.
//!
//! **Stopping.** The relative change of an iteration is `delta_k = sum A |B_k - B_{k-1}| / sum A B_k`
//! over sides and channels (A the surfel area). Jacobi converges geometrically, so the error left
//! after iteration k is about `delta_k * q / (1 - q)` with `q = delta_k / delta_{k-1}` the observed
//! contraction (about the scene's reflectance). That estimate is the reported `residual`, and the
//! solve stops when it is below the tolerance: so a scene with reflectance 0.999 runs long enough,
//! where a bare `delta_k < tolerance` would stop about `rho / (1 - rho)` times too early.
//!
//! **Checkpoints and signals** ([`solve_checkpointed`]): at iteration boundaries the radiosity
//! and the bookkeeping above are saved (see `crate::checkpoint`), and a solve can start from
//! them; between directions the loop asks whether SIGTERM or SIGINT came (`crate::interrupt`).
//! With mid-iteration checkpoints on (`Saver::within`), the ranks agree between every two
//! directions (one `max_u64`) on stopping and on saving, and a stop keeps the directions already
//! gathered; without, they agree once per iteration before they sum and a stop abandons the
//! iteration in progress. Either way none waits for a rank that has stopped.

use super::dispatch::{dispatch, Lines, OrderedEntry};
use super::normalize::cosine_sums;
use super::propagate::{gather_line, prop_surfels, DirectionInput, LineScratch};
use super::{Solution, SolveStats};
use crate::checkpoint::{Interruption, Loaded, Saver};
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
    /// Gather the emitters' own light once with a dense direction set (see `direct`).
    pub direct: super::direct::DirectPass,
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            directions: 1000,
            max_iterations: 1000,
            tolerance: Some(1e-4),
            threads: 0,
            grey: false,
            accelerate: false,
            direct: super::direct::DirectPass::Off,
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
    // The four lexicographic orders, sorted once.
    let orders: Vec<Vec<OrderedEntry>> =
        pool.install(|| super::dispatch::lexicographic_orders(set));
    // This rank's directions (all of them on one process).
    let mine = crate::comm::dealt(directions.len(), comm.rank(), comm.size());
    let frames: Vec<LineFrame> = directions
        .directions
        .iter()
        .map(|d| LineFrame::new(d.vector, set.grid.dims))
        .collect();

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
    let mut reflected = Vec::new();

    let channels = if options.grey && super::effects::is_grey(set) {
        1
    } else {
        3
    };
    let mut extrapolation = super::accelerate::Extrapolation::default();
    let mut previous = Vec::new();
    let mut stats = SolveStats {
        channels,
        directions: directions.len(),
        threads,
        normalize_seconds,
        ..Default::default()
    };
    let mut radiosity = emission.clone();
    let mut acc = vec![[[0f64; 3]; 2]; n];
    let mut lines = Lines::default();
    let any_light = emission
        .iter()
        .any(|e| e.iter().flatten().any(|&v| v > 0.0));
    // One bar per iteration over its directions: on a large scene a single iteration is long.
    let progress = crate::progress::bar(mine.len() as u64, "iteration 1");
    let mut convergence = Convergence::new();
    let mut first = 1;
    // Steps of an iteration: one direction per rank each, the same count on every rank (a rank
    // dealt one direction fewer idles in the last step), so that the ranks can agree between
    // two steps on stopping or saving.
    let steps = directions.len().div_ceil(comm.size());
    let within = checkpoints.as_ref().is_some_and(|c| c.saver.saves_within());
    // A mid-iteration checkpoint resumed from: the steps done and this rank's sums.
    let mut resume_within = None;
    if let Some(mut loaded) = checkpoints.as_mut().and_then(|c| c.resume.take()) {
        resume_within = loaded.take_within(0, comm.size());
        if let Some((done, _)) = &resume_within {
            tracing::info!(
                iteration = loaded.state.iteration + 1,
                within = done,
                "continuing inside an iteration from the checkpoint's partial sums"
            );
        }
        // The boundary the checkpoint holds, exactly as the interrupted run had it.
        radiosity = loaded.radiosity;
        assert_eq!(
            radiosity.len(),
            n,
            "a checkpoint is checked against the scene"
        );
        if loaded.state.ranks as usize != comm.size() {
            // Valid, but the sums across ranks are grouped differently from here on.
            tracing::info!(
                "the checkpoint was written by {} rank(s), this solve has {}: the result may \
                 differ from an uninterrupted run in the last bits",
                loaded.state.ranks,
                comm.size()
            );
        }
        first = convergence.resume(&loaded.state, &loaded.path, &mut stats);
        extrapolation = loaded.state.extrapolation.into();
    }

    if checkpoints.is_some() {
        crate::interrupt::start_iterating();
    }
    for iteration in first..=options.max_iterations {
        if !any_light {
            stats.converged = true;
            break;
        }
        let start = match resume_within.take() {
            Some((done, sums)) => {
                assert_eq!(sums.len(), n, "a checkpoint is checked against the scene");
                acc = sums;
                done as usize
            }
            None => {
                acc.iter_mut().for_each(|a| *a = [[0.0; 3]; 2]);
                0
            }
        };
        if let Some(d) = &direct {
            d.reflected(&radiosity, &emission, &mut reflected);
        }
        progress.reset();
        progress.set_position(start as u64);
        progress.set_message(format!("iteration {iteration}"));
        let mut signal = 0;
        let mut stopped_at = 0;
        for step in start..steps {
            if let Some(c) = checkpoints.as_mut().filter(|_| within) {
                // Between two steps every rank agrees on stopping and on saving.
                let asked = crate::interrupt::requested().unwrap_or(0);
                let (agreed, save) = c.saver.agree_within(comm, asked);
                if agreed != 0 {
                    (signal, stopped_at) = (agreed, step);
                    break;
                }
                // Not at the iteration's start (its boundary was saved, or is the one resumed
                // from) nor where this run resumed.
                if save && step > start {
                    let state =
                        c.saver
                            .state(iteration - 1, convergence.previous_change, &extrapolation);
                    let result = c
                        .saver
                        .save_within(comm, state, step as u64, &radiosity, &acc);
                    c.saver.warn_on_failure(result);
                }
            } else if let Some(s) = crate::interrupt::requested() {
                // Abandon the iteration; `radiosity` still holds the last completed one.
                signal = s;
                break;
            }
            let Some(&k) = mine.get(step) else {
                continue;
            };
            let (d, frame) = (&directions.directions[k], &frames[k]);
            let t0 = Instant::now();
            let t1 = pool.install(|| {
                dispatch(
                    &orders[order::order_of(d.vector)],
                    frame,
                    threads,
                    &mut lines,
                );
                let t1 = Instant::now();
                let input = DirectionInput {
                    unit: d.unit,
                    weight: d.solid_angle / std::f64::consts::PI,
                    surfels: &surfels,
                    radiosity: if direct.is_some() {
                        &reflected
                    } else {
                        &radiosity
                    },
                    channels,
                };
                gather_all_lines(&lines, &input, &mut acc, threads);
                t1
            });
            stats.dispatch_seconds += (t1 - t0).as_secs_f64();
            stats.propagate_seconds += t1.elapsed().as_secs_f64();
            progress.inc(1);
        }
        // Every rank takes part, signalled or not, before anyone sums: all stop or none. (With
        // mid-iteration checkpoints they agreed between the steps already.)
        if !within {
            signal = comm.max_u64(signal as u64) as i32;
        }
        if signal != 0 {
            progress.finish_and_clear();
            let completed = iteration - 1;
            let interruption = match checkpoints.as_mut() {
                Some(c) if stopped_at > 0 => {
                    let done = stopped_at as u64;
                    c.saver
                        .interrupt_at(signal, completed, Some(done), |saver| {
                            let state =
                                saver.state(completed, convergence.previous_change, &extrapolation);
                            saver.save_within(comm, state, done, &radiosity, &acc)
                        })
                }
                Some(c) => c.saver.interrupt(signal, completed, |saver| {
                    let state = saver.state(completed, convergence.previous_change, &extrapolation);
                    saver.save_memory(state, &radiosity)
                }),
                None => Interruption::without_checkpoint(signal, completed, comm.rank() == 0),
            };
            return Err(SolveError::Interrupted(interruption));
        }
        if comm.size() > 1 {
            let t = Instant::now();
            let mut flat: Vec<f64> = acc.iter().flatten().flatten().copied().collect();
            comm.sum_in_place(&mut flat);
            for (a, v) in acc.iter_mut().flatten().flatten().zip(&flat) {
                *a = *v;
            }
            stats.reduce_seconds += t.elapsed().as_secs_f64();
        }
        stats.updates += (n * directions.len()) as u64;

        // B = E + rho H / S, and the change it makes.
        if options.accelerate {
            previous.clone_from(&radiosity);
        }
        let mut sums = super::update::UpdateSums::default();
        for k in 0..n {
            let s = &set.surfels[k];
            radiosity[k] = super::update::update_surfel(
                &emission[k],
                &reflectance[k],
                acc[k],
                super::update::direct_of(direct.as_ref(), k),
                channels,
                &radiosity[k],
                cosine_sum[s.normal_id as usize],
                s.area as f64,
                &mut sums,
            );
        }
        let (change, total, falling) = (sums.change, sums.total, sums.falling);
        // Right after an extrapolation the change history starts again: until it contracts, the
        // contraction measured before the jump estimates the error (see `accelerate`).
        let stop = convergence.record(iteration, change, total, options, &mut stats, |relative| {
            extrapolation.error_estimate(relative)
        });
        let relative = stats.last_change;
        if stop {
            break;
        }
        if options.accelerate {
            if let Some(factor) = extrapolation.observe(change, relative, falling) {
                super::accelerate::extrapolate(&mut radiosity, &previous, &emission, factor);
                // The jump is not an iteration's change: the stopping rule starts again.
                convergence.restart();
            }
        }
        // A boundary the solve goes on from (never the last: a resumed solve must gather at
        // least once, for its energy balance).
        if iteration < options.max_iterations {
            if let Some(c) = checkpoints.as_mut() {
                c.saver.save_if_due(
                    |saver| saver.state(iteration, convergence.previous_change, &extrapolation),
                    |saver, state| saver.save_memory(state, &radiosity),
                );
            }
        }
    }
    stats.extrapolations = extrapolation.count;
    if channels == 1 {
        for (b, a) in radiosity.iter_mut().zip(acc.iter_mut()) {
            for side in 0..2 {
                b[side] = [b[side][0]; 3];
                a[side] = [a[side][0]; 3];
            }
        }
    }
    progress.finish_and_clear();
    if options.tolerance.is_none() {
        // A fixed count of iterations: report whether it reached the default tolerance.
        stats.converged = stats.residual <= SolveOptions::default().tolerance.unwrap_or(0.0);
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
    energy(set, &acc, &cosine_sum, direct.as_ref(), &mut stats);
    if let Some(d) = direct {
        stats.direct = Some(d.stats);
    }
    Ok(Solution { radiosity, stats })
}

/// The stopping rule's bookkeeping, shared by the in-memory and the out-of-core loops.
pub(crate) struct Convergence {
    /// The last relative change (kept in checkpoints).
    pub(crate) previous_change: Option<f64>,
    started: Instant,
}

impl Convergence {
    pub(crate) fn new() -> Self {
        Convergence {
            previous_change: None,
            started: Instant::now(),
        }
    }

    /// Records iteration `iteration`, whose area-weighted change and total of `B` are `change`
    /// and `total`, in `stats`; logs it; tells whether the solve should stop. `fallback` gives
    /// an estimate from the relative change while the history cannot (after a restart).
    pub(crate) fn record(
        &mut self,
        iteration: usize,
        change: f64,
        total: f64,
        options: &SolveOptions,
        stats: &mut SolveStats,
        fallback: impl FnOnce(f64) -> Option<f64>,
    ) -> bool {
        let relative = if total > 0.0 { change / total } else { 0.0 };
        let estimate = match error_estimate(relative, self.previous_change) {
            e if e.is_finite() => e,
            e => fallback(relative).unwrap_or(e),
        };
        stats.iterations = iteration;
        stats.last_change = relative;
        stats.residual = estimate;
        tracing::info!(
            iteration,
            change = format!("{relative:.3e}"),
            estimated_error = format!("{estimate:.3e}"),
            seconds = format!("{:.1}", self.started.elapsed().as_secs_f64()),
            "iteration done"
        );
        let stalled = self
            .previous_change
            .is_some_and(|prev| relative > 0.0 && relative >= prev && relative < STALL_LEVEL);
        self.previous_change = Some(relative);
        let stop = options.tolerance.is_some_and(|tol| estimate <= tol);
        if stop {
            stats.converged = true;
        } else if stalled && options.tolerance.is_some() {
            // Iterating on cannot get closer: report it and stop, not converged.
            stats.stalled = true;
            tracing::warn!(
                iteration,
                change = format!("{relative:.3e}"),
                "the changes stopped shrinking at the rounding of the f32 radiosity: the \
                 tolerance is below what this scene can show (its reflectance is close to 1); \
                 stopping here"
            );
            return true;
        }
        stop
    }

    /// Continues from a checkpoint's `state` (read from `path`): takes its change history,
    /// records the iterations it holds in `stats`, logs it; returns the first iteration to run.
    pub(crate) fn resume(
        &mut self,
        state: &crate::checkpoint::State,
        path: &std::path::Path,
        stats: &mut SolveStats,
    ) -> usize {
        self.previous_change = state.previous_change;
        let done = state.iteration as usize;
        stats.iterations = done;
        stats.resumed_from_iteration = Some(done);
        tracing::info!(iteration = done, path = %path.display(), "resumed from a checkpoint");
        done + 1
    }

    /// Forgets the change history (after a jump that was not an iteration).
    pub(crate) fn restart(&mut self) {
        self.previous_change = None;
    }
}

/// A relative change below this that no longer shrinks is the rounding of the f32 radiosity
/// (two units in the last place): iterating on only shuffles the last bits. The error left then
/// is about that rounding times `rho / (1 - rho)` (6e-5 at `rho = 0.999`), which no tolerance
/// below it can reach.
const STALL_LEVEL: f64 = 2.0 * f32::EPSILON as f64;

/// The relative error left after an iteration whose relative change is `relative`, given the
/// previous iteration's change (see the module header); infinite until the changes contract.
fn error_estimate(relative: f64, previous_change: Option<f64>) -> f64 {
    match previous_change {
        _ if relative == 0.0 => 0.0,
        Some(prev) if prev > 0.0 && relative < prev => {
            let q = relative / prev;
            relative * q / (1.0 - q)
        }
        _ => f64::INFINITY,
    }
}

/// Runs `gather_line` over all lines, spread over `threads` in contiguous line ranges of about
/// equal surfel counts.
pub(crate) fn gather_all_lines(
    lines: &Lines,
    input: &DirectionInput,
    acc: &mut [[[f64; 3]; 2]],
    threads: usize,
) {
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
    let acc_ptr = AccPtr(acc.as_mut_ptr());
    bounds.par_windows(2).for_each(|w| {
        let mut scratch = LineScratch::default();
        for l in w[0]..w[1] {
            let line = lines.line(l);
            if line.len() < 2 {
                continue;
            }
            // SAFETY: `acc` has one entry per surfel; each surfel lies on exactly one line of this
            // direction and line ranges are disjoint, so no entry is touched by two threads.
            unsafe { gather_line(line, input, &mut scratch, acc_ptr.get()) };
        }
    });
}

#[derive(Clone, Copy)]
struct AccPtr(*mut [[f64; 3]; 2]);
// SAFETY: shared only for writes at disjoint indices (see `gather_all_lines`).
unsafe impl Send for AccPtr {}
unsafe impl Sync for AccPtr {}
impl AccPtr {
    fn get(self) -> *mut [[f64; 3]; 2] {
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
            &mut sums,
        );
    }
    stats.emitted_power = sums.emitted;
    for ch in 0..3 {
        stats.absorbed_power[ch] = sums.absorbed[ch] + sums.absorbed_direct[ch];
    }
}

//! The iteration loop, written once for every solve path: steps, stop signals and
//! checkpoints inside and between iterations, the update's stopping rule, the tail
//! extrapolation and the Chebyshev semi-iteration's weights (`accelerate`). What differs between the paths (where the surfels and their light live, and
//! how the work is dealt over processes) is a [`Sweep`]: the in-memory solver (one process or
//! directions over ranks, `jacobi`), the data and hybrid modes (`distribute::data`), the
//! out-of-core solver (`outcore::solver`) and the data and hybrid modes out of core
//! (`distribute::ooc`).
//!
//! **An iteration** is [`Sweep::steps`] steps, the same count on every rank (a rank with less
//! to do idles in its last steps), each gathering one direction (or one per rank or group) into
//! the light the sweep holds; then [`Sweep::end`] brings that light together and updates
//! `B = E + rho (H / S(n) + H_direct)` on every surfel (`update`), returning the stopping rule's
//! sums added over the world.
//!
//! **Stopping.** The relative change of an iteration is `delta_k = sum A |B_k - B_{k-1}| / sum A
//! B_k` over sides and channels (A the surfel area). Jacobi converges geometrically, so the
//! error left after iteration k is about `delta_k * q / (1 - q)` with `q = delta_k /
//! delta_{k-1}` the observed contraction (about the scene's reflectance). That estimate is the
//! reported `residual`, and the solve stops when it is below the tolerance: so a scene with
//! reflectance 0.999 runs long enough, where a bare `delta_k < tolerance` would stop about `rho
//! / (1 - rho)` times too early.
//!
//! **Signals and checkpoints.** Before every step the ranks agree (one `max_u64`) on a stop
//! signal any of them received and on whether rank 0 finds a mid-iteration checkpoint due;
//! none waits for a rank that has stopped. A stop keeps the steps already gathered where the
//! sweep can save them ([`Sweep::can_save_within`]) and mid-iteration checkpoints are on, else
//! it saves the last completed iteration. A signal during the last step stops the solve at the
//! next boundary, with that iteration kept. A one-process sweep may stop inside a step (the
//! out-of-core solver between two bands of a long direction); the solve then stops where that
//! step began. At a boundary the solve goes on from, a checkpoint is written when rank 0's
//! clock says one is due.

use super::accelerate::Extrapolation;
use super::{SolveOptions, SolveStats};
use crate::checkpoint::{CheckpointError, Interruption, Saver, State};
use crate::comm::Comm;
use std::time::Instant;

/// One solve path's store and distribution, as the loop drives it. Every method that talks to
/// other ranks is called on every rank in the same order.
pub(crate) trait Sweep {
    type Error: From<Interruption>;

    /// Steps of one iteration, the same on every rank.
    fn steps(&self) -> usize;

    /// Surfel-direction updates of one iteration (the report's rate).
    fn updates(&self) -> u64;

    /// Starts iteration `iteration` (counted from 1) at step `from`: 0 clears the light
    /// gathered; more continues from the light a checkpoint put back. (The out-of-core sweeps
    /// walk their steps in an order that depends on the iteration, `outcore::solver::Walk`.)
    fn begin(&mut self, iteration: usize, from: usize) -> Result<(), Self::Error>;

    /// Gathers step `step`. `false`: it stopped part way on a stop signal (its light is not
    /// whole; the loop stops as if the signal had come before it). Only a one-process sweep
    /// may stop part way: the ranks of the others must agree on where they stop.
    fn step(&mut self, step: usize) -> Result<bool, Self::Error>;

    /// Whether a checkpoint can hold the state `done` steps into an iteration (0 < done). The
    /// same on every rank. Where it is false after [`Sweep::settle`], a stop signal with
    /// mid-iteration checkpoints on waits for the next step where it is true (or the
    /// iteration's end): the sweep answers so only where the steps until then do nothing
    /// (blocks of links replayed, `kept_links`).
    fn can_save_within(&self, done: usize) -> bool;

    /// Gathers the steps done whose light the sweep left for later (an in-memory sweep's first
    /// iteration writes the links of a run of steps down and replays them together at its end,
    /// `kept_links`), so that the light can be saved here: called where a checkpoint or a stop
    /// inside the iteration asks and [`Sweep::can_save_within`] is false.
    fn settle(&mut self) {}

    /// Saves the state `done` steps into iteration `state.iteration + 1` (collective).
    fn save_within(
        &mut self,
        saver: &mut Saver,
        state: State,
        done: usize,
    ) -> Result<(), CheckpointError>;

    /// Saves the radiosity of the last completed iteration, which the sweep still holds
    /// (collective; an abandoned iteration only gathered).
    fn save_boundary(&mut self, saver: &mut Saver, state: State) -> Result<(), CheckpointError>;

    /// Brings the iteration's light together and updates `B` of every surfel, with the
    /// Chebyshev weight `omega` (1: a plain iteration, see `accelerate`); returns the update's
    /// sums `[change, total, falling, residual]` added over the world (`update::UpdateSums`).
    fn end(&mut self, omega: f64) -> Result<[f64; 4], Self::Error>;

    /// Whether this sweep keeps the radiosity before the last iteration's, as the Chebyshev
    /// semi-iteration needs (in its updates and its checkpoints).
    fn keeps_older(&self) -> bool {
        false
    }

    /// Adds the geometric tail `factor * (B - B_previous)` to the radiosity (see `accelerate`).
    fn extrapolate(&mut self, factor: f64) -> Result<(), Self::Error>;
}

/// Where a solve starts: afresh, or from a checkpoint's state.
pub(crate) struct Start {
    /// The first iteration to run.
    pub iteration: usize,
    /// Steps of that iteration already gathered (a mid-iteration checkpoint; 0: none).
    pub within: usize,
    pub convergence: Convergence,
    pub extrapolation: Extrapolation,
}

impl Start {
    pub(crate) fn fresh() -> Self {
        Start {
            iteration: 1,
            within: 0,
            convergence: Convergence::new(),
            extrapolation: Extrapolation::default(),
        }
    }

    /// From a checkpoint's `state` (read from `path`), the iterations it holds recorded in
    /// `stats`; `within` steps of the next iteration gathered.
    pub(crate) fn resumed(
        state: &State,
        path: &std::path::Path,
        within: usize,
        stats: &mut SolveStats,
    ) -> Self {
        let mut convergence = Convergence::new();
        let iteration = convergence.resume(state, path, stats);
        Start {
            iteration,
            within,
            convergence,
            extrapolation: state.extrapolation.clone().into(),
        }
    }
}

/// Runs iterations of `sweep` from `start` until the stopping rule (or `options.max_iterations`)
/// says so, saving checkpoints with `saver`; records them in `stats`. `any_light`: something
/// emits (else `B = E` is the answer and nothing runs). A stop signal ends it with the sweep's error for an
/// [`Interruption`].
pub(crate) fn iterate<S: Sweep>(
    sweep: &mut S,
    options: &SolveOptions,
    world: &dyn Comm,
    mut saver: Option<&mut Saver>,
    start: Start,
    any_light: bool,
    stats: &mut SolveStats,
) -> Result<(), S::Error> {
    let Start {
        iteration: first,
        within: mut from,
        mut convergence,
        mut extrapolation,
    } = start;
    let steps = sweep.steps();
    let within = saver.as_ref().is_some_and(|s| s.saves_within());
    if saver.is_some() {
        crate::interrupt::start_iterating();
    }
    let progress = crate::progress::bar(steps as u64, "iteration 1");
    for iteration in first..=options.max_iterations {
        if !any_light {
            stats.converged = true;
            break;
        }
        let begin = std::mem::take(&mut from).min(steps);
        sweep.begin(iteration, begin)?;
        progress.reset();
        progress.set_position(begin as u64);
        progress.set_message(format!("iteration {iteration}"));
        let completed = iteration - 1;
        // Between two steps every rank agrees on stopping and on saving. (Not after the last:
        // a signal then stops the solve at the next boundary, with this iteration kept.)
        for step in begin..steps {
            let asked = crate::interrupt::requested().unwrap_or(0);
            let (signal, save) = match saver.as_deref() {
                Some(s) if within => s.agree_within(world, asked),
                _ => (world.max_u64(asked.max(0) as u64) as i32, false),
            };
            // Where the light holds steps beyond this one (links replayed in blocks, see
            // `Sweep::can_save_within`), the stop waits for the next step it can be saved at:
            // the steps until then add nothing, and every rank agrees on that step.
            if within && step > 0 && (signal != 0 || save) && !sweep.can_save_within(step) {
                sweep.settle();
            }
            let defer = within && step > 0 && !sweep.can_save_within(step);
            if signal != 0 && !defer {
                progress.finish_and_clear();
                let history = (convergence.previous_change, &extrapolation);
                let at = (completed, step);
                let saver = saver.as_deref_mut().map(|s| (s, within));
                return Err(interrupted(sweep, saver, signal, at, history, world).into());
            }
            // Not at the iteration's start (its boundary was saved, or is the one resumed
            // from), nor where this run resumed.
            if save && step > begin && sweep.can_save_within(step) {
                if let Some(s) = saver.as_deref_mut() {
                    let state = s.state(completed, convergence.previous_change, &extrapolation);
                    let result = sweep.save_within(s, state, step);
                    s.warn_on_failure(result);
                }
            }
            if !sweep.step(step)? {
                // Stopped part way: the signal, still pending, stops the solve where this step
                // began (a one-process sweep: no other rank waits for an agreement).
                let signal = crate::interrupt::requested().unwrap_or(0);
                progress.finish_and_clear();
                let history = (convergence.previous_change, &extrapolation);
                let at = (completed, step);
                let saver = saver.as_deref_mut().map(|s| (s, within));
                return Err(interrupted(sweep, saver, signal, at, history, world).into());
            }
            progress.inc(1);
        }
        stats.updates += sweep.updates();
        let omega = extrapolation.omega();
        let [change, total, falling, residual] = sweep.end(omega)?;
        // Under Chebyshev the plain iteration's residual estimates the error (see
        // `accelerate`).
        let chebyshev = extrapolation
            .chebyshev
            .filter(|_| omega != 1.0)
            .map(|c| c.error_estimate(if total > 0.0 { residual / total } else { 0.0 }));
        // Right after an extrapolation the change history starts again: until it contracts,
        // the contraction measured before the jump estimates the error (see `accelerate`).
        let stop = convergence.record(
            iteration,
            (change, total),
            chebyshev,
            options,
            stats,
            |relative| extrapolation.error_estimate(relative),
        );
        if stop {
            break;
        }
        if options.accelerate {
            if let Some(factor) = extrapolation.observe(change, stats.last_change, falling) {
                sweep.extrapolate(factor)?;
                // The jump is not an iteration's change: the stopping rule starts again.
                convergence.restart();
            } else if options.chebyshev && sweep.keeps_older() {
                extrapolation.chebyshev_after(stats.last_change);
            }
        }
        // A boundary the solve goes on from (never the last: a resumed solve must gather at
        // least once, for its energy balance); rank 0's clock decides for every rank.
        if iteration < options.max_iterations {
            if let Some(s) = saver.as_deref_mut() {
                if world.max_u64((world.rank() == 0 && s.due()) as u64) == 1 {
                    let state = s.state(iteration, convergence.previous_change, &extrapolation);
                    let result = sweep.save_boundary(s, state);
                    s.warn_on_failure(result);
                }
            }
        }
    }
    progress.finish_and_clear();
    stats.extrapolations = extrapolation.count;
    stats.chebyshev_updates = extrapolation.chebyshev.map(|c| c.updates);
    if options.tolerance.is_none() {
        // A fixed count of iterations: report whether it reached the default tolerance.
        stats.converged = stats.residual <= SolveOptions::default().tolerance.unwrap_or(0.0);
    }
    Ok(())
}

/// The interruption by `signal` at `(completed, done)`: `done` steps into the iteration after
/// `completed`. With mid-iteration checkpoints on (`saver`'s flag) and where the sweep can hold
/// them, those steps are saved; else the last completed iteration (unless the checkpoint on
/// disk holds it already). `history` is the stopping rule's and the extrapolation's.
fn interrupted<S: Sweep>(
    sweep: &mut S,
    saver: Option<(&mut Saver, bool)>,
    signal: i32,
    (completed, done): (usize, usize),
    (previous_change, extrapolation): (Option<f64>, &Extrapolation),
    world: &dyn Comm,
) -> Interruption {
    match saver {
        Some((s, true)) if done > 0 && sweep.can_save_within(done) => {
            s.interrupt_at(signal, completed, Some(done as u64), |s| {
                let state = s.state(completed, previous_change, extrapolation);
                sweep.save_within(s, state, done)
            })
        }
        Some((s, _)) => s.interrupt(signal, completed, |s| {
            let state = s.state(completed, previous_change, extrapolation);
            sweep.save_boundary(s, state)
        }),
        None => Interruption::without_checkpoint(signal, completed, world.rank() == 0),
    }
}

/// The stopping rule's bookkeeping.
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
    /// an estimate from the relative change while the history cannot (after a restart);
    /// `chebyshev` is the estimate of an update of the Chebyshev semi-iteration, which takes
    /// the place of both.
    pub(crate) fn record(
        &mut self,
        iteration: usize,
        (change, total): (f64, f64),
        chebyshev: Option<f64>,
        options: &SolveOptions,
        stats: &mut SolveStats,
        fallback: impl FnOnce(f64) -> Option<f64>,
    ) -> bool {
        let relative = if total > 0.0 { change / total } else { 0.0 };
        let estimate = match (chebyshev, error_estimate(relative, self.previous_change)) {
            (Some(e), _) => e,
            (None, e) if e.is_finite() => e,
            (None, e) => fallback(relative).unwrap_or(e),
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
        state: &State,
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

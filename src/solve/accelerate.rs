//! Convergence acceleration: extrapolating the geometric tail of the Jacobi iterations.
//!
//! Jacobi from `B_0 = E` adds one bounce per iteration, and after a few iterations the change
//! `d_k = B_k - B_{k-1}` shrinks by a nearly constant factor `q` (the dominant eigenvalue of the
//! transport, about the scene's mean reflectance). The light not yet gathered is then the rest of a
//! geometric series, `d_k (q + q^2 + ...) = d_k q / (1 - q)`, and adding it at once skips the
//! many iterations that would add it one bounce at a time (a furnace with `rho = 0.99` needs about
//! 900 iterations for 1e-4; its changes are exactly geometric, so one extrapolation lands on
//! `E / (1 - rho)`).
//!
//! Applied carefully, so that the answer stays physical:
//! - only when the last two ratios of the change norms agree (the iteration is in its geometric
//!   regime), and only well above the f32 rounding noise of the stored radiosity;
//! - `q` is the smaller of the two ratios (under-shooting only costs iterations; over-shooting a
//!   scene with `q` near 1 would put energy in that the next iterations must take out);
//! - the extrapolated value never goes below the emission (`B >= E`) nor below the current value
//!   where the change is positive (the tail of a non-negative series is non-negative);
//! - only while the iteration is still monotone: plain Jacobi from `B_0 = E` only raises values,
//!   so a falling part of the change (more than [`FALLING_LIMIT`] of it) means an earlier jump
//!   overshot somewhere and the iterations are taking it back. The change norms can look
//!   geometric then (at reflectance 0.999 under a lamp they do), but extrapolating a correction
//!   with a factor near `1 / (1 - q)` overshoots again, and repeated jumps diverged (`B` a
//!   thousand times the answer within 20 iterations in `tests/hard_case_twins.rs`);
//! - after an extrapolation the change history starts again, and the solver's stopping rule must
//!   do the same (an extrapolation is a jump, not an iteration's change); until it has two fresh
//!   changes it estimates the error left with the contraction measured before the jump
//!   ([`Extrapolation::error_estimate`]). That also ends a solve whose extrapolation was exact:
//!   its later changes are f32 rounding noise, which does not shrink.
//!
//! **Chebyshev semi-iteration** ([`Chebyshev`]), where the tail does not follow one mode: a scene
//! of many rooms converges by several slow modes at once, and one ratio jumps some of them too
//! far (the falling guard above then holds every later jump back). When the third change since
//! the start (or since the last jump) brings no jump, the updates that follow mix each new
//! value with the one before last, `B_{k+1} = B_{k-1} + w_k (G(B_k) - B_{k-1})` (`G` one plain
//! iteration), with the weights of Chebyshev polynomials on `[-q, q]`. The error of every
//! eigenvalue `|x| < 1` is then multiplied by `T_k(x / q) / T_k(1 / q)`, below 1 whatever `q`
//! is, so a wrong `q` costs iterations but never diverges; for `|x| <= q` it falls like
//! `(q / (1 + sqrt(1 - q^2)))^k`, 0.42 an iteration where plain iterations give 0.72. `q` is
//! [`CHEBYSHEV_MARGIN`] times the larger of the last two ratios of the change norms (the ratios
//! still grow toward the dominant eigenvalue when it starts, and too small a `q` costs more than
//! too large a one); at [`CHEBYSHEV_LIMIT`] or more it does not start and the tail
//! extrapolation is left to do its work (a box of reflectance 0.999 took 839 iterations with
//! `q` held below its dominant eigenvalue, 14 with the jump). While it runs there is no jump, and
//! the stopping rule estimates the error from the plain iteration's change `|G(B_k) - B_k|`
//! (the residual) as `residual / (1 - ratio)`: successive changes are not geometric under
//! Chebyshev, and their ratio underestimated the furnace's error a thousandfold. Values are kept
//! at least their emission.
//!
//! Everything here is a pure function of per-iteration quantities (change norms, the current and
//! previous radiosity vectors, the emission), so an in-memory and an out-of-core solver can share
//! it: the out-of-core one streams its shards through [`extrapolate`].

use crate::checkpoint::ExtrapolationState;

/// Smallest relative change at which ratios are trusted: below it the change is mostly the
/// rounding of f32 storage, and its ratios are noise.
const NOISE_FLOOR: f64 = 1e-6;

/// Two successive ratios of change norms must agree to this relative difference.
const RATIO_AGREEMENT: f64 = 2e-2;

/// Largest falling part of an iteration's change (area times the decrease, over the change
/// norm) at which it still counts as the monotone tail of plain Jacobi.
pub const FALLING_LIMIT: f64 = 1e-3;

/// Chebyshev's `q` is this times the measured ratio of the change norms.
pub const CHEBYSHEV_MARGIN: f64 = 1.1;

/// Chebyshev does not start with a `q` of this or more (see the module header).
pub const CHEBYSHEV_LIMIT: f64 = 0.98;

/// Decides when to extrapolate, from the per-iteration change norms alone.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Extrapolation {
    /// Change norms (sum over elements of area times |d|) since the last extrapolation.
    changes: Vec<f64>,
    /// How many extrapolations were made.
    pub count: usize,
    /// The larger of the two ratios that allowed the last extrapolation.
    last_ratio: Option<f64>,
    /// The Chebyshev semi-iteration, once started (it then runs to the end of the solve).
    pub chebyshev: Option<Chebyshev>,
}

/// The Chebyshev semi-iteration's state: enough to give the next update's weight.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Chebyshev {
    /// The ratio of change norms measured when it started (`q` is [`CHEBYSHEV_MARGIN`] times
    /// it).
    pub ratio: f64,
    /// Updates made with its weights so far.
    pub updates: u64,
}

impl Chebyshev {
    /// The weight of the next update: `w_2 = 1 / (1 - q^2 / 2)`, then `w_{k+1} = 1 / (1 - q^2
    /// w_k / 4)` (the plain iteration it started from was the first).
    pub fn omega(&self) -> f64 {
        let q = CHEBYSHEV_MARGIN * self.ratio;
        let mut w = 1.0 / (1.0 - q * q / 2.0);
        for _ in 0..self.updates {
            w = 1.0 / (1.0 - q * q * w / 4.0);
        }
        w
    }

    /// The relative error left after an update whose plain iteration would have changed `B` by
    /// `residual` (relative): for the slowest mode, `residual / (1 - ratio)`.
    pub fn error_estimate(&self, residual: f64) -> f64 {
        residual / (1.0 - self.ratio)
    }
}

impl From<&Extrapolation> for ExtrapolationState {
    fn from(e: &Extrapolation) -> Self {
        ExtrapolationState {
            chebyshev: e.chebyshev.map(|c| (c.ratio, c.updates)),
            ..ExtrapolationState::from_parts(e.changes.clone(), e.count, e.last_ratio)
        }
    }
}

impl From<ExtrapolationState> for Extrapolation {
    fn from(s: ExtrapolationState) -> Self {
        Extrapolation {
            chebyshev: s
                .chebyshev
                .map(|(ratio, updates)| Chebyshev { ratio, updates }),
            ..Extrapolation::from_parts(s.changes, s.count, s.last_ratio)
        }
    }
}

impl Extrapolation {
    /// Its whole state (change norms since the last extrapolation, count, last ratio), for a
    /// checkpoint: a resumed solve must extrapolate exactly when the uninterrupted one would.
    pub fn parts(&self) -> (&[f64], usize, Option<f64>) {
        (&self.changes, self.count, self.last_ratio)
    }

    /// The state [`Extrapolation::parts`] gave.
    pub fn from_parts(changes: Vec<f64>, count: usize, last_ratio: Option<f64>) -> Self {
        Extrapolation {
            changes,
            count,
            last_ratio,
            chebyshev: None,
        }
    }

    /// The weight of the next update of `B`: 1 for a plain iteration, Chebyshev's once it runs.
    pub fn omega(&self) -> f64 {
        self.chebyshev.map_or(1.0, |c| c.omega())
    }

    /// After an iteration whose change norm is `change` (recorded by [`Extrapolation::observe`],
    /// which found no jump), starts Chebyshev if the last three changes since the start or the
    /// last jump give a ratio below [`CHEBYSHEV_LIMIT`] (see the module header); counts its
    /// updates once it runs. Returns whether it runs.
    pub fn chebyshev_after(&mut self, relative: f64) -> bool {
        if let Some(c) = &mut self.chebyshev {
            c.updates += 1;
            return true;
        }
        let n = self.changes.len();
        if n < 3 || relative < NOISE_FLOOR {
            return false;
        }
        let (a, b, c) = (
            self.changes[n - 3],
            self.changes[n - 2],
            self.changes[n - 1],
        );
        if !(a > 0.0 && b > 0.0 && c.is_finite()) {
            return false;
        }
        let ratio = (b / a).max(c / b);
        if ratio > 0.0 && CHEBYSHEV_MARGIN * ratio < CHEBYSHEV_LIMIT {
            self.chebyshev = Some(Chebyshev { ratio, updates: 0 });
        }
        self.chebyshev.is_some()
    }

    /// Records iteration `k`'s change norm `change` (absolute, sum of area times |d|), its
    /// relative change `relative` (`change / total`) and its falling part `falling` (sum of area
    /// times the decrease where values went down); returns the factor `q / (1 - q)` to
    /// extrapolate with, or `None` to iterate plainly.
    pub fn observe(&mut self, change: f64, relative: f64, falling: f64) -> Option<f64> {
        if self.chebyshev.is_some() {
            return None;
        }
        self.changes.push(change);
        let n = self.changes.len();
        if n < 3 || relative < NOISE_FLOOR || !change.is_finite() {
            return None;
        }
        if falling > FALLING_LIMIT * change {
            return None;
        }
        let (a, b, c) = (
            self.changes[n - 3],
            self.changes[n - 2],
            self.changes[n - 1],
        );
        if a <= 0.0 || b <= 0.0 {
            return None;
        }
        let (q1, q2) = (b / a, c / b);
        if !(q1 > 0.0 && q1 < 1.0 && q2 > 0.0 && q2 < 1.0) {
            return None;
        }
        if (q1 - q2).abs() > RATIO_AGREEMENT * q2 {
            return None;
        }
        let q = q1.min(q2);
        self.changes.clear();
        self.count += 1;
        // The error estimate after the jump takes the larger ratio: it must not stop early.
        self.last_ratio = Some(q1.max(q2));
        Some(q / (1.0 - q))
    }

    /// The relative error left after an iteration whose relative change is `relative`, from the
    /// contraction measured at the last extrapolation (the larger ratio, to err on the side of
    /// iterating): `relative q / (1 - q)`. For the stopping
    /// rule right after a jump, when the change history has started again (and, once the changes
    /// reach the f32 noise, no longer shrink from one iteration to the next).
    pub fn error_estimate(&self, relative: f64) -> Option<f64> {
        self.last_ratio.map(|q| relative * q / (1.0 - q))
    }
}

/// Adds the geometric tail `factor * (current - previous)` to `current`, element by element,
/// keeping every value at least its emission and never lowering a value that is rising.
/// The three slices are parallel (one entry per surfel, by side and channel).
pub fn extrapolate(
    current: &mut [[[f32; 3]; 2]],
    previous: &[[[f32; 3]; 2]],
    emission: &[[[f32; 3]; 2]],
    factor: f64,
) {
    for ((b, p), e) in current.iter_mut().zip(previous).zip(emission) {
        for side in 0..2 {
            for ch in 0..3 {
                let now = b[side][ch] as f64;
                let d = now - p[side][ch] as f64;
                let next = now + factor * d;
                let floor = if d > 0.0 { now } else { e[side][ch] as f64 };
                b[side][ch] = next.max(floor) as f32;
            }
        }
    }
}

/// The Chebyshev update of one value: `older + omega (plain - older)`, at least `emission`
/// (`plain` is the plain iteration's new value `G(B_k)`, `older` the value before last,
/// `B_{k-1}`).
#[inline]
pub fn chebyshev_value(plain: f64, older: f64, omega: f64, emission: f64) -> f64 {
    (older + omega * (plain - older)).max(emission)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn geometric_series_is_completed_exactly() {
        // B_k = E (1 + rho + ... + rho^k): changes E rho^k (per unit area).
        let (e, rho) = (2.0f64, 0.9f64);
        let mut ex = Extrapolation::default();
        let mut b = e;
        let mut factor = None;
        for k in 1..=3 {
            let prev = b;
            b += e * rho.powi(k);
            factor = ex.observe(b - prev, (b - prev) / b, 0.0);
        }
        let f = factor.expect("three geometric changes are enough");
        let mut current = [[[b as f32; 3]; 2]];
        let previous = [[[(b - e * rho.powi(3)) as f32; 3]; 2]];
        extrapolate(&mut current, &previous, &[[[e as f32; 3]; 2]], f);
        let exact = e / (1.0 - rho);
        assert!((current[0][0][0] as f64 - exact).abs() < 1e-5 * exact);
        assert_eq!(ex.count, 1);
    }

    #[test]
    fn no_extrapolation_while_ratios_disagree_or_in_noise() {
        let mut ex = Extrapolation::default();
        assert_eq!(ex.observe(1.0, 0.1, 0.0), None);
        assert_eq!(ex.observe(0.5, 0.05, 0.0), None);
        // Ratio 0.5 then 0.8: not geometric yet.
        assert_eq!(ex.observe(0.4, 0.04, 0.0), None);
        // Geometric but below the noise floor.
        let mut quiet = Extrapolation::default();
        for c in [1e-8, 0.5e-8, 0.25e-8] {
            assert_eq!(quiet.observe(c, c, 0.0), None);
        }
    }

    #[test]
    fn no_extrapolation_while_an_overshoot_is_taken_back() {
        // Geometric change norms, but a tenth of the last change is values falling.
        let mut ex = Extrapolation::default();
        assert_eq!(ex.observe(1.0, 0.1, 0.0), None);
        assert_eq!(ex.observe(0.5, 0.05, 0.0), None);
        assert_eq!(ex.observe(0.25, 0.025, 0.025), None);
        // Once the values only rise again, the tail is extrapolated.
        assert!(ex.observe(0.125, 0.0125, 0.0).is_some());
    }

    #[test]
    fn values_stay_at_least_the_emission() {
        // A falling value (an earlier overshoot being corrected) may not go below E.
        let mut current = [[[1.1f32; 3]; 2]];
        let previous = [[[2.0f32; 3]; 2]];
        extrapolate(&mut current, &previous, &[[[1.0; 3]; 2]], 50.0);
        assert_eq!(current[0][0][0], 1.0);
    }

    /// Iterates `B = e + K B` for a diagonal `K` (each entry one mode, eigenvalue `lambda`):
    /// plain Jacobi, or as `iterate` drives the solvers with acceleration (the tail jump when
    /// `observe` finds one, Chebyshev's weights once `chebyshev_after` starts it). Stops when the stopping rule's
    /// estimate is below `tolerance`; returns the iterations and the true relative error then.
    fn solve_modes(lambda: &[f64], chebyshev: bool, tolerance: f64) -> (usize, f64) {
        let exact: Vec<f64> = lambda.iter().map(|l| 1.0 / (1.0 - l)).collect();
        let total: f64 = exact.iter().sum();
        let mut b = vec![1.0f64; lambda.len()];
        let mut older = b.clone();
        let mut ex = Extrapolation::default();
        let mut last_relative: Option<f64> = None;
        for k in 1..10_000 {
            let omega = ex.omega();
            let (mut change, mut residual, mut sum) = (0.0, 0.0, 0.0);
            for i in 0..b.len() {
                let plain = 1.0 + lambda[i] * b[i];
                residual += (plain - b[i]).abs();
                let new = if omega != 1.0 {
                    chebyshev_value(plain, older[i], omega, 0.0)
                } else {
                    plain
                };
                change += (new - b[i]).abs();
                sum += new;
                older[i] = b[i];
                b[i] = new;
            }
            let relative = change / sum;
            let estimate = match (ex.chebyshev.filter(|_| omega != 1.0), last_relative) {
                (Some(c), _) => c.error_estimate(residual / sum),
                (None, Some(p)) if relative < p => relative * (relative / p) / (1.0 - relative / p),
                _ => f64::INFINITY,
            };
            last_relative = Some(relative);
            let error: f64 = b
                .iter()
                .zip(&exact)
                .map(|(x, e)| (x - e).abs())
                .sum::<f64>()
                / total;
            if estimate <= tolerance {
                return (k, error);
            }
            if !chebyshev {
                continue;
            }
            if let Some(factor) = ex.observe(change, relative, 0.0) {
                // The tail jump (no floors: these modes are not a scene's light).
                for i in 0..b.len() {
                    b[i] += factor * (b[i] - older[i]);
                }
                last_relative = None;
            } else {
                ex.chebyshev_after(relative);
            }
        }
        panic!("no convergence");
    }

    #[test]
    fn chebyshev_needs_fewer_iterations_and_its_estimate_is_honest() {
        // Several slow modes of both signs, as in a building of many rooms.
        let lambda = [0.72, 0.66, 0.5, 0.3, 0.0, -0.2, -0.45];
        let tolerance = 1e-6;
        let (plain, plain_error) = solve_modes(&lambda, false, tolerance);
        let (fast, fast_error) = solve_modes(&lambda, true, tolerance);
        assert!(fast * 10 <= plain * 7, "{fast} iterations against {plain}");
        // The estimate is measured with the ratio seen when Chebyshev started, a little below
        // the slowest mode's: the error left may exceed the tolerance a little, not more.
        assert!(fast_error <= 1.5 * tolerance, "error {fast_error:e}");
        assert!(plain_error <= 1.5 * tolerance, "error {plain_error:e}");
    }

    #[test]
    fn chebyshev_weights_never_diverge_on_modes_beyond_q() {
        // q from a ratio of 0.6 (q = 0.66): a mode at -0.95 and one at 0.9, far outside
        // [-q, q], still shrink, and no slower than plain iterations would shrink them.
        let c = Chebyshev {
            ratio: 0.6,
            updates: 0,
        };
        for lambda in [-0.95, 0.9, 0.99] {
            // Error of the mode: e_{k+1} = e_{k-1} + w (lambda e_k - e_{k-1}).
            let (mut older, mut now) = (1.0f64, lambda);
            let mut state = c;
            for k in 2..400 {
                let w = state.omega();
                let next = older + w * (lambda * now - older);
                (older, now) = (now, next);
                state.updates += 1;
                assert!(
                    now.abs() <= 1.05 * f64::abs(lambda).powi(k - 1) + 1e-300,
                    "mode {lambda}: error {now} at step {k}"
                );
            }
            assert!(now.abs() < 1e-1 || lambda.abs() > 0.98);
        }
    }

    #[test]
    fn chebyshev_does_not_start_near_reflectance_one_nor_in_noise() {
        let mut slow = Extrapolation::default();
        for c in [1.0, 0.9, 0.85] {
            slow.observe(c, c, 0.0);
        }
        // Ratio 0.944: q would be 1.04.
        assert!(!slow.chebyshev_after(0.1));
        let mut quiet = Extrapolation::default();
        for c in [1e-8, 0.6e-8, 0.4e-8] {
            quiet.observe(c, c, 0.0);
        }
        assert!(!quiet.chebyshev_after(1e-8));
        let mut fast = Extrapolation::default();
        for c in [1.0, 0.6, 0.4] {
            fast.observe(c, c, 0.0);
        }
        assert!(fast.chebyshev_after(0.1));
        let started = fast.chebyshev.expect("started");
        assert!((started.ratio - 2.0 / 3.0).abs() < 1e-12);
        // Its first weight is w_2 = 1 / (1 - q^2 / 2), and the weights fall toward
        // 2 / (1 + sqrt(1 - q^2)).
        let q: f64 = CHEBYSHEV_MARGIN * 2.0 / 3.0;
        assert!((fast.omega() - 1.0 / (1.0 - q * q / 2.0)).abs() < 1e-12);
        for _ in 0..50 {
            fast.chebyshev_after(0.1);
        }
        assert!((fast.omega() - 2.0 / (1.0 + (1.0 - q * q).sqrt())).abs() < 1e-9);
        // No jump while it runs.
        assert_eq!(fast.observe(0.1, 0.1, 0.0), None);
    }
}

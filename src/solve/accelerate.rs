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

/// Decides when to extrapolate, from the per-iteration change norms alone.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Extrapolation {
    /// Change norms (sum over elements of area times |d|) since the last extrapolation.
    changes: Vec<f64>,
    /// How many extrapolations were made.
    pub count: usize,
    /// The larger of the two ratios that allowed the last extrapolation.
    last_ratio: Option<f64>,
}

impl From<&Extrapolation> for ExtrapolationState {
    fn from(e: &Extrapolation) -> Self {
        ExtrapolationState::from_parts(e.changes.clone(), e.count, e.last_ratio)
    }
}

impl From<ExtrapolationState> for Extrapolation {
    fn from(s: ExtrapolationState) -> Self {
        Extrapolation::from_parts(s.changes, s.count, s.last_ratio)
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
        }
    }

    /// Records iteration `k`'s change norm `change` (absolute, sum of area times |d|), its
    /// relative change `relative` (`change / total`) and its falling part `falling` (sum of area
    /// times the decrease where values went down); returns the factor `q / (1 - q)` to
    /// extrapolate with, or `None` to iterate plainly.
    pub fn observe(&mut self, change: f64, relative: f64, falling: f64) -> Option<f64> {
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
}

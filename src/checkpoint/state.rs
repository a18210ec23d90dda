//! What a checkpoint holds beside the radiosity: where the solve stood (iterations done, the
//! stopping rule's and the extrapolation's history, a position inside an iteration).

use super::*;

/// The solver's bookkeeping at an iteration boundary.
/// The tail extrapolation's whole state (`solve::accelerate::Extrapolation`): the change norms
/// since its last jump, its count of jumps and the ratio that allowed the last one. A resumed
/// solve must extrapolate exactly when the uninterrupted one would. Plain data here, so that the
/// checkpoints do not depend on the solver.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExtrapolationState {
    pub changes: Vec<f64>,
    pub count: usize,
    pub last_ratio: Option<f64>,
    /// The Chebyshev semi-iteration once it runs (format version 6): the ratio it started
    /// with and its updates so far. The next update then also needs the radiosity before the
    /// last, which the file holds after the radiosity.
    pub chebyshev: Option<(f64, u64)>,
}

impl ExtrapolationState {
    /// The change norms, the count and the last ratio.
    pub fn parts(&self) -> (&[f64], usize, Option<f64>) {
        (&self.changes, self.count, self.last_ratio)
    }

    /// The state [`ExtrapolationState::parts`] gave.
    pub fn from_parts(changes: Vec<f64>, count: usize, last_ratio: Option<f64>) -> Self {
        ExtrapolationState {
            changes,
            count,
            last_ratio,
            chebyshev: None,
        }
    }
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct State {
    /// Iterations completed.
    pub iteration: u64,
    /// Ranks of the run that wrote it (a resume on another count is allowed; its sums across
    /// ranks are added in another grouping, so the last bits may differ).
    pub ranks: u32,
    /// The stopping rule's last relative change (`iterate::Convergence`).
    pub previous_change: Option<f64>,
    pub extrapolation: ExtrapolationState,
    /// In mid-iteration: how many of this rank's directions (the same count on every rank, see
    /// `jacobi`) of iteration `iteration + 1` are gathered; the file then holds every rank's
    /// partial sums. `None` at an iteration boundary.
    pub within: Option<u64>,
    /// Whose partial sums a mid-iteration checkpoint holds. 0: each rank's light gathered from
    /// its own directions, for every surfel (one process, `--distribute directions`, out of
    /// core). `G` of 1 or more: the data mode (1) or the hybrid mode with `G` groups
    /// (`distribute::data`), each rank's light of the surfels it held at that direction, by
    /// surfel id (zero for the others); `within` then counts the steps of the group's
    /// directions. Only a run of the same layout and rank count continues inside the iteration.
    pub data_groups: u32,
    /// Out of core, inside a main axis (format version 4): after the one rank's partial sums
    /// (then the canonical sum of the light of the axes done), the file holds one more array,
    /// the light the axis in progress has gathered so far, brought to canonical order
    /// (`outcore::solver`). With `data_groups` `G` (format version 5, the data and hybrid
    /// modes out of core, `distribute::ooc`): the file holds `G` canonical sums of the axes each
    /// group has done, then `G` arrays of the light of each group's axis in progress (zeros
    /// where a group has none), whatever the rank count. `false` at an iteration boundary and in
    /// every other layout.
    pub axis_in_progress: bool,
    /// The partial sums are f32 values (format version 7): the out-of-core solvers hold the
    /// light they gather in f32, so their sums take 24 bytes a surfel instead of 48 (a
    /// mid-iteration checkpoint of 1.2 x 10^8 surfels fell from 14 to 8.5 GB). `false`: f64, as
    /// the in-memory solvers add them up (and every file before version 7).
    pub sums_in_f32: bool,
    /// Read from a file before format version 8, whose out-of-core solver walked every
    /// iteration in one order; not stored (see [`State::walked_otherwise`]).
    pub walked_forwards: bool,
}

impl State {
    /// Whether the out-of-core solvers now walk iteration `iteration + 1` in another order
    /// than the solver that wrote this mid-iteration checkpoint: since format version 8 they
    /// walk even iterations backwards (`outcore::solver::walk_of_iteration`), so the light of a
    /// file before it, written inside an even iteration, belongs to other directions than
    /// theirs. They then start that iteration from its beginning (the same radiosity).
    pub fn walked_otherwise(&self) -> bool {
        self.walked_forwards && self.within.is_some() && (self.iteration + 1) % 2 == 0
    }
}

/// Everything in a checkpoint but the radiosity.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    pub identity: Identity,
    pub state: State,
}

impl Header {
    /// Whether the partial sums are the out-of-core layout by groups (see
    /// [`State::axis_in_progress`]).
    pub fn by_groups_out_of_core(&self) -> bool {
        self.state.within.is_some() && self.state.axis_in_progress && self.state.data_groups > 0
    }

    /// Radiosity arrays the file holds before the partial sums: the radiosity, and while the
    /// Chebyshev semi-iteration runs the radiosity before the last iteration's.
    pub fn radiosity_arrays(&self) -> u32 {
        1 + self.state.extrapolation.chebyshev.is_some() as u32
    }

    /// Arrays of partial sums the file holds before the axes in progress: one per rank that
    /// wrote it, or one per group out of core (none at an iteration boundary).
    pub fn partial_ranks(&self) -> u32 {
        if self.by_groups_out_of_core() {
            self.state.data_groups
        } else if self.state.within.is_some() {
            self.state.ranks
        } else {
            0
        }
    }

    /// Bytes a surfel of one array of partial sums takes in the file (f64 or f32, see
    /// [`State::sums_in_f32`]).
    pub fn partial_len(&self) -> usize {
        if self.state.sums_in_f32 {
            super::file::PARTIAL32_LEN
        } else {
            super::file::PARTIAL_LEN
        }
    }

    /// Arrays of partial sums the file holds: the ranks' (or groups'), then the axis in
    /// progress's, one or one per group (see [`State::axis_in_progress`]).
    pub fn partial_arrays(&self) -> u32 {
        let axes = if self.by_groups_out_of_core() {
            self.state.data_groups
        } else {
            (self.state.within.is_some() && self.state.axis_in_progress) as u32
        };
        self.partial_ranks() + axes
    }
}

//! The radiosity solver: Jacobi iterations over all line directions.
//!
//! Pipeline of one solve: per-normal energy normalisation (`normalize`), then iterations; each
//! iteration walks the directions, and per direction dispatches surfels into their discrete lines
//! (`dispatch`) and gathers light along each line (`propagate`). `jacobi` owns the iteration loop,
//! the stopping rule and the result.

pub mod accelerate;
pub mod coverage;
pub mod direct;
pub mod dispatch;
pub mod effects;
pub mod jacobi;
pub mod normalize;
pub mod propagate;

pub use jacobi::{solve, SolveOptions};

/// Radiosity of every surfel, by side (`FRONT`, `BACK`) and RGB channel, in the units of `Ke`.
#[derive(Clone, Debug, Default)]
pub struct Solution {
    pub radiosity: Vec<[[f32; 3]; 2]>,
    pub stats: SolveStats,
}

/// What a solve did, for the report.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct SolveStats {
    pub directions: usize,
    pub iterations: usize,
    pub converged: bool,
    /// Estimated relative error left in `B` when the solve stopped (see `jacobi`).
    pub residual: f64,
    /// Relative change of the last iteration.
    pub last_change: f64,
    /// The solve stopped because the changes no longer shrank at the rounding level of f32
    /// storage, before reaching the tolerance (see `jacobi`).
    pub stalled: bool,
    pub threads: usize,
    /// Seconds spent in dispatch (building lines) and in propagation, summed over iterations.
    pub dispatch_seconds: f64,
    pub propagate_seconds: f64,
    pub normalize_seconds: f64,
    /// Seconds summing the gathered light across ranks (distributed solves).
    pub reduce_seconds: f64,
    /// Distributed solves: every rank's dispatch, propagate and reduce seconds, by rank.
    pub per_rank_seconds: Vec<[f64; 3]>,
    /// Surfel-side updates: surfels x line directions x iterations.
    pub updates: u64,
    /// Emitted and absorbed power per channel (world units: B times area).
    pub emitted_power: [f64; 3],
    pub absorbed_power: [f64; 3],
    /// Channels actually solved: 1 for a grey scene solved once and copied, else 3.
    pub channels: usize,
    /// Tail extrapolations made (see `accelerate`).
    pub extrapolations: usize,
    /// Data and hybrid modes: what the distribution moved and how balanced it was.
    pub data: Option<crate::distribute::data::DataStats>,
    /// The iteration of the checkpoint this solve continued from (`--resume`).
    pub resumed_from_iteration: Option<usize>,
    /// The direct-light pass, where it ran (see `direct`).
    pub direct: Option<direct::DirectStats>,
}

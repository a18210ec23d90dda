//! What a solve returns and reports: the radiosity, the solver's statistics, and what the
//! data distribution moved (kept here, beside the statistics that hold them, so that the
//! solver does not depend on the distribution modes).

use super::direct;

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
    /// Updates made by the Chebyshev semi-iteration (see `accelerate`); `None` where it did
    /// not start.
    pub chebyshev_updates: Option<u64>,
    /// Data and hybrid modes: what the distribution moved and how balanced it was.
    pub data: Option<DataStats>,
    /// The iteration of the checkpoint this solve continued from (`--resume`).
    pub resumed_from_iteration: Option<usize>,
    /// The direct-light pass, where it ran (see `direct`).
    pub direct: Option<direct::DirectStats>,
    /// The partner links kept between iterations (the in-memory solver's; `None` where every
    /// iteration searches again).
    pub links: Option<LinkStats>,
    /// Whether the scene's light is sealed in, and the scales of its last update (see `closed`).
    pub closure: Option<ClosureStats>,
}

/// A closed scene's check and the scales its last update applied (see `closed`).
#[derive(Clone, Copy, Debug, Default, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct ClosureStats {
    pub verdict: super::enclosure::Verdict,
    pub scales: super::closed::Scales,
}

/// The partner links kept between iterations (see `links`).
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct LinkStats {
    /// Directions whose links were kept (on every rank that gathers them).
    pub kept_directions: usize,
    pub directions: usize,
    /// Bytes the kept links hold, summed over the ranks.
    pub bytes: u64,
    /// Those bytes per surfel and kept direction.
    pub bytes_per_surfel_direction: f64,
    /// Where they are kept: `memory` (in memory), `files` (out of core, in work files beside the
    /// band data), or `none` (every iteration searches again).
    #[serde(default)]
    pub kept_in: String,
}

impl LinkStats {
    /// A solve that keeps no links: every iteration searches again.
    pub fn none(directions: usize) -> Self {
        LinkStats {
            directions,
            kept_in: "none".to_string(),
            ..Default::default()
        }
    }
}

/// What the data distribution did, for the report.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct DataStats {
    /// Direction groups (1 in the data mode) and ranks per group.
    pub groups: usize,
    pub ranks_per_group: usize,
    /// Mean, over the directions, of the fraction of the surfels that changed rank in each
    /// exchange of that direction (in memory, iterations that replay every link exchange
    /// nothing until their end).
    pub exchanged_fraction: f64,
    /// The largest such fraction (the first direction of an iteration, or of an octant).
    pub max_exchanged_fraction: f64,
    /// The fraction for each direction, in walk order (averaged over its exchanges).
    pub exchanged_by_direction: Vec<f64>,
    /// Mean, over directions, of the largest rank's surfels over the mean (1 is perfect).
    pub imbalance: f64,
    pub max_imbalance: f64,
    /// Surfel bytes sent to other ranks, before and after compression.
    pub bytes_packed: u64,
    pub bytes_sent: u64,
    /// In memory: bytes of the exchange plans all ranks keep (`distribute::data::plan`) and
    /// of the parts of the light and radiosity moved at the ends of iterations.
    #[serde(default)]
    pub plan_bytes: u64,
    #[serde(default)]
    pub end_of_iteration_bytes: u64,
    /// Every rank's seconds per phase, by rank.
    pub per_rank: Vec<PhaseSeconds>,
    /// The data mode out of core (`--memory`): every rank's work-file traffic, largest share
    /// and peak memory, by rank.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub out_of_core: Vec<RankOutOfCore>,
    /// Out of core: the steps inside an axis that moved no record on any rank the first time
    /// and were skipped in later iterations without reading the held files (the same on every
    /// rank; 0 in memory).
    #[serde(default)]
    pub quiet_steps_skipped: u64,
}

/// What one rank of the data mode out of core moved through its disk and held.
#[derive(Clone, Copy, Debug, Default, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct RankOutOfCore {
    /// Bytes read from and written to the input and the rank's work files.
    pub bytes_read: u64,
    pub bytes_written: u64,
    /// The same per surfel of the scene and direction of every iteration.
    pub bytes_read_per_voxel_direction: f64,
    pub bytes_written_per_voxel_direction: f64,
    /// The most surfel bytes (one held record per surfel: static data, radiosity, light) the
    /// rank held in its files for one direction.
    pub largest_share_bytes: u64,
    /// The rank's peak resident memory (`VmHWM`) over the whole run.
    pub peak_rss_bytes: u64,
    /// The same before the scene was read: the program and its MPI library, which the budget
    /// does not cover.
    pub start_rss_bytes: u64,
    /// Passes over the rank's held files that gathered several directions of one slope
    /// together, and the directions they gathered beyond one each (over all iterations).
    #[serde(default)]
    pub joint_passes: u64,
    #[serde(default)]
    pub joint_directions: u64,
}

/// One rank's seconds in each phase of the data mode.
#[derive(Clone, Copy, Debug, Default, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct PhaseSeconds {
    pub balance: f64,
    pub fill: f64,
    pub exchange: f64,
    pub merge: f64,
    pub dispatch: f64,
    pub propagate: f64,
    pub reduce: f64,
}

impl PhaseSeconds {
    pub(crate) const FIELDS: usize = 7;

    pub(crate) fn to_array(self) -> [f64; Self::FIELDS] {
        [
            self.balance,
            self.fill,
            self.exchange,
            self.merge,
            self.dispatch,
            self.propagate,
            self.reduce,
        ]
    }

    pub(crate) fn from_slice(v: &[f64]) -> Self {
        PhaseSeconds {
            balance: v[0],
            fill: v[1],
            exchange: v[2],
            merge: v[3],
            dispatch: v[4],
            propagate: v[5],
            reduce: v[6],
        }
    }
}

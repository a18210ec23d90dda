//! The radiosity solver: Jacobi iterations over all line directions.
//!
//! Pipeline of one solve: per-normal energy normalisation (`normalize`), then iterations; each
//! iteration walks the directions, and per direction dispatches surfels into their discrete lines
//! (`dispatch`) and gathers light along each line (`propagate`). `iterate` owns the one
//! iteration loop of every solve path and the stopping rule; `jacobi` is its in-memory sweep.

pub mod accelerate;
pub mod closed;
pub mod coverage;
pub mod direct;
pub mod dispatch;
pub mod effects;
pub mod enclosure;
pub mod iterate;
pub mod jacobi;
pub mod kept_links;
pub mod light_sum;
pub mod links;
pub(crate) mod mix_hash;
pub mod normalize;
pub mod propagate;
pub mod stats;
pub mod update;

pub use jacobi::{solve, SolveOptions};

pub use stats::{Solution, SolveStats};

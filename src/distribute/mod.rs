//! Running one solve on several processes: the modes, the data mode's distribution, and (cargo
//! feature `mpi`) the MPI implementation of the communication trait (`crate::comm`).
//!
//! Modes (`--distribute`): `directions` (paper, section 3.2): every rank holds the whole scene,
//! takes every `size`-th direction, and the light gathered is summed across ranks once per
//! iteration; every rank then holds the same radiosity. `data` (section 4, module [`data`]):
//! each rank owns whole lines, found per direction by an elastic balance ([`balance`]), and the
//! surfels travel between ranks as the directions turn. `hybrid` (section 5): groups of ranks take
//! blocks of directions, and inside a group the data is distributed.

pub mod balance;
pub mod data;
#[cfg(feature = "mpi")]
pub mod mpi_comm;
pub mod ooc;

pub use crate::comm::{dealt, Comm, SingleProcess};

/// How a solve is spread over processes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// One process.
    Single,
    /// Directions dealt out to ranks; every rank holds the whole scene.
    Directions,
    /// Whole lines owned by ranks, surfels exchanged per direction (`compress`: with zstd).
    Data { compress: bool },
    /// Groups of ranks share the directions; data distributed inside a group. `groups` 0 picks
    /// the count (see [`hybrid_groups`]).
    Hybrid { groups: usize, compress: bool },
}

impl Mode {
    pub fn name(self) -> &'static str {
        match self {
            Mode::Single => "single",
            Mode::Directions => "directions",
            Mode::Data { .. } => "data",
            Mode::Hybrid { .. } => "hybrid",
        }
    }
}

/// The number of direction groups of a hybrid run on `size` ranks when the user gave none: the
/// largest divisor of `size` not above its square root (4 ranks: 2 groups of 2), so that both the
/// direction share and the data share grow with the machine.
pub fn hybrid_groups(size: usize) -> usize {
    (1..=size.max(1))
        .filter(|g| size % g == 0 && g * g <= size)
        .max()
        .unwrap_or(1)
}

/// The world size an MPI launcher announced to this process, if any (Open MPI, MPICH/Hydra and
/// Slurm's PMI set these). A process started by `mpirun -n 4` that sees no MPI (a build without
/// the `mpi` feature, or an MPI library that does not match the launcher) would otherwise run
/// the whole solve four times over, all writing the same files.
pub fn launcher_world_size() -> Option<usize> {
    [
        "OMPI_COMM_WORLD_SIZE",
        "PMI_SIZE",
        "PMIX_SIZE",
        "MPI_LOCALNRANKS",
    ]
    .iter()
    .filter_map(|k| std::env::var(k).ok())
    .find_map(|v| v.trim().parse().ok())
}

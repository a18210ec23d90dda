//! Running one solve on several processes: the communication the solver needs, behind one small
//! trait, with a single-process implementation and (cargo feature `mpi`) the MPI one.
//!
//! Modes (`--distribute`): `directions` (paper, section 3.2): every rank holds the whole scene,
//! takes every `size`-th direction, and the light gathered is summed across ranks once per
//! iteration; every rank then holds the same radiosity. `data` (section 4, module [`data`]):
//! each rank owns whole lines, found per direction by an elastic balance ([`balance`]), and the
//! surfels travel between ranks as the directions turn. `hybrid` (section 5): groups of ranks take
//! blocks of directions, and inside a group the data is distributed.
//!
//! All communication happens on the main thread, between the threaded parts of the solver.
//! Sums are made in rank order (each rank adds one part of the values, rank 0's first, and
//! hands the result to all), never by the MPI library's own reduction, whose order may change
//! between runs: so the same launch gives the same bits every time.

pub mod balance;
pub mod data;
#[cfg(feature = "mpi")]
pub mod mpi_comm;
pub mod ooc;

/// What the solver needs from the processes it runs on.
pub trait Comm {
    /// This process's rank, `0..size`.
    fn rank(&self) -> usize;
    /// Number of processes.
    fn size(&self) -> usize;
    /// Replaces `values` on every rank by the element-wise sum over ranks, added in rank order.
    fn sum_in_place(&self, values: &mut [f64]);
    /// The largest of `value` over ranks.
    fn max_u64(&self, value: u64) -> u64;
    /// Sends `outgoing[d]` to rank `d` (one buffer per rank, this rank's own included) and
    /// returns what every rank sent here, indexed by source rank.
    fn exchange(&self, outgoing: Vec<Vec<u8>>) -> Vec<Vec<u8>>;
    /// Splits the processes into groups: those passing the same `color` form one, ranked in the
    /// order of their ranks here. Every process must call it.
    fn split(&self, color: usize) -> Box<dyn Comm>;
}

/// One process: sums are the values themselves.
#[derive(Clone, Copy, Debug, Default)]
pub struct SingleProcess;

impl Comm for SingleProcess {
    fn rank(&self) -> usize {
        0
    }

    fn size(&self) -> usize {
        1
    }

    fn sum_in_place(&self, _values: &mut [f64]) {}

    fn max_u64(&self, value: u64) -> u64 {
        value
    }

    fn exchange(&self, outgoing: Vec<Vec<u8>>) -> Vec<Vec<u8>> {
        outgoing
    }

    fn split(&self, _color: usize) -> Box<dyn Comm> {
        Box::new(SingleProcess)
    }
}

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

/// Splits `count` items (directions) into this rank's share: every `size`-th one from `rank`.
pub fn dealt(count: usize, rank: usize, size: usize) -> Vec<usize> {
    (rank..count).step_by(size.max(1)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_direction_is_dealt_once() {
        for size in 1..6 {
            let mut all: Vec<usize> = (0..size).flat_map(|r| dealt(23, r, size)).collect();
            all.sort_unstable();
            assert_eq!(all, (0..23).collect::<Vec<_>>());
        }
    }
}

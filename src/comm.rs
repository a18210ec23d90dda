//! How the processes of one solve talk: the small trait the solvers call ([`Comm`]), its
//! single-process implementation, and how directions are dealt to ranks. The MPI implementation
//! lives in `distribute::mpi_comm` (cargo feature `mpi`); the solvers know only this trait, so
//! they do not depend on the distribution modes built on them.
//!
//! All communication happens on the main thread, between the threaded parts of the solver.
//! Sums are made in rank order (each rank adds one part of the values, rank 0's first, and
//! hands the result to all), never by the MPI library's own reduction, whose order may change
//! between runs: so the same launch gives the same bits every time.

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
    /// Returns once every rank has called it, sleeping between checks instead of spinning: a
    /// rank that waits while another works alone (rank 0 writing the outputs, or running the
    /// direct-light pass out of core) leaves its core to that rank's threads. MPI's own waits
    /// spin: where ranks shared a node's cores, rank 0's outputs took 2.7 to 2.8 s against
    /// 2.0 s with this wait (docs/cluster.md).
    fn wait_quietly(&self);
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

    fn wait_quietly(&self) {}
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

//! The MPI implementation of [`Comm`] (cargo feature `mpi`, over the system's MPI library
//! through the `mpi` crate).
//!
//! One MPI call moves at most 2^31 - 1 elements, and very large messages were slow: sums go in
//! chunks of [`CHUNK`] values. Each chunk is gathered to rank 0, added there in rank order, and
//! broadcast back, so the result does not depend on the library's choice of reduction order.

use super::Comm;
use mpi::collective::CommunicatorCollectives;
use mpi::topology::{Communicator, SimpleCommunicator};
use mpi::traits::Root;

/// Values per collective call (8 MiB of f64 per rank).
pub const CHUNK: usize = 1 << 20;

/// MPI's world communicator; MPI is finalized when this is dropped.
pub struct MpiComm {
    _universe: mpi::environment::Universe,
    world: SimpleCommunicator,
}

impl MpiComm {
    /// Initializes MPI (once per process); `None` if it cannot be or already was.
    pub fn init() -> Option<Self> {
        let universe = mpi::initialize()?;
        let world = universe.world();
        Some(MpiComm {
            _universe: universe,
            world,
        })
    }
}

impl Comm for MpiComm {
    fn rank(&self) -> usize {
        self.world.rank() as usize
    }

    fn size(&self) -> usize {
        self.world.size() as usize
    }

    fn sum_in_place(&self, values: &mut [f64]) {
        let size = self.size();
        if size == 1 {
            return;
        }
        let root = self.world.process_at_rank(0);
        let mut gathered = if self.rank() == 0 {
            vec![0f64; CHUNK.min(values.len()) * size]
        } else {
            Vec::new()
        };
        for chunk in values.chunks_mut(CHUNK) {
            let len = chunk.len();
            if self.rank() == 0 {
                let buf = &mut gathered[..len * size];
                root.gather_into_root(&*chunk, buf);
                // Rank 0's own values first, then rank 1's, ...: a fixed order.
                for (k, v) in chunk.iter_mut().enumerate() {
                    let mut sum = buf[k];
                    for r in 1..size {
                        sum += buf[r * len + k];
                    }
                    *v = sum;
                }
            } else {
                root.gather_into(&*chunk);
            }
            root.broadcast_into(chunk);
        }
    }

    fn max_u64(&self, value: u64) -> u64 {
        let mut out = 0u64;
        self.world
            .all_reduce_into(&value, &mut out, mpi::collective::SystemOperation::max());
        out
    }
}

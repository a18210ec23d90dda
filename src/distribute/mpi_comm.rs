//! The MPI implementation of [`Comm`] (cargo feature `mpi`, over the system's MPI library
//! through the `mpi` crate).
//!
//! One MPI call moves at most 2^31 - 1 elements, and very large messages were slow: sums go in
//! chunks of [`CHUNK`] values. Each chunk is gathered to rank 0, added there in rank order, and
//! broadcast back, so the result does not depend on the library's choice of reduction order.

use super::Comm;
use mpi::collective::CommunicatorCollectives;
use mpi::datatype::{Partition, PartitionMut};
use mpi::topology::{Color, Communicator, SimpleCommunicator};
use mpi::traits::Root;
use mpi::Count;

/// Values per collective call (8 MiB of f64 per rank).
pub const CHUNK: usize = 1 << 20;

/// Bytes per pair of ranks in one round of an exchange (well below MPI's 2^31 - 1 counts).
pub const EXCHANGE_CHUNK: usize = 1 << 26;

/// An MPI communicator: the world (MPI is finalized when that one is dropped) or a group split
/// from it.
pub struct MpiComm {
    _universe: Option<mpi::environment::Universe>,
    world: SimpleCommunicator,
}

impl MpiComm {
    /// Initializes MPI (once per process); `None` if it cannot be or already was.
    pub fn init() -> Option<Self> {
        let universe = mpi::initialize()?;
        let world = universe.world();
        Some(MpiComm {
            _universe: Some(universe),
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

    fn exchange(&self, outgoing: Vec<Vec<u8>>) -> Vec<Vec<u8>> {
        let size = self.size();
        assert_eq!(outgoing.len(), size, "one buffer per rank");
        let send_counts: Vec<u64> = outgoing.iter().map(|b| b.len() as u64).collect();
        let mut recv_counts = vec![0u64; size];
        self.world
            .all_to_all_into(&send_counts[..], &mut recv_counts[..]);
        // A round's displacements are MPI ints too: all pieces of a round stay below 2^31.
        let chunk = EXCHANGE_CHUNK.min(Count::MAX as usize / size) as u64;
        // Every receive count is some rank's send count: the largest send fixes the rounds.
        let largest = send_counts.iter().copied().max().unwrap_or(0);
        let rounds = self.max_u64(largest.div_ceil(chunk));
        let mut incoming: Vec<Vec<u8>> = recv_counts
            .iter()
            .map(|&c| Vec::with_capacity(c as usize))
            .collect();
        let piece = |total: u64, round: u64| -> usize {
            let start = round * chunk;
            total.saturating_sub(start).min(chunk) as usize
        };
        for round in 0..rounds {
            let start = (round * chunk) as usize;
            let send_sizes: Vec<usize> = send_counts.iter().map(|&c| piece(c, round)).collect();
            let recv_sizes: Vec<usize> = recv_counts.iter().map(|&c| piece(c, round)).collect();
            // One spare byte in each buffer: two empty vectors share one dangling address, and
            // Open MPI refuses a send buffer equal to the receive buffer.
            let mut send = Vec::with_capacity(send_sizes.iter().sum::<usize>() + 1);
            for (buffer, &len) in outgoing.iter().zip(&send_sizes) {
                send.extend_from_slice(&buffer[start.min(buffer.len())..][..len]);
            }
            send.push(0);
            let mut recv = vec![0u8; recv_sizes.iter().sum::<usize>() + 1];
            let (send_counts_i, send_displs) = counts_and_displacements(&send_sizes);
            let (recv_counts_i, recv_displs) = counts_and_displacements(&recv_sizes);
            {
                let send_part = Partition::new(&send[..], send_counts_i, &send_displs[..]);
                let mut recv_part =
                    PartitionMut::new(&mut recv[..], recv_counts_i, &recv_displs[..]);
                self.world
                    .all_to_all_varcount_into(&send_part, &mut recv_part);
            }
            let mut at = 0;
            for (buffer, &len) in incoming.iter_mut().zip(&recv_sizes) {
                buffer.extend_from_slice(&recv[at..at + len]);
                at += len;
            }
        }
        incoming
    }

    fn split(&self, color: usize) -> Box<dyn Comm> {
        let group = self
            .world
            .split_by_color(Color::with_value(color as i32))
            .expect("a defined colour always yields a communicator");
        Box::new(MpiComm {
            _universe: None,
            world: group,
        })
    }
}

/// MPI counts and displacements of consecutive pieces of the given sizes (each below 2^31).
fn counts_and_displacements(sizes: &[usize]) -> (Vec<Count>, Vec<Count>) {
    let counts: Vec<Count> = sizes.iter().map(|&s| s as Count).collect();
    let mut displs = Vec::with_capacity(sizes.len());
    let mut at: Count = 0;
    for &c in &counts {
        displs.push(at);
        at += c;
    }
    (counts, displs)
}

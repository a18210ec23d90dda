//! The MPI implementation of [`Comm`] (cargo feature `mpi`, over the system's MPI library
//! through the `mpi` crate).
//!
//! One MPI call moves at most 2^31 - 1 elements, and very large messages were slow: sums go in
//! chunks of [`CHUNK`] values per rank, exchanges in rounds of at most [`EXCHANGE_CHUNK`] bytes
//! per pair of ranks. A large sum is a reduce-scatter and an all-gather built on the exchange:
//! each rank adds one part of the values in rank order, so the result does not depend on the
//! library's choice of reduction order, and no rank moves more than about twice the values. A
//! small one (histograms, energy sums) is gathered to rank 0, added there in rank order and
//! broadcast: fewer messages. Both add in the same order, so they give the same bits.

use super::Comm;
use mpi::collective::CommunicatorCollectives;
use mpi::datatype::{Partition, PartitionMut};
use mpi::topology::{Color, Communicator, SimpleCommunicator};
use mpi::traits::Root;
use mpi::Count;

/// Values per collective call (8 MiB of f64 per rank).
pub const CHUNK: usize = 1 << 20;

/// Sums whose gathered values (`len * size`) stay below this go through rank 0.
pub const GATHER_LIMIT: usize = 1 << 20;

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

impl MpiComm {
    /// A small sum: gathered to rank 0, added there in rank order, broadcast back (a tree of
    /// messages, where an all-to-all would send `size - 1` messages from every rank).
    fn sum_through_root(&self, values: &mut [f64]) {
        let size = self.size();
        let root = self.world.process_at_rank(0);
        if self.rank() == 0 {
            let mut gathered = vec![0f64; values.len() * size];
            root.gather_into_root(&*values, &mut gathered[..]);
            let len = values.len();
            for (k, v) in values.iter_mut().enumerate() {
                let mut sum = gathered[k];
                for r in 1..size {
                    sum += gathered[r * len + k];
                }
                *v = sum;
            }
        } else {
            root.gather_into(&*values);
        }
        root.broadcast_into(values);
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
        if values.len() * size <= GATHER_LIMIT {
            self.sum_through_root(values);
            return;
        }
        // A reduce-scatter then an all-gather, both as exchanges: every rank adds up one part of
        // the values, in rank order, so each rank moves about twice its values whatever the
        // rank count (a sum gathered on one rank would move `size` times that through it).
        // Chunks of `CHUNK` values per part bound the buffers.
        for chunk in values.chunks_mut(CHUNK * size) {
            let len = chunk.len();
            let part = |r: usize| len * r / size..len * (r + 1) / size;
            let outgoing = (0..size).map(|r| to_bytes(&chunk[part(r)])).collect();
            let incoming = self.exchange(outgoing);
            let mut sum = from_bytes(&incoming[0]);
            for bytes in &incoming[1..] {
                for (s, v) in sum.iter_mut().zip(from_bytes(bytes)) {
                    *s += v;
                }
            }
            let gathered = self.exchange(vec![to_bytes(&sum); size]);
            for (r, bytes) in gathered.iter().enumerate() {
                chunk[part(r)].copy_from_slice(&from_bytes(bytes));
            }
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

    fn wait_quietly(&self) {
        if self.size() == 1 {
            return;
        }
        // A millisecond between tests: far below the seconds such waits last, and far above
        // what a test costs.
        let mut barrier = self.world.immediate_barrier();
        loop {
            match barrier.test() {
                Ok(_) => return,
                Err(pending) => barrier = pending,
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
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

fn to_bytes(values: &[f64]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn from_bytes(bytes: &[u8]) -> Vec<f64> {
    bytes
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes")))
        .collect()
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

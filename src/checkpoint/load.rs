//! Reading a checkpoint to resume from: checked against the run, read by rank 0 and shared with
//! every rank (its partial sums dealt to the ranks that wrote them).

use super::*;

/// Refuses a checkpoint of another run (see [`Identity`]) or one the solve cannot go on from.
pub fn check(
    path: &Path,
    header: &Header,
    this: &Identity,
    max_iterations: usize,
) -> Result<(), CheckpointError> {
    if let Some(what) = header.identity.mismatch(this) {
        return Err(CheckpointError::Bad {
            path: path.to_path_buf(),
            what: format!(
                "this checkpoint belongs to another run: {what}; solve with that run's options, \
                 or remove the checkpoint (or give another --out) to start afresh"
            ),
        });
    }
    // A position is a count of one rank's directions, never all of them (that is the next
    // boundary): more is damage that a checksum cannot see (a file written so).
    if header
        .state
        .within
        .is_some_and(|done| done >= this.directions as u64)
    {
        return Err(CheckpointError::Bad {
            path: path.to_path_buf(),
            what: format!(
                "damaged checkpoint: {} directions into an iteration of {}",
                header.state.within.unwrap_or(0),
                this.directions
            ),
        });
    }
    if header.state.iteration >= max_iterations as u64 {
        return Err(CheckpointError::Bad {
            path: path.to_path_buf(),
            what: format!(
                "the checkpoint is at iteration {}, and this run stops at {max_iterations}; \
                 give a larger --iterations to go on from it",
                header.state.iteration
            ),
        });
    }
    Ok(())
}

/// A checkpoint held in memory (the in-memory solver).
#[derive(Clone, Debug)]
pub struct Loaded {
    pub path: PathBuf,
    pub state: State,
    pub radiosity: Vec<Radiosity>,
    /// The radiosity before the last iteration's, while the Chebyshev semi-iteration runs.
    pub older: Option<Vec<Radiosity>>,
    /// In mid-iteration, written by as many ranks as this run has: this rank's partial sums.
    pub partial: Option<Vec<Gathered>>,
}

impl Loaded {
    /// The mid-iteration position and this rank's sums to continue from, or `None` (and, if the
    /// checkpoint is a mid-iteration one, a log line saying that its iteration starts again)
    /// when the layout of its sums (`data_groups`, see [`State::data_groups`]) or the rank
    /// count differs from this solve's.
    pub fn take_within(&mut self, data_groups: u32, ranks: usize) -> Option<(u64, Vec<Gathered>)> {
        let done = self.state.within?;
        let partial = self.partial.take();
        let layout = |groups: u32| match groups {
            0 => "by directions".to_string(),
            1 => "in the data mode".to_string(),
            g => format!("in the hybrid mode with {g} groups"),
        };
        match partial {
            Some(acc)
                if self.state.data_groups == data_groups && self.state.ranks as usize == ranks =>
            {
                Some((done, acc))
            }
            _ => {
                tracing::info!(
                    "the checkpoint is {done} directions into iteration {} (written by {} \
                     rank(s) distributed {}); this solve ({ranks} rank(s) distributed {}) \
                     cannot continue inside it, so that iteration starts from its beginning",
                    self.state.iteration + 1,
                    self.state.ranks,
                    layout(self.state.data_groups),
                    layout(data_groups),
                );
                None
            }
        }
    }
}

/// Reads the checkpoint at `path` on rank 0 and hands it to every rank of `comm` (the ranks need
/// not share a file system), checked against `this`; `None` if rank 0 has no checkpoint there.
/// Every rank returns the same outcome, so none is left waiting in a collective call.
pub fn load_shared(
    comm: &dyn Comm,
    path: &Path,
    this: &Identity,
    max_iterations: usize,
) -> Result<Option<Loaded>, CheckpointError> {
    // Rank 0 reads: 0 no checkpoint, 1 read, 2 failed (its error kept for its own message).
    let mut bytes = Vec::new();
    let mut failure = None;
    let mut status = 0u64;
    if comm.rank() == 0 && path.exists() {
        match std::fs::read(path) {
            Ok(b) => {
                bytes = b;
                status = 1;
            }
            Err(source) => {
                failure = Some(CheckpointError::Io {
                    path: path.to_path_buf(),
                    action: "read",
                    source,
                });
                status = 2;
            }
        }
    }
    match comm.max_u64(status) {
        0 => return Ok(None),
        2 => {
            return Err(failure.unwrap_or_else(|| {
                let_rank_0_speak_first();
                CheckpointError::Bad {
                    path: path.to_path_buf(),
                    what: "rank 0 could not read it (see rank 0's message)".to_string(),
                }
            }))
        }
        _ => {}
    }
    let parsed = if comm.size() == 1 {
        file::parse(path, &bytes, 0)?
    } else {
        share(comm, path, bytes)?
    };
    check(path, &parsed.header, this, max_iterations)?;
    let steps = (this.directions as u64).div_ceil(comm.size() as u64);
    // (The data and hybrid modes check their own positions: their steps are per group.)
    if let Some(done) = parsed.header.state.within {
        let by_directions = parsed.header.state.data_groups == 0;
        if by_directions && parsed.header.state.ranks as usize == comm.size() && done >= steps {
            return Err(CheckpointError::Bad {
                path: path.to_path_buf(),
                what: format!(
                    "damaged checkpoint: {done} directions per rank into an iteration of \
                     {steps} for {} ranks",
                    comm.size()
                ),
            });
        }
    }
    Ok(Some(Loaded {
        path: path.to_path_buf(),
        state: parsed.header.state,
        radiosity: parsed.radiosity,
        older: parsed.older,
        partial: parsed.partial,
    }))
}

/// The checkpoint file `bytes` read on rank 0, checked there whole (every checksum), then
/// handed out: its header and radiosity to every rank (which checks the header's own checksum
/// again), and each rank's partial sums to that rank only, in pieces of [`GATHER_PIECE`]
/// surfels; so a rank holds the radiosity and its own sums, whatever the rank count. Every rank
/// returns the same verdict.
pub(super) fn share(
    comm: &dyn Comm,
    path: &Path,
    bytes: Vec<u8>,
) -> Result<file::Parsed, CheckpointError> {
    let mut own = None;
    let mut failure = None;
    let mut head = Vec::new();
    if comm.rank() == 0 {
        match file::parse(path, &bytes, 0) {
            Ok(parsed) => {
                head = file::head(&bytes, &parsed.header).to_vec();
                own = Some(parsed);
            }
            Err(e) => failure = Some(e),
        }
    }
    if comm.max_u64(failure.is_some() as u64) == 1 {
        return Err(failure.unwrap_or_else(|| {
            let_rank_0_speak_first();
            CheckpointError::Bad {
                path: path.to_path_buf(),
                what: "rank 0 refused it (see rank 0's message)".to_string(),
            }
        }));
    }
    let head = broadcast_bytes(comm, head);
    let mut parsed = match own {
        Some(parsed) => parsed,
        None => file::parse_head(path, &head)?,
    };
    drop(head);
    let surfels = parsed.header.identity.surfels as usize;
    if parsed.header.partial_ranks() as usize != comm.size() {
        // Sums of another rank count are of no use here (the iteration starts again).
        parsed.partial = None;
        return Ok(parsed);
    }
    let sums = file::sums(&bytes, &parsed.header);
    let pieces = surfels.div_ceil(GATHER_PIECE);
    let mut mine = Vec::with_capacity(if comm.rank() > 0 { surfels } else { 0 });
    for to in 1..comm.size() {
        for piece in 0..pieces {
            let first = piece * GATHER_PIECE;
            let len = GATHER_PIECE.min(surfels - first);
            let mut outgoing = vec![Vec::new(); comm.size()];
            if comm.rank() == 0 {
                let at = (to * surfels + first) * file::PARTIAL_LEN;
                outgoing[to] = sums[at..at + len * file::PARTIAL_LEN].to_vec();
            }
            let incoming = comm.exchange(outgoing).swap_remove(0);
            if comm.rank() == to {
                if incoming.len() != len * file::PARTIAL_LEN {
                    return Err(CheckpointError::Bad {
                        path: path.to_path_buf(),
                        what: "rank 0 sent partial sums of the wrong length".to_string(),
                    });
                }
                mine.extend(
                    incoming
                        .chunks_exact(file::PARTIAL_LEN)
                        .map(file::decode_gathered),
                );
            }
        }
    }
    if comm.rank() > 0 {
        parsed.partial = Some(mine);
    }
    Ok(parsed)
}

/// Rank 0's `bytes` on every rank, through the solver's only collectives (`max_u64` and the sum
/// in rank order): four bytes per f64, whole numbers that a sum with zeros keeps exactly.
/// Waits a moment on a rank that learned that rank 0 refused a checkpoint, before it fails too.
/// The launcher ends the whole job when the first rank exits with an error: had this rank
/// exited at once, rank 0 could be killed before it printed why, and the user would read only
/// "see rank 0's message" (seen under load in the MPI tests).
pub(crate) fn let_rank_0_speak_first() {
    std::thread::sleep(std::time::Duration::from_secs(2));
}

pub(super) fn broadcast_bytes(comm: &dyn Comm, bytes: Vec<u8>) -> Vec<u8> {
    let len = comm.max_u64(bytes.len() as u64) as usize;
    let mut words = vec![0f64; len.div_ceil(4)];
    if comm.rank() == 0 {
        for (w, chunk) in words.iter_mut().zip(bytes.chunks(4)) {
            let mut b = [0u8; 4];
            b[..chunk.len()].copy_from_slice(chunk);
            *w = u32::from_le_bytes(b) as f64;
        }
    }
    drop(bytes);
    comm.sum_in_place(&mut words);
    let mut out = Vec::with_capacity(words.len() * 4);
    for w in words {
        out.extend_from_slice(&(w as u32).to_le_bytes());
    }
    out.truncate(len);
    out
}

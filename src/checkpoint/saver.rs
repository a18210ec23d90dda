//! When and how checkpoints are written: on a clock, at iteration boundaries and inside
//! iterations, by the one process that writes, after the ranks agree.

use super::*;

/// When and where a solve writes its checkpoints.
pub struct Saver {
    path: PathBuf,
    identity: Identity,
    /// Only one process writes (rank 0 under MPI); the others keep the bookkeeping only.
    writes: bool,
    /// Least time between two checkpoints (zero: at every iteration).
    every: Duration,
    last: Instant,
    /// How long the last checkpoint took to write (it spaces the mid-iteration ones).
    last_write: Duration,
    /// The checkpoint on disk for this run, if any: its iteration and mid-iteration position.
    saved: Option<(u64, Option<u64>)>,
    ranks: u32,
    /// Whether checkpoints are also written between two directions (see [`Saver::within`]).
    within: bool,
    /// See [`WRITE_TIME_FACTOR`].
    write_factor: u32,
}

/// A mid-iteration checkpoint is due only once the time since the last one is this many times
/// what that one took to write: so checkpoints inside iterations take at most about a
/// twentieth of the solve at the default interval. With a factor of 4 a scene of 13 million
/// surfels out of core spent 12 % of its first iteration writing them (a 1.6 GB checkpoint
/// took 8 s to write, one a minute).
pub const WRITE_TIME_FACTOR: u32 = 19;

/// The factor where `--checkpoint-every` is given: an interval asked for is kept as far as a
/// fifth of the solve.
pub const ASKED_WRITE_TIME_FACTOR: u32 = 4;

/// Surfels of partial sums gathered to rank 0 per exchange (3 MiB): the memory a mid-iteration
/// checkpoint needs beyond the solver's own, on every rank.
pub(super) const GATHER_PIECE: usize = 1 << 16;

impl Saver {
    /// A saver for `out`'s checkpoint; `resumed` is the iteration of the checkpoint this run
    /// started from.
    pub fn new(
        out: &Path,
        identity: Identity,
        writes: bool,
        every: Duration,
        ranks: usize,
        resumed: Option<u64>,
    ) -> Self {
        Saver {
            path: path_in(out),
            identity,
            writes,
            every,
            last: Instant::now(),
            last_write: Duration::ZERO,
            saved: resumed.map(|i| (i, None)),
            ranks: ranks as u32,
            within: false,
            write_factor: WRITE_TIME_FACTOR,
        }
    }

    /// Spaces the mid-iteration checkpoints by `factor` times the last one's writing time
    /// instead of [`WRITE_TIME_FACTOR`].
    pub fn write_factor(mut self, factor: u32) -> Self {
        self.write_factor = factor;
        self
    }

    /// Also writes checkpoints inside iterations, between two directions (or steps).
    pub fn within(mut self, on: bool) -> Self {
        self.within = on;
        self
    }

    /// Whether this saver writes mid-iteration checkpoints.
    pub fn saves_within(&self) -> bool {
        self.within
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether the time since the last checkpoint calls for another.
    pub fn due(&self) -> bool {
        self.last.elapsed() >= self.every
    }

    /// Whether a checkpoint is due between two directions: as [`Saver::due`], and no sooner than
    /// [`WRITE_TIME_FACTOR`] (or [`Saver::write_factor`]) times the last one's writing time.
    pub fn due_within(&self) -> bool {
        self.within && self.last.elapsed() >= self.every.max(self.last_write * self.write_factor)
    }

    /// What every rank of `comm` does between two directions: agrees on the stop signal any
    /// rank received (`signal`, 0 for none) and on whether rank 0 finds a checkpoint due. One
    /// `max_u64` (a stop signal outranks the due flag; a stop saves anyway). Returns the signal
    /// (0 for none) and whether to save.
    pub fn agree_within(&self, comm: &dyn Comm, signal: i32) -> (i32, bool) {
        let due = comm.rank() == 0 && self.due_within();
        let agreed = comm.max_u64(((signal.max(0) as u64) << 1) | due as u64);
        let signal = (agreed >> 1) as i32;
        (signal, signal != 0 || agreed & 1 == 1)
    }

    /// The state to save after `iteration` iterations.
    pub fn state(
        &self,
        iteration: usize,
        previous_change: Option<f64>,
        extrapolation: impl Into<ExtrapolationState>,
    ) -> State {
        State {
            iteration: iteration as u64,
            ranks: self.ranks,
            previous_change,
            extrapolation: extrapolation.into(),
            within: None,
            data_groups: 0,
            axis_in_progress: false,
            sums_in_f32: false,
            walked_forwards: false,
        }
    }

    /// Writes a checkpoint of `state` whose payload `fill` writes (`buffer_bytes` of write
    /// buffer). A failure keeps the earlier checkpoint and is returned for the caller to report.
    pub fn save(
        &mut self,
        state: State,
        buffer_bytes: usize,
        fill: impl FnOnce(&mut dyn std::io::Write) -> std::io::Result<()>,
    ) -> Result<(), CheckpointError> {
        let at = (state.iteration, state.within);
        let t = Instant::now();
        if self.writes {
            let header = Header {
                identity: self.identity.clone(),
                state,
            };
            file::write(&self.path, &header, buffer_bytes, fill)?;
            tracing::info!(
                iteration = at.0,
                within = at.1.unwrap_or(0),
                seconds = format!("{:.3}", t.elapsed().as_secs_f64()),
                path = %self.path.display(),
                "checkpoint written"
            );
        }
        self.saved = Some(at);
        self.last_write = t.elapsed();
        self.last = Instant::now();
        Ok(())
    }

    /// [`Saver::save`] of radiosity held in memory; `older`, the radiosity before the last
    /// iteration's, is written while the state's Chebyshev semi-iteration runs (and must be
    /// given then).
    pub fn save_memory(
        &mut self,
        state: State,
        radiosity: &[Radiosity],
        older: Option<&[Radiosity]>,
    ) -> Result<(), CheckpointError> {
        let older = kept_older(&state, older);
        self.save(state, 1 << 20, |w| {
            write_radiosity(w, radiosity)?;
            older.map_or(Ok(()), |o| write_radiosity(w, o))
        })
    }

    /// A mid-iteration checkpoint, `done` directions into iteration `state.iteration + 1`:
    /// the radiosity the iteration gathers from and every rank's partial sums `acc`, gathered
    /// to rank 0 in pieces of [`GATHER_PIECE`] surfels. Every rank of `comm` must call it (the
    /// same number of exchanges happens on every rank, whatever rank 0's writing meets).
    pub fn save_within(
        &mut self,
        comm: &dyn Comm,
        mut state: State,
        done: u64,
        (radiosity, older): (&[Radiosity], Option<&[Radiosity]>),
        acc: &[Gathered],
    ) -> Result<(), CheckpointError> {
        state.within = Some(done);
        let older = kept_older(&state, older);
        let pieces = acc.len().div_ceil(GATHER_PIECE);
        let exchanges = (comm.size() - 1) * pieces;
        let made = std::cell::Cell::new(0usize);
        // The `made`-th exchange: rank `1 + made / pieces` sends piece `made % pieces` of its
        // sums to rank 0, which gets them back (the others get nothing).
        let exchange = || {
            let k = made.get();
            made.set(k + 1);
            let (from, piece) = (1 + k / pieces, k % pieces);
            let mut outgoing = vec![Vec::new(); comm.size()];
            if comm.rank() == from {
                outgoing[0] = encode_sums(
                    &acc[piece * GATHER_PIECE..]
                        [..GATHER_PIECE.min(acc.len() - piece * GATHER_PIECE)],
                );
            }
            comm.exchange(outgoing).swap_remove(from)
        };
        let result = self.save(state, 1 << 20, |w| {
            write_radiosity(w, radiosity)?;
            if let Some(o) = older {
                write_radiosity(w, o)?;
            }
            w.write_all(&encode_sums(acc))?;
            while made.get() < exchanges {
                w.write_all(&exchange())?;
            }
            Ok(())
        });
        // Rank 0's writing may have stopped short (or, on the other ranks, never started):
        // the exchanges left are made all the same, so that no rank waits for another.
        while made.get() < exchanges {
            exchange();
        }
        result
    }

    /// Counts `took` (a whole save, with the gathering the caller did before [`Saver::save`]) as
    /// the last checkpoint's writing time, when longer, for the spacing of the next ones.
    pub fn took(&mut self, took: Duration) {
        self.last_write = self.last_write.max(took);
    }

    /// At a boundary the solve goes on from: saves if due, and on failure warns and goes on
    /// (the earlier checkpoint stays; losing the solve for a checkpoint would be worse).
    pub fn save_if_due(
        &mut self,
        state: impl FnOnce(&Self) -> State,
        save: impl FnOnce(&mut Self, State) -> Result<(), CheckpointError>,
    ) {
        if !self.due() {
            return;
        }
        let state = state(self);
        let result = save(self, state);
        self.warn_on_failure(result);
    }

    /// Warns of a checkpoint that could not be written; the solve goes on (the earlier
    /// checkpoint stays; losing the solve for a checkpoint would be worse).
    pub fn warn_on_failure(&mut self, result: Result<(), CheckpointError>) {
        if let Err(e) = result {
            tracing::warn!("checkpoint not written ({e}); the solve goes on");
            // Not again at once: the disk is full or failing.
            self.last = Instant::now();
        }
    }

    /// The interruption after `completed` iterations, saving that boundary first (`save`) unless
    /// the checkpoint on disk already holds it.
    pub fn interrupt(
        &mut self,
        signal: i32,
        completed: usize,
        save: impl FnOnce(&mut Self) -> Result<(), CheckpointError>,
    ) -> Interruption {
        self.interrupt_at(signal, completed, None, save)
    }

    /// The interruption after `completed` iterations and, `within`, that many directions of the
    /// next, saving that state first (`save`) unless the checkpoint on disk already holds it.
    pub fn interrupt_at(
        &mut self,
        signal: i32,
        completed: usize,
        within: Option<u64>,
        save: impl FnOnce(&mut Self) -> Result<(), CheckpointError>,
    ) -> Interruption {
        let mut failure = None;
        if self.saved != Some((completed as u64, within)) {
            if let Err(e) = save(self) {
                failure = Some(e.to_string());
            }
        }
        Interruption {
            signal,
            completed,
            within,
            checkpoint: self.saved.map(|(i, w)| (self.path.clone(), i, w)),
            failure,
            writer: self.writes,
        }
    }
}

/// Writes radiosity held in memory as a checkpoint's payload.
/// The older radiosity a checkpoint of `state` holds: `older` while its Chebyshev
/// semi-iteration runs, else none.
fn kept_older<'a>(state: &State, older: Option<&'a [Radiosity]>) -> Option<&'a [Radiosity]> {
    debug_assert!(
        state.extrapolation.chebyshev.is_none() || older.is_some(),
        "a checkpoint of a Chebyshev semi-iteration needs the older radiosity"
    );
    older.filter(|_| state.extrapolation.chebyshev.is_some())
}

pub(super) fn write_radiosity(
    w: &mut dyn std::io::Write,
    radiosity: &[Radiosity],
) -> std::io::Result<()> {
    let mut bytes = vec![0u8; file::RADIOSITY_LEN * 4096];
    for piece in radiosity.chunks(4096) {
        for (b, out) in piece
            .iter()
            .zip(bytes.chunks_exact_mut(file::RADIOSITY_LEN))
        {
            file::encode_radiosity(b, out);
        }
        w.write_all(&bytes[..piece.len() * file::RADIOSITY_LEN])?;
    }
    Ok(())
}

/// Partial sums as a checkpoint stores them.
pub(super) fn encode_sums(acc: &[Gathered]) -> Vec<u8> {
    let mut bytes = vec![0u8; acc.len() * file::PARTIAL_LEN];
    for (g, out) in acc.iter().zip(bytes.chunks_exact_mut(file::PARTIAL_LEN)) {
        file::encode_gathered(g, out);
    }
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A saver whose last checkpoint took `took` to write, just now.
    fn saver_after(dir: &Path, took: Duration, factor: Option<u32>) -> Saver {
        let set = crate::voxel::voxelize::voxelize(
            &crate::gen::furnace(1.0, 0.5),
            crate::voxel::voxelize::GridSpec::Resolution(4),
        )
        .unwrap();
        let directions = crate::geometry::directions::DirectionSet::with_count(13);
        let identity = Identity::in_memory(&set, &directions, 1, false);
        let saver = Saver::new(dir, identity, true, Duration::ZERO, 1, None).within(true);
        let mut saver = match factor {
            Some(f) => saver.write_factor(f),
            None => saver,
        };
        saver.took(took);
        saver
    }

    #[test]
    fn checkpoints_inside_iterations_wait_for_their_share_of_the_time() {
        let dir = tempfile::tempdir().unwrap();
        let took = Duration::from_millis(10);
        let default = saver_after(dir.path(), took, None);
        let asked = saver_after(dir.path(), took, Some(ASKED_WRITE_TIME_FACTOR));
        assert!(!default.due_within() && !asked.due_within());
        // 60 ms on: past 4 times the writing time, short of 19 times.
        std::thread::sleep(Duration::from_millis(60));
        assert!(
            asked.due_within(),
            "an asked interval is kept to a fifth of the time"
        );
        assert!(!default.due_within(), "the default keeps to a twentieth");
        assert!(
            default.due(),
            "at iteration boundaries the interval alone counts"
        );
    }
}

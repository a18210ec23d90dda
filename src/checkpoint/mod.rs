//! Checkpoints: the state of a solve at an iteration boundary, kept in `OUT/checkpoint.bin`, from
//! which `voxrad solve ... --resume` continues with exactly the bits an uninterrupted run would
//! have produced.
//!
//! What makes the continuation bit-identical: the solvers' next iteration is a pure function of
//! the radiosity after the last one (stored as the f32 values the solver itself keeps), the
//! stopping rule's last relative change (`jacobi::Convergence`) and the extrapolation's history
//! of change norms (`accelerate::Extrapolation`); the gathering order within an iteration is
//! fixed (directions in set order, sums across ranks in rank order), so it does not need saving.
//! A checkpoint is written only at a boundary the solve goes on from (never for the iteration it
//! stops at), so a resumed solve always runs at least one iteration and its last gather (the
//! energy balance) is its own.
//!
//! **Inside an iteration** (the in-memory solver, one process or `--distribute directions`):
//! between two directions the state is the radiosity of the last completed iteration, how many
//! directions of the next one are done, and the light gathered from them (`acc`, f64 exactly as
//! held, one array per rank, since each rank gathers its own directions and the arrays are added
//! in rank order at the end of the iteration). Continuing from that direction with those sums
//! gives the uninterrupted run's bits. Such a checkpoint is written when one is due between two
//! directions (see [`Saver::due_within`]) and on a stop signal in mid-iteration; under MPI the
//! ranks agree between directions on whether to write one ([`Saver::agree_within`]), and rank 0
//! gathers the other ranks' sums in bounded pieces ([`Saver::save_within`]). The data and
//! hybrid modes (`distribute::data`) write the same layout between two steps, each rank's array
//! holding the light of the surfels it holds, by id ([`State::data_groups`] says which layout a
//! file has). A resume on another rank count or layout starts that iteration from its beginning
//! (the radiosity it starts from is in the file) and says so. The out-of-core solver writes the
//! same layout between two main axes, with its canonical sum as the one rank's
//! (`outcore::solver`).
//!
//! A checkpoint names the run it belongs to ([`Identity`]: solver, grid, surfels, directions,
//! channels, extrapolation, and a checksum of the voxelized scene or of the shard set): one from
//! another run is refused with what differs, never used. The tolerance, the iteration limit and
//! the thread count are not part of it: they do not change the iterations already made (so a
//! stopped solve can be resumed with a higher `--iterations`).
//!
//! `file` owns the byte layout; this module owns what goes in it, when it is written
//! ([`Saver`]), the message of an interrupted run ([`Interruption`]), and handing a checkpoint
//! read on rank 0 to every rank ([`load_shared`]).

pub mod file;

pub use file::{CheckpointFile, Gathered, Radiosity};

use crate::comm::Comm;
use crate::geometry::directions::DirectionSet;
use crate::scene::Material;
use crate::voxel::{Grid, Surfel, SurfelSet};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The checkpoint's name inside the out directory.
pub const FILE_NAME: &str = "checkpoint.bin";

/// Prefixes of the work directories a solve makes inside its out directory (removed when it
/// ends, but left behind by a process that was killed).
pub const WORK_DIR_PREFIXES: [&str; 3] = [".voxrad-work-", ".voxrad-shards-", ".voxrad-new-"];

/// The checkpoint path of the out directory `out`.
pub fn path_in(out: &Path) -> PathBuf {
    out.join(FILE_NAME)
}

/// Which solver wrote a checkpoint (their surfel orders differ).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Solver {
    InMemory = 1,
    OutOfCore = 2,
}

impl Solver {
    fn name(self) -> &'static str {
        match self {
            Solver::InMemory => "the in-memory solver",
            Solver::OutOfCore => "the out-of-core solver (a shard set or --memory)",
        }
    }
}

/// What a checkpoint must match to be continued from.
#[derive(Clone, Debug, PartialEq)]
pub struct Identity {
    pub solver: Solver,
    pub surfels: u64,
    pub dims: [u32; 3],
    pub voxel_size: f64,
    pub directions: u32,
    /// CRC-32 of the direction vectors and their solid angles.
    pub directions_checksum: u32,
    /// Channels solved (1 for a grey scene solved once, else 3).
    pub channels: u32,
    /// Tail extrapolation on.
    pub accelerate: bool,
    /// CRC-32 of the voxelized scene (see [`scene_checksum`]) or of the shard set.
    pub scene_checksum: u32,
}

impl Identity {
    /// The identity of an in-memory solve of `set` over `directions`.
    pub fn in_memory(
        set: &SurfelSet,
        directions: &DirectionSet,
        channels: usize,
        accelerate: bool,
    ) -> Self {
        Identity {
            solver: Solver::InMemory,
            surfels: set.surfels.len() as u64,
            dims: set.grid.dims,
            voxel_size: set.grid.voxel_size,
            directions: directions.len() as u32,
            directions_checksum: directions_checksum(directions),
            channels: channels as u32,
            accelerate,
            scene_checksum: scene_checksum(&set.grid, &set.normals, &set.materials, |h| {
                set.surfels.iter().for_each(|s| hash_surfel(h, s))
            }),
        }
    }

    /// The identity of a solve that also runs the direct-light pass over `dense` (see
    /// `solve::direct`): its direct light changes every iteration's answer, so its direction set
    /// joins the directions' checksum.
    pub fn with_direct_pass(mut self, dense: Option<&DirectionSet>) -> Self {
        if let Some(dense) = dense {
            let mut h = crc32fast::Hasher::new();
            h.update(&self.directions_checksum.to_le_bytes());
            h.update(b"direct");
            h.update(&directions_checksum(dense).to_le_bytes());
            self.directions_checksum = h.finalize();
        }
        self
    }

    /// How `self` (the checkpoint's) differs from `this` (the run's), in words.
    fn mismatch(&self, this: &Identity) -> Option<String> {
        if self.solver != this.solver {
            return Some(format!(
                "it was written by {}, and this run uses {}",
                self.solver.name(),
                this.solver.name()
            ));
        }
        if self.dims != this.dims || self.voxel_size != this.voxel_size {
            let [a, b, c] = self.dims;
            let [x, y, z] = this.dims;
            return Some(format!(
                "it is for a grid of {a} x {b} x {c} voxels of {}, and this run's is {x} x {y} x \
                 {z} voxels of {} (another --resolution or --voxel-size?)",
                self.voxel_size, this.voxel_size
            ));
        }
        if self.directions != this.directions {
            return Some(format!(
                "it is for {} directions, and this run uses {} (another --directions or \
                 --quality?)",
                self.directions, this.directions
            ));
        }
        if self.directions_checksum != this.directions_checksum {
            return Some(format!(
                "it is for {} directions but another direction set or direct-light pass \
                 (another --direct-directions or --quality?)",
                self.directions
            ));
        }
        if self.surfels != this.surfels || self.scene_checksum != this.scene_checksum {
            return Some(format!(
                "it is for another scene ({} surfels, checksum {:#010x}; this run: {} surfels, \
                 checksum {:#010x})",
                self.surfels, self.scene_checksum, this.surfels, this.scene_checksum
            ));
        }
        if self.channels != this.channels || self.accelerate != this.accelerate {
            return Some(format!(
                "it was made with {} channel(s) and extrapolation {}, and this run has {} and {} \
                 (another --quality, --iterations or --tolerance?)",
                self.channels,
                if self.accelerate { "on" } else { "off" },
                this.channels,
                if this.accelerate { "on" } else { "off" }
            ));
        }
        None
    }
}

/// CRC-32 of a direction set: the integer vectors and the solid angles' bits.
pub fn directions_checksum(directions: &DirectionSet) -> u32 {
    let mut h = crc32fast::Hasher::new();
    for d in &directions.directions {
        for v in d.vector {
            h.update(&v.to_le_bytes());
        }
        h.update(&d.solid_angle.to_bits().to_le_bytes());
    }
    h.finalize()
}

/// CRC-32 of everything of a voxelized scene that the radiosity depends on: the grid, the
/// normal table, the materials, and every surfel (fed by `surfels`, in solver order).
pub fn scene_checksum(
    grid: &Grid,
    normals: &[[f32; 3]],
    materials: &[Material],
    surfels: impl FnOnce(&mut crc32fast::Hasher),
) -> u32 {
    let mut h = crc32fast::Hasher::new();
    for o in grid.origin {
        h.update(&o.to_bits().to_le_bytes());
    }
    h.update(&grid.voxel_size.to_bits().to_le_bytes());
    for d in grid.dims {
        h.update(&d.to_le_bytes());
    }
    for n in normals.iter().flatten() {
        h.update(&n.to_bits().to_le_bytes());
    }
    for m in materials {
        for v in m.reflectance.iter().chain(&m.emission) {
            h.update(&v.to_bits().to_le_bytes());
        }
    }
    surfels(&mut h);
    h.finalize()
}

/// Feeds one surfel's fields to a scene checksum.
pub fn hash_surfel(h: &mut crc32fast::Hasher, s: &Surfel) {
    let mut b = [0u8; 80];
    let mut at = 0;
    let mut put = |w: [u8; 4]| {
        b[at..at + 4].copy_from_slice(&w);
        at += 4;
    };
    s.voxel.iter().for_each(|v| put(v.to_le_bytes()));
    s.point
        .iter()
        .chain(&s.normal)
        .chain(std::iter::once(&s.area))
        .chain(s.extent.iter().flatten())
        .for_each(|v| put(v.to_bits().to_le_bytes()));
    [s.normal_id, s.group, s.material[0], s.material[1]]
        .iter()
        .for_each(|v| put(v.to_le_bytes()));
    h.update(&b[..at]);
}

/// The solver's bookkeeping at an iteration boundary.
/// The tail extrapolation's whole state (`solve::accelerate::Extrapolation`): the change norms
/// since its last jump, its count of jumps and the ratio that allowed the last one. A resumed
/// solve must extrapolate exactly when the uninterrupted one would. Plain data here, so that the
/// checkpoints do not depend on the solver.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExtrapolationState {
    pub changes: Vec<f64>,
    pub count: usize,
    pub last_ratio: Option<f64>,
}

impl ExtrapolationState {
    /// The change norms, the count and the last ratio.
    pub fn parts(&self) -> (&[f64], usize, Option<f64>) {
        (&self.changes, self.count, self.last_ratio)
    }

    /// The state [`ExtrapolationState::parts`] gave.
    pub fn from_parts(changes: Vec<f64>, count: usize, last_ratio: Option<f64>) -> Self {
        ExtrapolationState {
            changes,
            count,
            last_ratio,
        }
    }
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct State {
    /// Iterations completed.
    pub iteration: u64,
    /// Ranks of the run that wrote it (a resume on another count is allowed; its sums across
    /// ranks are added in another grouping, so the last bits may differ).
    pub ranks: u32,
    /// The stopping rule's last relative change (`jacobi::Convergence`).
    pub previous_change: Option<f64>,
    pub extrapolation: ExtrapolationState,
    /// In mid-iteration: how many of this rank's directions (the same count on every rank, see
    /// `jacobi`) of iteration `iteration + 1` are gathered; the file then holds every rank's
    /// partial sums. `None` at an iteration boundary.
    pub within: Option<u64>,
    /// Whose partial sums a mid-iteration checkpoint holds. 0: each rank's light gathered from
    /// its own directions, for every surfel (one process, `--distribute directions`, out of
    /// core). `G` of 1 or more: the data mode (1) or the hybrid mode with `G` groups
    /// (`distribute::data`), each rank's light of the surfels it held at that direction, by
    /// surfel id (zero for the others); `within` then counts the steps of the group's
    /// directions. Only a run of the same layout and rank count continues inside the iteration.
    pub data_groups: u32,
}

/// Everything in a checkpoint but the radiosity.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    pub identity: Identity,
    pub state: State,
}

impl Header {
    /// Ranks whose partial sums the file holds (none at an iteration boundary).
    pub fn partial_ranks(&self) -> u32 {
        if self.state.within.is_some() {
            self.state.ranks
        } else {
            0
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// Damaged, of another format, or of another run: the user's to fix (exit status 2).
    #[error("{}: {what}", path.display())]
    Bad { path: PathBuf, what: String },
    #[error("cannot {action} {}: {source}", path.display())]
    Io {
        path: PathBuf,
        action: &'static str,
        #[source]
        source: std::io::Error,
    },
}

impl CheckpointError {
    pub fn is_bad_input(&self) -> bool {
        matches!(self, CheckpointError::Bad { .. })
    }
}

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
        partial: parsed.partial,
    }))
}

/// The checkpoint file `bytes` read on rank 0, checked there whole (every checksum), then
/// handed out: its header and radiosity to every rank (which checks the header's own checksum
/// again), and each rank's partial sums to that rank only, in pieces of [`GATHER_PIECE`]
/// surfels; so a rank holds the radiosity and its own sums, whatever the rank count. Every rank
/// returns the same verdict.
fn share(comm: &dyn Comm, path: &Path, bytes: Vec<u8>) -> Result<file::Parsed, CheckpointError> {
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

fn broadcast_bytes(comm: &dyn Comm, bytes: Vec<u8>) -> Vec<u8> {
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
}

/// A mid-iteration checkpoint is due only once the time since the last one is this many times
/// what that one took to write: so a short `--checkpoint-every` (zero included) never spends
/// more than about a fifth of the solve writing checkpoints inside iterations.
const WRITE_TIME_FACTOR: u32 = 4;

/// Surfels of partial sums gathered to rank 0 per exchange (3 MiB): the memory a mid-iteration
/// checkpoint needs beyond the solver's own, on every rank.
const GATHER_PIECE: usize = 1 << 16;

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
        }
    }

    /// Also writes checkpoints inside iterations, between two directions (or steps, or main
    /// axes out of core).
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
    /// [`WRITE_TIME_FACTOR`] times the last one's writing time.
    pub fn due_within(&self) -> bool {
        self.within && self.last.elapsed() >= self.every.max(self.last_write * WRITE_TIME_FACTOR)
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

    /// [`Saver::save`] of radiosity held in memory.
    pub fn save_memory(
        &mut self,
        state: State,
        radiosity: &[Radiosity],
    ) -> Result<(), CheckpointError> {
        self.save(state, 1 << 20, |w| write_radiosity(w, radiosity))
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
        radiosity: &[Radiosity],
        acc: &[Gathered],
    ) -> Result<(), CheckpointError> {
        state.within = Some(done);
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
fn write_radiosity(w: &mut dyn std::io::Write, radiosity: &[Radiosity]) -> std::io::Result<()> {
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
fn encode_sums(acc: &[Gathered]) -> Vec<u8> {
    let mut bytes = vec![0u8; acc.len() * file::PARTIAL_LEN];
    for (g, out) in acc.iter().zip(bytes.chunks_exact_mut(file::PARTIAL_LEN)) {
        file::encode_gathered(g, out);
    }
    bytes
}

/// A solve stopped by SIGTERM or SIGINT (exit status 3).
#[derive(Clone, Debug)]
pub struct Interruption {
    pub signal: i32,
    /// Iterations completed when it stopped.
    pub completed: usize,
    /// Directions of the next iteration gathered when it stopped (and saved), if it stopped
    /// inside an iteration and kept that.
    pub within: Option<u64>,
    /// The checkpoint to resume from, its iteration and its mid-iteration position.
    pub checkpoint: Option<(PathBuf, u64, Option<u64>)>,
    /// Why the checkpoint of the last completed iteration could not be written.
    pub failure: Option<String>,
    /// Whether this process wrote the checkpoints (rank 0).
    pub writer: bool,
}

impl Interruption {
    /// A stop with no checkpoint to point to (the solve keeps none); `writer` is whether this
    /// process speaks for the run (rank 0).
    pub fn without_checkpoint(signal: i32, completed: usize, writer: bool) -> Self {
        Interruption {
            signal,
            completed,
            within: None,
            checkpoint: None,
            failure: None,
            writer,
        }
    }
}

impl std::fmt::Display for Interruption {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let signal = crate::interrupt::name(self.signal);
        let when = match self.within {
            Some(done) => format!(
                "after iteration {} and {done} directions of the next",
                self.completed
            ),
            None => format!("after iteration {}", self.completed),
        };
        if !self.writer {
            return write!(
                f,
                "interrupted by {signal} {when}; rank 0 wrote the checkpoint"
            );
        }
        write!(f, "interrupted by {signal} {when}; ")?;
        if let Some(e) = &self.failure {
            write!(f, "its checkpoint could not be written ({e}); ")?;
        }
        match &self.checkpoint {
            Some((path, iteration, within)) => {
                write!(f, "checkpoint at {} (iteration {iteration}", path.display())?;
                if let Some(done) = within {
                    write!(f, ", {done} directions into the next")?;
                }
                write!(f, "); rerun with --resume to continue")
            }
            None => write!(f, "no checkpoint; rerun to start again"),
        }
    }
}

/// Removes what a killed solve left in `out`: work directories and a half-written checkpoint.
/// (A solve that ends, even by an error or a signal, removes its own.)
pub fn remove_leftovers(out: &Path) {
    let Ok(entries) = std::fs::read_dir(out) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name();
        let name = name.to_string_lossy();
        let is_dir = entry.file_type().is_ok_and(|t| t.is_dir());
        let result = if is_dir && WORK_DIR_PREFIXES.iter().any(|p| name.starts_with(p)) {
            std::fs::remove_dir_all(entry.path())
        } else if !is_dir && *name == *format!("{FILE_NAME}.partial") {
            std::fs::remove_file(entry.path())
        } else {
            continue;
        };
        match result {
            Ok(()) => tracing::info!(
                path = %entry.path().display(),
                "removed what an interrupted run left"
            ),
            Err(e) => tracing::warn!("cannot remove {}: {e}", entry.path().display()),
        }
    }
}

/// Removes the checkpoint of a finished solve (its outputs are written): a later `--resume` in
/// the same directory then starts afresh instead of redoing the last iterations.
pub fn remove_finished(out: &Path) {
    let path = path_in(out);
    match std::fs::remove_file(&path) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => tracing::warn!("cannot remove {}: {e}", path.display()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::comm::SingleProcess;

    #[test]
    fn a_checkpoint_of_another_run_is_refused_with_the_difference() {
        let set = crate::voxel::voxelize::voxelize(
            &crate::gen::furnace(1.0, 0.5),
            crate::voxel::voxelize::GridSpec::Resolution(6),
        )
        .unwrap();
        let directions = DirectionSet::with_count(13);
        let this = Identity::in_memory(&set, &directions, 3, false);
        let dir = tempfile::tempdir().unwrap();
        let mut saver = Saver::new(dir.path(), this.clone(), true, Duration::ZERO, 1, None);
        let state = saver.state(4, Some(0.5), ExtrapolationState::default());
        let radiosity = vec![[[1.0f32; 3]; 2]; set.surfels.len()];
        saver.save_memory(state.clone(), &radiosity).unwrap();
        let path = path_in(dir.path());
        let loaded = load_shared(&SingleProcess, &path, &this, 10)
            .unwrap()
            .unwrap();
        assert_eq!(loaded.state, state);
        assert_eq!(loaded.radiosity, radiosity);

        let other = Identity::in_memory(&set, &DirectionSet::with_count(49), 3, false);
        let err = load_shared(&SingleProcess, &path, &other, 10).unwrap_err();
        assert!(err.is_bad_input());
        let text = err.to_string();
        assert!(
            text.contains("checkpoint.bin") && text.contains("directions"),
            "{text}"
        );
        let grey = Identity::in_memory(&set, &directions, 1, false);
        let text = load_shared(&SingleProcess, &path, &grey, 10)
            .unwrap_err()
            .to_string();
        assert!(text.contains("channel"), "{text}");
        let text = load_shared(&SingleProcess, &path, &this, 4)
            .unwrap_err()
            .to_string();
        assert!(text.contains("--iterations"), "{text}");
        assert!(
            load_shared(&SingleProcess, &dir.path().join("none"), &this, 10)
                .unwrap()
                .is_none()
        );
    }

    #[test]
    fn a_mid_iteration_checkpoint_hands_back_its_sums_or_restarts_the_iteration() {
        let set = crate::voxel::voxelize::voxelize(
            &crate::gen::furnace(1.0, 0.5),
            crate::voxel::voxelize::GridSpec::Resolution(6),
        )
        .unwrap();
        let directions = DirectionSet::with_count(13);
        let this = Identity::in_memory(&set, &directions, 3, false);
        let dir = tempfile::tempdir().unwrap();
        let n = set.surfels.len();
        let mut saver =
            Saver::new(dir.path(), this.clone(), true, Duration::ZERO, 1, None).within(true);
        let radiosity = vec![[[0.5f32; 3]; 2]; n];
        let acc: Vec<Gathered> = (0..n)
            .map(|i| [[i as f64 / 7.0, 1e-310, 0.0], [3.0, 2.0, 1.0]])
            .collect();
        let state = saver.state(2, Some(0.25), ExtrapolationState::default());
        saver
            .save_within(&SingleProcess, state, 5, &radiosity, &acc)
            .unwrap();
        let path = path_in(dir.path());
        let mut loaded = load_shared(&SingleProcess, &path, &this, 10)
            .unwrap()
            .unwrap();
        assert_eq!((loaded.state.iteration, loaded.state.within), (2, Some(5)));
        let mut other = loaded.clone();
        let (done, sums) = loaded.take_within(0, 1).unwrap();
        assert_eq!(done, 5);
        let bits = |v: &[Gathered]| -> Vec<u64> {
            v.iter().flatten().flatten().map(|x| x.to_bits()).collect()
        };
        assert_eq!(bits(&sums), bits(&acc));
        // Another rank count or a mode that cannot use them: the iteration starts again.
        // The sums of the hybrid mode's layout (2 groups) continue only in that layout.
        let mut hybrid = other.clone();
        hybrid.state.data_groups = 2;
        assert!(hybrid.clone().take_within(1, 1).is_none());
        assert!(hybrid.clone().take_within(0, 1).is_none());
        assert_eq!(hybrid.take_within(2, 1).map(|(done, _)| done), Some(5));
        assert!(other.clone().take_within(0, 2).is_none());
        assert!(other.take_within(1, 1).is_none());
        // Its interruption message names the position.
        let i = saver.interrupt_at(libc::SIGTERM, 2, Some(5), |_| unreachable!("on disk"));
        let text = i.to_string();
        assert!(
            text.contains("after iteration 2 and 5 directions of the next")
                && text.contains("5 directions into the next"),
            "{text}"
        );
        // A position past the iteration's end is refused.
        let state = saver.state(2, None, ExtrapolationState::default());
        saver
            .save_within(&SingleProcess, state, 13, &radiosity, &acc)
            .unwrap();
        let err = load_shared(&SingleProcess, &path, &this, 10).unwrap_err();
        assert!(
            err.is_bad_input() && err.to_string().contains("damaged"),
            "{err}"
        );
    }

    #[test]
    fn interruption_messages() {
        let i = Interruption {
            signal: libc::SIGTERM,
            completed: 7,
            within: None,
            checkpoint: Some((PathBuf::from("out/checkpoint.bin"), 7, None)),
            failure: None,
            writer: true,
        };
        let text = i.to_string();
        assert!(
            text.contains("SIGTERM")
                && text.contains("out/checkpoint.bin")
                && text.contains("--resume"),
            "{text}"
        );
    }
}

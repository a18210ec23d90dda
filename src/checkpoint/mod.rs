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

pub use file::{CheckpointFile, Radiosity};

use crate::distribute::Comm;
use crate::geometry::directions::DirectionSet;
use crate::scene::Material;
use crate::solve::accelerate::Extrapolation;
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
#[derive(Clone, Debug, Default, PartialEq)]
pub struct State {
    /// Iterations completed.
    pub iteration: u64,
    /// Ranks of the run that wrote it (a resume on another count is allowed; its sums across
    /// ranks are added in another grouping, so the last bits may differ).
    pub ranks: u32,
    /// The stopping rule's last relative change (`jacobi::Convergence`).
    pub previous_change: Option<f64>,
    pub extrapolation: Extrapolation,
}

/// Everything in a checkpoint but the radiosity.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    pub identity: Identity,
    pub state: State,
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
            return Err(failure.unwrap_or_else(|| CheckpointError::Bad {
                path: path.to_path_buf(),
                what: "rank 0 could not read it (see rank 0's message)".to_string(),
            }))
        }
        _ => {}
    }
    if comm.size() > 1 {
        bytes = broadcast_bytes(comm, bytes);
    }
    // Every rank checks the same bytes against the same identity: the same verdict everywhere.
    let (header, radiosity) = file::parse(path, &bytes)?;
    drop(bytes);
    check(path, &header, this, max_iterations)?;
    Ok(Some(Loaded {
        path: path.to_path_buf(),
        state: header.state,
        radiosity,
    }))
}

/// Rank 0's `bytes` on every rank, through the solver's only collectives (`max_u64` and the sum
/// in rank order): four bytes per f64, whole numbers that a sum with zeros keeps exactly.
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
    /// Iteration of the checkpoint on disk for this run, if any.
    saved: Option<u64>,
    ranks: u32,
}

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
            saved: resumed,
            ranks: ranks as u32,
        }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether the time since the last checkpoint calls for another.
    pub fn due(&self) -> bool {
        self.last.elapsed() >= self.every
    }

    /// The state to save after `iteration` iterations.
    pub fn state(
        &self,
        iteration: usize,
        previous_change: Option<f64>,
        extrapolation: &Extrapolation,
    ) -> State {
        State {
            iteration: iteration as u64,
            ranks: self.ranks,
            previous_change,
            extrapolation: extrapolation.clone(),
        }
    }

    /// Writes a checkpoint of `state` whose radiosity `fill` writes (`buffer_bytes` of write
    /// buffer). A failure keeps the earlier checkpoint and is returned for the caller to report.
    pub fn save(
        &mut self,
        state: State,
        buffer_bytes: usize,
        fill: impl FnOnce(&mut dyn std::io::Write) -> std::io::Result<()>,
    ) -> Result<(), CheckpointError> {
        let iteration = state.iteration;
        if self.writes {
            let t = Instant::now();
            let header = Header {
                identity: self.identity.clone(),
                state,
            };
            file::write(&self.path, &header, buffer_bytes, fill)?;
            tracing::info!(
                iteration,
                seconds = format!("{:.2}", t.elapsed().as_secs_f64()),
                path = %self.path.display(),
                "checkpoint written"
            );
        }
        self.saved = Some(iteration);
        self.last = Instant::now();
        Ok(())
    }

    /// [`Saver::save`] of radiosity held in memory.
    pub fn save_memory(
        &mut self,
        state: State,
        radiosity: &[Radiosity],
    ) -> Result<(), CheckpointError> {
        self.save(state, 1 << 20, |w| {
            let mut bytes = [0u8; file::RADIOSITY_LEN];
            for b in radiosity {
                file::encode_radiosity(b, &mut bytes);
                w.write_all(&bytes)?;
            }
            Ok(())
        })
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
        if let Err(e) = save(self, state) {
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
        let mut failure = None;
        if self.saved != Some(completed as u64) {
            if let Err(e) = save(self) {
                failure = Some(e.to_string());
            }
        }
        Interruption {
            signal,
            completed,
            checkpoint: self.saved.map(|i| (self.path.clone(), i)),
            failure,
            writer: self.writes,
        }
    }
}

/// A solve stopped by SIGTERM or SIGINT (exit status 3).
#[derive(Clone, Debug)]
pub struct Interruption {
    pub signal: i32,
    /// Iterations completed when it stopped.
    pub completed: usize,
    /// The checkpoint to resume from and its iteration.
    pub checkpoint: Option<(PathBuf, u64)>,
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
            checkpoint: None,
            failure: None,
            writer,
        }
    }
}

impl std::fmt::Display for Interruption {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let signal = crate::interrupt::name(self.signal);
        if !self.writer {
            return write!(
                f,
                "interrupted by {signal} after iteration {}; rank 0 wrote the checkpoint",
                self.completed
            );
        }
        write!(
            f,
            "interrupted by {signal} after iteration {}; ",
            self.completed
        )?;
        if let Some(e) = &self.failure {
            write!(f, "its checkpoint could not be written ({e}); ")?;
        }
        match &self.checkpoint {
            Some((path, iteration)) => write!(
                f,
                "checkpoint at {} (iteration {iteration}); rerun with --resume to continue",
                path.display()
            ),
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
    use crate::distribute::SingleProcess;

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
        let state = saver.state(4, Some(0.5), &Extrapolation::default());
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
    fn interruption_messages() {
        let i = Interruption {
            signal: libc::SIGTERM,
            completed: 7,
            checkpoint: Some((PathBuf::from("out/checkpoint.bin"), 7)),
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

//! Checkpoints: the state of a solve at an iteration boundary, kept in `OUT/checkpoint.bin`, from
//! which `voxrad solve ... --resume` continues with exactly the bits an uninterrupted run would
//! have produced.
//!
//! What makes the continuation bit-identical: the solvers' next iteration is a pure function of
//! the radiosity after the last one (stored as the f32 values the solver itself keeps), the
//! stopping rule's last relative change (`iterate::Convergence`) and the extrapolation's history
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
//! same layout between two directions, with the canonical sum of the main axes done as the one
//! rank's, and inside a main axis one more array, that axis's light so far
//! ([`State::axis_in_progress`], `outcore::solver`).
//!
//! A checkpoint names the run it belongs to ([`Identity`]: solver, grid, surfels, directions,
//! channels, extrapolation, and a checksum of the voxelized scene or of the shard set): one from
//! another run is refused with what differs, never used. The tolerance, the iteration limit and
//! the thread count are not part of it: they do not change the iterations already made (so a
//! stopped solve can be resumed with a higher `--iterations`).
//!
//! `file` owns the byte layout; `identity` what names a run, `state` where a solve stood,
//! `saver` when checkpoints are written ([`Saver`]), `load` reading one and handing it from rank
//! 0 to every rank ([`load_shared`]), `interruption` the message of a stopped run
//! ([`Interruption`]); this file the errors, the paths and the clean-up of an out directory.

pub mod file;
mod identity;
mod interruption;
mod load;
mod saver;
mod state;

pub use identity::*;
pub use interruption::*;
pub use load::*;
pub use saver::*;
pub use state::*;

pub use file::{CheckpointFile, Gathered, Radiosity};

use crate::comm::Comm;
use crate::geometry::directions::DirectionSet;
use crate::scene::Material;
use crate::voxel::{Grid, Surfel, SurfelSet};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The checkpoint's name inside the out directory.
pub const FILE_NAME: &str = "checkpoint.bin";

/// The prefix of a rank's work directory in the data and hybrid modes out of core (followed by
/// the rank and `-`).
pub const RANK_WORK_DIR_PREFIX: &str = ".voxrad-rank";

/// Prefixes of the work directories a solve makes inside its out directory (removed when it
/// ends, but left behind by a process that was killed).
pub const WORK_DIR_PREFIXES: [&str; 4] = [
    ".voxrad-work-",
    ".voxrad-shards-",
    ".voxrad-new-",
    RANK_WORK_DIR_PREFIX,
];

/// The checkpoint path of the out directory `out`.
pub fn path_in(out: &Path) -> PathBuf {
    out.join(FILE_NAME)
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
    fn what_a_killed_run_left_is_removed_and_nothing_else() {
        let out = tempfile::TempDir::new().unwrap();
        // The names the solvers give their work directories (a data-mode rank's was missed
        // once, and a killed run's stayed behind for good).
        let left = [
            ".voxrad-work-a1",
            ".voxrad-shards-b2",
            ".voxrad-shards-rank1-c3",
            ".voxrad-new-d4",
            ".voxrad-rank0-e5",
            ".voxrad-rank12-f6",
        ];
        for name in left {
            std::fs::create_dir(out.path().join(name)).unwrap();
            std::fs::write(out.path().join(name).join("work.bin"), b"x").unwrap();
        }
        std::fs::write(out.path().join("checkpoint.bin.partial"), b"x").unwrap();
        let kept = ["checkpoint.bin", "report.json", "voxrad-rank-notes"];
        for name in kept {
            std::fs::write(out.path().join(name), b"x").unwrap();
        }
        std::fs::create_dir(out.path().join("rank0")).unwrap();
        remove_leftovers(out.path());
        let mut now: Vec<String> = std::fs::read_dir(out.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        now.sort();
        assert_eq!(
            now,
            [
                "checkpoint.bin",
                "rank0",
                "report.json",
                "voxrad-rank-notes"
            ]
        );
    }

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
        saver.save_memory(state.clone(), &radiosity, None).unwrap();
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
        // A run that allows the Chebyshev semi-iteration iterates otherwise.
        let chebyshev = this.clone().with_chebyshev(true);
        let text = load_shared(&SingleProcess, &path, &chebyshev, 10)
            .unwrap_err()
            .to_string();
        assert!(text.contains("--chebyshev"), "{text}");
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
            .save_within(&SingleProcess, state, 5, (&radiosity, None), &acc)
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
            .save_within(&SingleProcess, state, 13, (&radiosity, None), &acc)
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

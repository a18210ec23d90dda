//! Checkpoints inside an iteration in the data and hybrid modes out of core: the light every
//! group has gathered so far, brought to canonical order on rank 0 beside the radiosity, and
//! put back into the held records of a resumed run.
//!
//! Between two steps a group's light is in two slots of its held records: the canonical sum of
//! the main axes it has done (`earlier`, or still `gathered` when its last axis ended with the
//! step just done, and is folded only when the next one starts), and the light of the axis in
//! progress (`gathered`). The checkpoint keeps them apart (`State::axis_in_progress` with
//! `data_groups`, format version 5): an axis's light added to the sum early would round
//! otherwise than the uninterrupted run, which adds it whole. The sum of a finished axis is
//! folded here exactly as the next step would fold it, so a resume adds the same bits in the
//! same order. Each array is by surfel id, so a run with another rank count but the same
//! groups continues inside the iteration too.

use super::held::{self, Held, HeldReader, Wire, EARLIER_AT, GATHERED_AT};
use super::route::Router;
use super::{fold_axis, DataOocSweep, Solver, WalkStep};
use crate::checkpoint::{CheckpointError, CheckpointFile, Saver, State};
use crate::outcore::files::{
    decode_gathered, encode_light32, IoCounters, GATHER_LEN, LIGHT32_LEN, RADIOSITY_LEN,
};
use crate::outcore::OocError;
use std::path::PathBuf;
use std::time::Instant;

/// A group's light `done` steps into an iteration, as the held records of its last step hold
/// it.
#[derive(Clone, Copy)]
struct Position {
    /// `earlier` holds the sum of the axes done.
    earlier_any: bool,
    /// `gathered` holds a whole axis, to be added to `earlier` when the next one starts.
    pending: bool,
    /// `gathered` holds the light of the axis in progress.
    in_axis: bool,
}

impl Position {
    /// The canonical sum of the light of the axes done (zeros before the first), its f32
    /// slot as a checkpoint holds it (`State::sums_in_f32`).
    fn sum(self, w: &Wire) -> [u8; LIGHT32_LEN] {
        let mut record = *w;
        if self.pending {
            fold_axis(&mut record, !self.earlier_any);
        } else if !self.earlier_any {
            return [0; LIGHT32_LEN];
        }
        slot(&record, EARLIER_AT)
    }

    /// The light of the axis in progress (zeros between two axes), its f32 slot as a
    /// checkpoint holds it.
    fn axis(self, w: &Wire) -> [u8; LIGHT32_LEN] {
        if self.in_axis {
            slot(w, GATHERED_AT)
        } else {
            [0; LIGHT32_LEN]
        }
    }
}

/// The f32 light slot at `at`.
fn slot(w: &Wire, at: usize) -> [u8; LIGHT32_LEN] {
    w[at..at + LIGHT32_LEN].try_into().expect("a light slot")
}

/// Whether a group that has done the first `done` steps of `walk` has finished an axis.
pub(super) fn axes_done(walk: &[WalkStep], done: usize) -> bool {
    walk[..done.min(walk.len())].iter().any(|s| s.last)
}

impl DataOocSweep<'_, '_> {
    /// Saves the state `done` steps into iteration `state.iteration + 1`: rank 0 gathers the
    /// radiosity (from group 0; and the radiosity before last while the Chebyshev
    /// semi-iteration runs), every group's sum of its axes done, then every group's light of its
    /// axis in progress, each in canonical order, and writes them. Collective.
    ///
    /// Each array is gathered into a canonical file on rank 0, copied into the checkpoint and
    /// removed before the next one is gathered, so that rank 0's disk holds one of them at a
    /// time beside its held files (all of them at once made the data mode's peak). Every rank
    /// takes part in every gather, in the same order, whatever happens to rank 0's writing:
    /// a failed write ends the copying, not the gathers.
    pub(super) fn save_inside(
        &mut self,
        saver: &mut Saver,
        mut state: State,
        done: usize,
    ) -> Result<(), CheckpointError> {
        let t = Instant::now();
        let solver = self.solver;
        let at = Position {
            earlier_any: self.earlier_any,
            pending: self.pending,
            in_axis: done.min(self.walk.len()) > 0 && !self.pending,
        };
        let held = self.held.as_ref().expect("held files between steps");
        let (dir, plan, surfels) = (self.dir, self.plan, self.surfels);
        let mut io = IoCounters::default();
        let chebyshev = state.extrapolation.chebyshev.is_some();
        // The arrays in the checkpoint's order: the radiosity, the one before last (while
        // Chebyshev runs), every group's sum of its axes done, every group's axis in progress.
        let groups = solver.groups;
        let arrays = 1 + chebyshev as usize + 2 * groups;
        let mut gather_array = |k: usize| -> Result<Option<PathBuf>, OocError> {
            if k == 0 {
                return solver.gather_canonical::<RADIOSITY_LEN>(
                    HeldReader::open(held, plan.io_bytes)?,
                    0,
                    surfels,
                    "checkpoint-radiosity.bin",
                    (dir, plan),
                    &mut io,
                    |w| {
                        w[held::RADIOSITY_AT..held::RADIOSITY_AT + RADIOSITY_LEN]
                            .try_into()
                            .expect("a radiosity record")
                    },
                );
            }
            if chebyshev && k == 1 {
                return solver.gather_older(
                    held,
                    surfels,
                    "checkpoint-older.bin",
                    (dir, plan),
                    &mut io,
                );
            }
            let light = k - 1 - chebyshev as usize;
            let (kind, group) = (light / groups, light % groups);
            let (name, value) = match kind {
                0 => (
                    "sum",
                    Position::sum as fn(Position, &Wire) -> [u8; LIGHT32_LEN],
                ),
                _ => (
                    "axis",
                    Position::axis as fn(Position, &Wire) -> [u8; LIGHT32_LEN],
                ),
            };
            solver.gather_canonical::<LIGHT32_LEN>(
                HeldReader::open(held, plan.io_bytes)?,
                group,
                surfels,
                &format!("checkpoint-{name}-{group}.bin"),
                (dir, plan),
                &mut io,
                |w| value(at, w),
            )
        };
        let checkpoint = saver.path().to_path_buf();
        let gather_error = |e: OocError| CheckpointError::Io {
            path: checkpoint.clone(),
            action: "gather the light of every rank for",
            source: std::io::Error::other(e.to_string()),
        };
        let mut gathered = 0;
        let mut failed: Option<CheckpointError> = None;
        state.within = Some(done as u64);
        state.data_groups = groups as u32;
        state.axis_in_progress = true;
        state.sums_in_f32 = true;
        // Called on rank 0 alone, once its checkpoint file is open.
        let result = saver.save(state, plan.io_bytes, |w| {
            let mut written = Ok(());
            while gathered < arrays && failed.is_none() {
                let array = gather_array(gathered);
                gathered += 1;
                match array {
                    Ok(Some(path)) => {
                        if written.is_ok() {
                            written = std::fs::File::open(&path).and_then(|file| {
                                let mut reader =
                                    std::io::BufReader::with_capacity(plan.io_bytes, file);
                                std::io::copy(&mut reader, w).map(|_| ())
                            });
                        }
                        let _ = std::fs::remove_file(&path);
                    }
                    Ok(None) => {}
                    Err(e) => failed = Some(gather_error(e)),
                }
            }
            // A checkpoint without all its arrays must not replace the last one.
            match &failed {
                Some(_) => Err(std::io::Error::other("an array was not gathered")),
                None => written,
            }
        });
        // The gathers rank 0 did not make inside its writing (every one, on the other ranks).
        while gathered < arrays && failed.is_none() {
            match gather_array(gathered) {
                Ok(Some(path)) => {
                    let _ = std::fs::remove_file(&path);
                }
                Ok(None) => {}
                Err(e) => failed = Some(gather_error(e)),
            }
            gathered += 1;
        }
        self.io.read += io.read;
        self.io.written += io.written;
        // The gathering is part of what a checkpoint costs here: it spaces the next ones too.
        saver.took(t.elapsed());
        match failed {
            Some(e) => Err(e),
            None => result,
        }
    }
}

impl Solver<'_> {
    /// Puts a mid-iteration checkpoint's light (`file`, on rank 0; written by a run of this
    /// many groups) into the held records in canonical order: each group's sum of its axes done
    /// into `earlier`, its light of the axis in progress into `gathered`. Rank 0 sends every
    /// rank of each group its slice of that group's arrays. Collective.
    pub(super) fn restore_inside(
        &self,
        mut held: Held,
        first: u64,
        file: Option<&CheckpointFile>,
        generation: &mut u64,
        router: &Router,
        io: &mut IoCounters,
    ) -> Result<Held, OocError> {
        let plan = router.plan;
        let name = file
            .map(|f| f.path.display().to_string())
            .unwrap_or_else(|| "the checkpoint".to_string());
        for (arrays_before, at) in [(0, EARLIER_AT), (self.groups, GATHERED_AT)] {
            let mut mine = None;
            for group in 0..self.groups {
                let read = |piece: &mut dyn FnMut(&[u8]) -> Result<(), OocError>| {
                    let file = file.ok_or_else(|| OocError::BadData {
                        source_name: "the checkpoint".to_string(),
                        what: "rank 0 did not open it".to_string(),
                    })?;
                    let array = (arrays_before + group) as u32;
                    file.read_array::<OocError>(array, plan.io_bytes, piece)
                };
                let slice =
                    self.send_slices(Some(group), first, GATHER_LEN, &name, read, router, io)?;
                mine = mine.or(slice);
            }
            let mine = mine.expect("every rank is in a group");
            *generation += 1;
            held = self.place_slice::<GATHER_LEN>(
                held,
                (&mine, false),
                *generation,
                router,
                io,
                |w, v| {
                    // Handed out in f64 (f32 in the file since format version 7), as f32
                    // sums made them: the slot holds them exactly.
                    encode_light32(&decode_gathered(v), &mut w[at..]);
                },
            )?;
        }
        Ok(held)
    }
}

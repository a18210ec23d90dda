//! The commands behind the `voxrad` binary, as library functions: `solve`, `render`, `probe`,
//! `generate`, `study`.
//!
//! The binary parses arguments (validation only) and calls these; each turns the parsed options
//! into the real objects, runs the pipeline (read -> voxelize -> solve -> write) and returns an
//! [`AppError`] that knows whether the user's input was at fault (exit status 2) or not (1),
//! or that a stop signal ended the solve (3, with a checkpoint to resume from).
//!
//! This module holds the errors, the parsed `solve` command and where each solve goes
//! ([`run_solve_on`]); each path is a file: [`in_memory`], [`out_of_core`] (one process),
//! [`data_out_of_core`] (the data mode under `--memory`); [`results`] renders and probes a
//! solve's results; [`generate`] writes scenes and runs the study.

mod data_out_of_core;
mod generate;
mod in_memory;
mod out_of_core;
mod results;

use data_out_of_core::*;
pub use generate::{run_generate, run_study, GenerateScene};
use in_memory::*;
use out_of_core::*;
use results::*;
pub use results::{run_bake, run_grid, run_probe, run_render};

use crate::checkpoint::{self, CheckpointError, CheckpointFile, Identity, Saver};
use crate::distribute::data::{solve_data, DataOptions};
use crate::distribute::{Comm, Mode, SingleProcess};
use crate::geometry::directions::DirectionSet;
use crate::outcore::{
    solve_out_of_core_checkpointed, OocCheckpoints, OocError, ShardSetSource, SurfelSource,
};
use crate::output::render::{auto_camera, render_pictures, render_png, Camera, Drawn};
use crate::output::report::{Report, RunInfo};
use crate::output::results::{read_results, write_results, Results, ResultsWriter};
use crate::output::staging::Staging;
use crate::output::{bake, glb, mesh_ply, ply, probe, RENDER_FILE};
use crate::scene::obj::load_obj;
use crate::solve::jacobi::{solve_checkpointed, Checkpoints, SolveError};
use crate::solve::{Solution, SolveOptions};
use crate::voxel::voxelize::{voxelize, GridSpec};
use crate::voxel::{Surfel, SurfelSet};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// An error of a command, with the exit status it maps to.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    /// The user's input is wrong (file, line and what to do are in the message): exit status 2.
    #[error("{0}")]
    BadInput(String),
    /// Anything else (I/O failures, resources): exit status 1.
    #[error("{0}")]
    Failure(String),
    /// SIGTERM or SIGINT stopped the solve; the message names the checkpoint: exit status 3.
    #[error("{0}")]
    Interrupted(String),
}

impl AppError {
    pub fn exit_code(&self) -> i32 {
        match self {
            AppError::BadInput(_) => 2,
            AppError::Failure(_) => 1,
            AppError::Interrupted(_) => 3,
        }
    }
}

/// Options of `voxrad solve`.
#[derive(Clone, Debug)]
pub struct SolveCommand {
    pub scene: PathBuf,
    pub out: PathBuf,
    pub grid: GridSpec,
    pub solve: SolveOptions,
    pub image_size: (u32, u32),
    /// `--memory`: solve out of core within this many bytes.
    pub memory: Option<u64>,
    /// `--resume` and how often checkpoints are written.
    pub checkpoint: CheckpointOptions,
    /// `--work-dir`: where out-of-core work directories go instead of `out` ([`work_parent`]).
    pub work_dir: Option<PathBuf>,
}

/// Where the work directories of an out-of-core solve of `cmd` go: `out` itself, or with
/// `--work-dir DIR` a subdirectory of DIR named after `out` (made here), so that jobs with
/// different out directories can share DIR (a node's local disk) and each removes there only
/// what a killed run of its own left.
pub(super) fn work_parent(cmd: &SolveCommand) -> Result<PathBuf, AppError> {
    let Some(parent) = work_subdirectory(cmd) else {
        return Ok(cmd.out.clone());
    };
    std::fs::create_dir_all(&parent).map_err(|e| {
        AppError::BadInput(format!(
            "cannot make the work directory {} (--work-dir): {e}",
            parent.display()
        ))
    })?;
    Ok(parent)
}

/// `--work-dir DIR`'s subdirectory for `cmd.out` (FNV-1a of its canonical path; `out` exists by
/// then, and names itself alike on every node that mounts it at the same place).
fn work_subdirectory(cmd: &SolveCommand) -> Option<PathBuf> {
    let dir = cmd.work_dir.as_ref()?;
    let out = std::fs::canonicalize(&cmd.out).unwrap_or_else(|_| cmd.out.clone());
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    for byte in out.as_os_str().as_encoded_bytes() {
        hash = (hash ^ *byte as u64).wrapping_mul(0x0100_0000_01b3);
    }
    Some(dir.join(format!("voxrad-work-{hash:016x}")))
}

/// When a solve writes checkpoints into its out directory, and whether it starts from one.
#[derive(Clone, Debug)]
pub struct CheckpointOptions {
    /// `--resume`: continue from `OUT/checkpoint.bin` if there is one.
    pub resume: bool,
    /// `--checkpoint-every`: least time between two checkpoints (zero: every iteration).
    pub every: std::time::Duration,
    /// Inside iterations, a checkpoint waits at least this many times the last one's writing
    /// time (`checkpoint::WRITE_TIME_FACTOR` at the default interval,
    /// `checkpoint::ASKED_WRITE_TIME_FACTOR` where one is given).
    pub write_factor: u32,
}

impl Default for CheckpointOptions {
    fn default() -> Self {
        CheckpointOptions {
            resume: false,
            every: std::time::Duration::from_secs(60),
            write_factor: crate::checkpoint::WRITE_TIME_FACTOR,
        }
    }
}

/// Reads and voxelizes the scene, solves, writes every output; returns the report.
pub fn run_solve(cmd: &SolveCommand) -> Result<Report, AppError> {
    run_solve_on(cmd, &SingleProcess, Mode::Single)
}

/// As [`run_solve`], on the processes of `comm` in `mode`; only rank 0 writes outputs.
pub fn run_solve_on(cmd: &SolveCommand, comm: &dyn Comm, mode: Mode) -> Result<Report, AppError> {
    if cmd.work_dir.is_some() && cmd.memory.is_none() && !cmd.scene.is_dir() {
        return Err(AppError::BadInput(
            "--work-dir applies to out-of-core solves (--memory SIZE, or a shard set): a solve \
             in memory makes no work files"
                .into(),
        ));
    }
    let result = run_solve_checked(cmd, comm, mode);
    // The work directories are gone (removed as their solvers ended); so is their parent under
    // --work-dir once empty (not while another rank on this node still works there).
    if let Some(parent) = work_subdirectory(cmd) {
        let _ = std::fs::remove_dir(parent);
    }
    result
}

fn run_solve_checked(cmd: &SolveCommand, comm: &dyn Comm, mode: Mode) -> Result<Report, AppError> {
    let started = Instant::now();
    if let Some(launched) = crate::distribute::launcher_world_size() {
        if launched != comm.size() {
            return Err(AppError::BadInput(format!(
                "the MPI launcher started {launched} processes but this one sees {} (rank {}): {}",
                comm.size(),
                comm.rank(),
                if mode == Mode::Single {
                    "give --distribute directions to share the solve (a build with the `mpi` \
                     feature), or run without mpirun"
                } else {
                    "this voxrad's MPI library does not match the launcher; build it against \
                     the MPI that provides this mpirun"
                }
            )));
        }
    }
    let mode = match mode {
        Mode::Hybrid {
            groups: 0,
            compress,
        } => Mode::Hybrid {
            groups: crate::distribute::hybrid_groups(comm.size()),
            compress,
        },
        Mode::Hybrid { groups, .. } if comm.size() % groups != 0 => {
            return Err(AppError::BadInput(format!(
                "--groups {groups}: {} ranks cannot form {groups} equal groups; give a divisor \
                 of the rank count (or leave --groups out)",
                comm.size()
            )))
        }
        other => other,
    };
    match (mode, cmd.memory) {
        (Mode::Data { .. }, Some(budget)) => {
            return run_solve_data_out_of_core(cmd, comm, 1, budget, started)
        }
        (Mode::Hybrid { groups, .. }, Some(budget)) => {
            return run_solve_data_out_of_core(cmd, comm, groups, budget, started)
        }
        (Mode::Directions, Some(_)) => {
            return Err(AppError::BadInput(format!(
                "{}: --distribute directions does not work out of core (--memory): every rank \
                 would hold the whole scene; --distribute data or hybrid does: use one, or \
                 leave --memory out",
                cmd.scene.display(),
            )))
        }
        _ => {}
    }
    if comm.rank() == 0 {
        checkpoint::remove_leftovers(&cmd.out);
        if let Some(parent) = work_subdirectory(cmd) {
            checkpoint::remove_leftovers(&parent);
        }
    }
    if cmd.scene.is_dir() && mode == Mode::Single {
        return run_solve_shard_set(cmd, started);
    }
    if let Some(budget) = cmd.memory {
        return run_solve_obj_out_of_core(cmd, budget, started);
    }
    solve_in_memory_from_scene(cmd, comm, mode, started)
}

/// Logs whether the solve continues from a checkpoint or starts afresh, and why.
fn say_where_it_starts(cmd: &SolveCommand, path: &Path, resumed: bool) {
    if resumed {
        return; // the solver logs the iteration it resumes from
    }
    if cmd.checkpoint.resume {
        tracing::info!(
            "--resume: no checkpoint at {}; starting from the beginning",
            path.display()
        );
    } else if path.exists() {
        tracing::warn!(
            "{} is left from an earlier run; starting afresh and replacing it (give --resume to \
             continue from it)",
            path.display()
        );
    }
}

fn checkpoint_error(e: CheckpointError) -> AppError {
    if e.is_bad_input() {
        AppError::BadInput(e.to_string())
    } else {
        AppError::Failure(e.to_string())
    }
}

/// Sets the report's total time and peak RSS, writes it beside the staged outputs and moves
/// them all into place.
fn finish_report(
    mut report: Report,
    staged: Staging,
    started: Instant,
) -> Result<Report, AppError> {
    report.set_total(started.elapsed().as_secs_f64());
    report.refresh_peak_rss();
    report
        .write(staged.path())
        .map_err(|e| AppError::Failure(e.to_string()))?;
    let out = staged.out().to_path_buf();
    publish(staged)?;
    checkpoint::remove_finished(&out);
    Ok(report)
}

/// A staging directory for a run's outputs inside `out` (see `output::staging`).
fn stage(out: &Path) -> Result<Staging, AppError> {
    Staging::new(out).map_err(|e| AppError::Failure(e.to_string()))
}

fn publish(staged: Staging) -> Result<(), AppError> {
    staged
        .publish()
        .map(|_| ())
        .map_err(|e| AppError::Failure(e.to_string()))
}

fn create_out_dir(out: &Path) -> Result<(), AppError> {
    std::fs::create_dir_all(out).map_err(|e| {
        AppError::Failure(format!(
            "cannot create output directory {}: {e}",
            out.display()
        ))
    })
}

fn ooc_error(e: OocError) -> AppError {
    if let OocError::Interrupted(i) = &e {
        AppError::Interrupted(i.to_string())
    } else if e.is_bad_input() {
        AppError::BadInput(e.to_string())
    } else {
        AppError::Failure(e.to_string())
    }
}

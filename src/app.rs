//! The commands behind the `voxrad` binary, as library functions: `solve`, `render`, `probe`.
//!
//! The binary parses arguments (validation only) and calls these; each turns the parsed options
//! into the real objects, runs the pipeline (read -> voxelize -> solve -> write) and returns an
//! [`AppError`] that knows whether the user's input was at fault (exit status 2) or not (1),
//! or that a stop signal ended the solve (3, with a checkpoint to resume from).

use crate::checkpoint::{self, CheckpointError, CheckpointFile, Identity, Saver};
use crate::distribute::data::{solve_data, DataOptions};
use crate::distribute::{Comm, Mode, SingleProcess};
use crate::geometry::directions::DirectionSet;
use crate::outcore::{
    solve_out_of_core_checkpointed, OocCheckpoints, OocError, ShardSetSource, SurfelSource,
};
use crate::output::render::{auto_camera, render_png, Camera};
use crate::output::report::{Effect, OutOfCoreReport, Report, RunInfo};
use crate::output::results::{read_results, write_results, Results, ResultsWriter};
use crate::output::staging::Staging;
use crate::output::{ply, probe, RENDER_FILE};
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
}

/// When a solve writes checkpoints into its out directory, and whether it starts from one.
#[derive(Clone, Debug)]
pub struct CheckpointOptions {
    /// `--resume`: continue from `OUT/checkpoint.bin` if there is one.
    pub resume: bool,
    /// `--checkpoint-every`: least time between two checkpoints (zero: every iteration).
    pub every: std::time::Duration,
}

impl Default for CheckpointOptions {
    fn default() -> Self {
        CheckpointOptions {
            resume: false,
            every: std::time::Duration::from_secs(60),
        }
    }
}

/// Reads and voxelizes the scene, solves, writes every output; returns the report.
pub fn run_solve(cmd: &SolveCommand) -> Result<Report, AppError> {
    run_solve_on(cmd, &SingleProcess, Mode::Single)
}

/// As [`run_solve`], on the processes of `comm` in `mode`; only rank 0 writes outputs.
pub fn run_solve_on(cmd: &SolveCommand, comm: &dyn Comm, mode: Mode) -> Result<Report, AppError> {
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
    if let (Mode::Data { .. }, Some(budget)) = (mode, cmd.memory) {
        return run_solve_data_out_of_core(cmd, comm, budget, started);
    }
    if mode != Mode::Single && cmd.memory.is_some() {
        return Err(AppError::BadInput(format!(
            "{}: --distribute {} does not work out of core (--memory); only --distribute data \
             does: use it, or leave --memory out",
            cmd.scene.display(),
            mode.name()
        )));
    }
    if comm.rank() == 0 {
        checkpoint::remove_leftovers(&cmd.out);
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
    if cmd.scene.is_dir() && mode == Mode::Single {
        return run_solve_shard_set(cmd, started);
    }
    if let Some(budget) = cmd.memory {
        return run_solve_obj_out_of_core(cmd, budget, started);
    }
    let (set, read_seconds, voxelize_seconds) = if cmd.scene.is_dir() {
        // Distributed: every rank reads the whole shard set (its own copy, or a shared one)
        // into memory.
        let set = load_shard_set(&cmd.scene)?;
        (set, started.elapsed().as_secs_f64(), 0.0)
    } else {
        let scene = load_obj(&cmd.scene).map_err(|e| {
            if e.is_bad_input() {
                AppError::BadInput(e.to_string())
            } else {
                AppError::Failure(e.to_string())
            }
        })?;
        let read_seconds = started.elapsed().as_secs_f64();
        tracing::info!(
            triangles = scene.triangles.len(),
            materials = scene.materials.len(),
            "scene read"
        );
        check_memory(&scene, cmd)?;
        let t = Instant::now();
        let set = voxelize(&scene, cmd.grid)
            .map_err(|e| AppError::BadInput(format!("{}: {e}", cmd.scene.display())))?;
        (set, read_seconds, t.elapsed().as_secs_f64())
    };
    tracing::info!(
        surfels = set.surfels.len(),
        voxels = set.voxel_count(),
        dims = ?set.grid.dims,
        voxel_size = set.grid.voxel_size,
        "voxelized"
    );

    // Simulate only what the scene calls for (see `solve::effects`).
    let analysis = crate::solve::effects::analyse(&set);
    let shaped = analysis.shape(&cmd.solve);
    let directions = DirectionSet::with_count(shaped.directions);
    let t = Instant::now();
    let solution = solve_in_memory(cmd, &set, &directions, &shaped, comm, mode)?;
    let solve_seconds = t.elapsed().as_secs_f64();
    let stats = &solution.stats;
    tracing::info!(
        iterations = stats.iterations,
        converged = stats.converged,
        residual = stats.residual,
        directions = stats.directions,
        "solved"
    );
    if stats.stalled {
        tracing::warn!(
            "stopped after {} iterations: the changes no longer shrink in f32 storage, so the \
             tolerance {:?} cannot be shown for this scene; the result is as close as it gets",
            stats.iterations,
            cmd.solve.tolerance
        );
    } else if !stats.converged {
        tracing::warn!(
            "stopped after {} iterations with an estimated relative error of {:.2e} (tolerance {:?}); \
             raise --iterations to go further",
            stats.iterations,
            stats.residual,
            cmd.solve.tolerance
        );
    }

    let t = Instant::now();
    // Staged: the earlier outputs stay as they were unless every new one is written.
    let staged = if comm.rank() == 0 {
        let staging = stage(&cmd.out)?;
        write_outputs(staging.path(), &set, &solution, cmd.image_size)?;
        Some(staging)
    } else {
        None
    };
    let write_seconds = t.elapsed().as_secs_f64();

    let resolution = set.grid.dims.iter().copied().max().unwrap_or(0);
    let run = RunInfo {
        scene: cmd.scene.display().to_string(),
        mode: mode.name().to_string(),
        ranks: comm.size(),
        resolution,
        tolerance: cmd.solve.tolerance.unwrap_or(0.0),
    };
    let mut report = Report::new(run, &set, stats);
    report.set_phase("reduce", stats.reduce_seconds);
    // The whole solve call (set-up, iterations, communication): what a speed-up compares.
    report.set_phase("solve", solve_seconds);
    report.effects = analysis.effects(&cmd.solve, stats, None);
    if let Some(direct) = &stats.direct {
        // Inside "solve": the direct-light pass, before the iterations.
        report.set_phase("direct", direct.seconds);
    }
    report.set_phase("read", read_seconds);
    report.set_phase("voxelize", voxelize_seconds);
    report.set_phase("write", write_seconds);
    report.set_total(started.elapsed().as_secs_f64());
    // The largest peak over ranks: what a node must have.
    report.peak_rss_bytes = comm.max_u64(crate::output::report::peak_rss_bytes());
    if let Some(staging) = staged {
        report
            .write(staging.path())
            .map_err(|e| AppError::Failure(e.to_string()))?;
        publish(staging)?;
        checkpoint::remove_finished(&cmd.out);
    }
    Ok(report)
}

/// The in-memory solve, with checkpoints in the out directory (rank 0 writes them), from the
/// one there under `--resume`.
fn solve_in_memory(
    cmd: &SolveCommand,
    set: &SurfelSet,
    directions: &DirectionSet,
    options: &SolveOptions,
    comm: &dyn Comm,
    mode: Mode,
) -> Result<Solution, AppError> {
    if comm.rank() == 0 {
        create_out_dir(&cmd.out)?;
    }
    // As the solver decides it (`jacobi`): one channel only for a grey scene.
    let channels = if options.grey && crate::solve::effects::is_grey(set) {
        1
    } else {
        3
    };
    let identity = Identity::in_memory(set, directions, channels, options.accelerate)
        .with_direct_pass(
            options
                .direct
                .directions_for(set, directions.len())
                .as_ref(),
        );
    let path = checkpoint::path_in(&cmd.out);
    let resume = if cmd.checkpoint.resume {
        checkpoint::load_shared(comm, &path, &identity, options.max_iterations)
            .map_err(checkpoint_error)?
    } else {
        None
    };
    if comm.rank() == 0 {
        say_where_it_starts(cmd, &path, resume.is_some());
    }
    let mut saver = Saver::new(
        &cmd.out,
        identity,
        comm.rank() == 0,
        cmd.checkpoint.every,
        comm.size(),
        resume.as_ref().map(|l| l.state.iteration),
    )
    // Inside iterations too, in every mode (see `checkpoint`).
    .within(true);
    let checkpoints = Checkpoints {
        saver: &mut saver,
        resume,
    };
    let data = |groups, compress| DataOptions { groups, compress };
    match mode {
        Mode::Data { compress } => solve_data(
            set,
            directions,
            options,
            comm,
            data(1, compress),
            Some(checkpoints),
        ),
        Mode::Hybrid { groups, compress } => solve_data(
            set,
            directions,
            options,
            comm,
            data(groups, compress),
            Some(checkpoints),
        ),
        Mode::Single | Mode::Directions => {
            solve_checkpointed(set, directions, options, comm, checkpoints)
        }
    }
    .map_err(|e| match e {
        SolveError::Interrupted(i) => AppError::Interrupted(i.to_string()),
        other => AppError::Failure(other.to_string()),
    })
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

/// A whole shard set read into memory, in the set's own order (each shard checked as it is
/// read).
fn load_shard_set(dir: &Path) -> Result<SurfelSet, AppError> {
    let source = ShardSetSource::open(dir).map_err(ooc_error)?;
    let info = source.info().clone();
    let mut surfels = Vec::with_capacity(info.count as usize);
    for surfel in source.stream(64 << 20).map_err(ooc_error)? {
        surfels.push(surfel.map_err(ooc_error)?);
    }
    tracing::info!(surfels = surfels.len(), set = %dir.display(), "shard set read");
    Ok(SurfelSet {
        grid: info.grid,
        surfels,
        normals: info.normals,
        materials: info.materials,
    })
}

/// `voxrad solve SHARDSET`: out of core, within `--memory` (default: a quarter of the memory
/// available now).
fn run_solve_shard_set(cmd: &SolveCommand, started: Instant) -> Result<Report, AppError> {
    let source = ShardSetSource::open(&cmd.scene).map_err(ooc_error)?;
    let budget = match cmd.memory {
        Some(b) => b,
        None => available_memory_bytes().map_or(1 << 30, |a| (a / 4).max(64 << 20)),
    };
    let read_seconds = started.elapsed().as_secs_f64();
    let (mut report, staged) = solve_out_of_core_to(cmd, &source, budget)?;
    report.set_phase("read", read_seconds);
    finish_report(report, staged, started)
}

/// The out-of-core solve, with checkpoints in the out directory, from the one there under
/// `--resume` (checked against the run before any work file is made).
/// [`crate::solve::effects::analyse_sides`] of the surfels `source` streams.
fn analyse_source(
    source: &dyn SurfelSource,
    budget: u64,
) -> Result<crate::solve::effects::Analysis, AppError> {
    let info = source.info();
    let window = crate::outcore::MemoryPlan::new(budget, info.grid.dims, 1)
        .map(|p| p.io_bytes as u64)
        .unwrap_or(1 << 16);
    let mut sides = Vec::new();
    let mut failure = None;
    let stream = source.stream(window).map_err(ooc_error)?;
    // Materials are few: collect the distinct pairs, not one entry per surfel.
    let mut seen = std::collections::HashSet::new();
    let mut emitting_surfels = 0usize;
    for item in stream {
        match item {
            Ok(s) => {
                emitting_surfels += s.material.iter().any(|&m| {
                    info.materials
                        .get(m as usize)
                        .is_some_and(|m| m.is_emitter())
                }) as usize;
                if seen.insert(s.material) {
                    sides.push(s.material);
                }
            }
            Err(e) => {
                failure = Some(e);
                break;
            }
        }
    }
    if let Some(e) = failure {
        return Err(ooc_error(e));
    }
    let mut analysis = crate::solve::effects::analyse_sides(&info.materials, sides.into_iter());
    analysis.emitting_surfels = emitting_surfels;
    analysis.surfels = info.count as usize;
    analysis.longest_axis = info.grid.dims.into_iter().max().unwrap_or(0);
    Ok(analysis)
}

fn solve_out_of_core_in(
    cmd: &SolveCommand,
    source: &dyn SurfelSource,
    directions: &DirectionSet,
    options: &SolveOptions,
    budget: u64,
) -> Result<crate::outcore::OocSolution, AppError> {
    let identity = out_of_core_identity(source, directions, options, budget)?;
    let path = checkpoint::path_in(&cmd.out);
    let resume = if cmd.checkpoint.resume && path.exists() {
        let file = CheckpointFile::open(&path).map_err(checkpoint_error)?;
        checkpoint::check(&path, &file.header, &identity, options.max_iterations)
            .map_err(checkpoint_error)?;
        Some(file)
    } else {
        None
    };
    say_where_it_starts(cmd, &path, resume.is_some());
    let mut saver = Saver::new(
        &cmd.out,
        identity,
        true,
        cmd.checkpoint.every,
        1,
        resume.as_ref().map(|f| f.header.state.iteration),
    )
    // Between two main axes too (see `outcore::solver`).
    .within(true);
    let checkpoints = OocCheckpoints {
        saver: &mut saver,
        resume,
    };
    solve_out_of_core_checkpointed(source, directions, options, budget, &cmd.out, checkpoints)
        .map_err(ooc_error)
}

/// What names an out-of-core run in its checkpoints (one process or the data mode: the same
/// radiosity, so either resumes the other's).
fn out_of_core_identity(
    source: &dyn SurfelSource,
    directions: &DirectionSet,
    options: &SolveOptions,
    budget: u64,
) -> Result<Identity, AppError> {
    let info = source.info();
    let window = crate::outcore::MemoryPlan::new(budget, info.grid.dims, 1)
        .map(|p| p.io_bytes as u64)
        .unwrap_or(1 << 16);
    Ok(Identity {
        solver: checkpoint::Solver::OutOfCore,
        surfels: info.count,
        dims: info.grid.dims,
        voxel_size: info.grid.voxel_size,
        directions: directions.len() as u32,
        directions_checksum: checkpoint::directions_checksum(directions),
        // As the solvers decide it: one channel for a grey scene (checked by the solver on the
        // materials used, as the analysis did).
        channels: if options.grey { 1 } else { 3 },
        accelerate: options.accelerate,
        scene_checksum: source.checksum(window).map_err(ooc_error)?,
    }
    .with_direct_pass(
        match options.direct {
            // Resolved by the analysis (`Analysis::shape`).
            crate::solve::direct::DirectPass::On(n) if n > 0 => Some(DirectionSet::with_count(n)),
            _ => None,
        }
        .as_ref(),
    ))
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

/// `voxrad solve SCENE.obj --memory SIZE`: the scene is converted to a temporary shard set (the
/// streaming conversion of `voxrad-shard convert`, within the same budget) and solved from it.
fn run_solve_obj_out_of_core(
    cmd: &SolveCommand,
    budget: u64,
    started: Instant,
) -> Result<Report, AppError> {
    create_out_dir(&cmd.out)?;
    let (_work, shards, converted) = convert_obj(cmd, budget, ".voxrad-shards-")?;
    let convert_seconds = started.elapsed().as_secs_f64();
    let source = ShardSetSource::open(&shards).map_err(ooc_error)?;
    let (mut report, staged) = solve_out_of_core_to(cmd, &source, budget)?;
    report.set_phase("convert", convert_seconds);
    tracing::info!(
        surfels = converted.surfels,
        "solved from a temporary shard set"
    );
    finish_report(report, staged, started)
}

/// Converts the OBJ scene of `cmd` into a shard set in a new temporary directory (named from
/// `prefix`) inside the out directory: the streaming conversion of `voxrad-shard convert`,
/// within `budget`. Returns the directory (removed when dropped), the set and its summary.
fn convert_obj(
    cmd: &SolveCommand,
    budget: u64,
    prefix: &str,
) -> Result<
    (
        tempfile::TempDir,
        PathBuf,
        crate::convert::commands::ConvertSummary,
    ),
    AppError,
> {
    let work = tempfile::Builder::new()
        .prefix(prefix)
        .tempdir_in(&cmd.out)
        .map_err(|e| {
            AppError::Failure(format!(
                "cannot create a work directory in {}: {e}",
                cmd.out.display()
            ))
        })?;
    let shards = work.path().join("scene.shards");
    let convert_options = crate::convert::commands::ConvertOptions {
        scene: cmd.scene.clone(),
        out: shards.clone(),
        spec: cmd.grid,
        ranks: 1,
        memory: budget,
        order: 0,
        threads: cmd.solve.threads,
    };
    let converted = crate::convert::commands::convert(&convert_options).map_err(|e| match e {
        crate::convert::ConvertError::BadInput(m) => AppError::BadInput(m),
        crate::convert::ConvertError::Failure(m) => AppError::Failure(m),
    })?;
    Ok((work, shards, converted))
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

/// Solves `source` out of core and writes the results file (and, when the results fit the
/// budget, the PLY and the picture) into a staging directory; returns the report, not yet
/// written, and the staged outputs.
fn solve_out_of_core_to(
    cmd: &SolveCommand,
    source: &dyn SurfelSource,
    budget: u64,
) -> Result<(Report, Staging), AppError> {
    create_out_dir(&cmd.out)?;
    // Simulate only what the scene calls for, as in memory (one streaming pass over the source).
    let analysis = analyse_source(source, budget)?;
    let shaped = analysis.shape(&cmd.solve);
    let directions = DirectionSet::with_count(shaped.directions);
    let solution = solve_out_of_core_in(cmd, source, &directions, &shaped, budget)?;
    let stats = &solution.stats;
    tracing::info!(
        iterations = stats.solve.iterations,
        converged = stats.solve.converged,
        residual = stats.solve.residual,
        bytes_read = stats.bytes_read,
        bytes_written = stats.bytes_written,
        "solved out of core"
    );
    let t = Instant::now();
    let info = source.info();
    let staged = stage(&cmd.out)?;
    write_streamed_outputs(cmd, &staged, info, budget, |f| solution.for_each(source, f))?;
    let write_seconds = t.elapsed().as_secs_f64();
    let resolution = info.grid.dims.iter().copied().max().unwrap_or(0);
    let run = RunInfo {
        scene: cmd.scene.display().to_string(),
        mode: "single".to_string(),
        ranks: 1,
        resolution,
        tolerance: cmd.solve.tolerance.unwrap_or(0.0),
    };
    let mut report = Report::from_counts(
        run,
        stats.voxels,
        stats.surfels,
        info.grid.voxel_size,
        &stats.solve,
    );
    report.set_phase("setup", stats.setup_seconds);
    report.set_phase("band_read", stats.read_seconds);
    report.set_phase("band_write", stats.write_seconds);
    report.set_phase("update", stats.update_seconds);
    if let Some(direct) = &stats.solve.direct {
        // Before the iterations: the direct-light pass out of core.
        report.set_phase("direct", direct.seconds);
    }
    report.set_phase("write", write_seconds);
    report.out_of_core = Some(OutOfCoreReport::new(
        budget,
        stats.bytes_read,
        stats.bytes_written,
        stats.bands,
        stats.surfels * stats.solve.directions as u64 * stats.solve.iterations as u64,
    ));
    if let (Some(ooc), Some(direct)) = (report.out_of_core.as_mut(), &stats.solve.direct) {
        ooc.direct_light_parts = direct.parts;
    }
    report.effects = analysis.effects(&cmd.solve, &stats.solve, None);
    report.effects.push(Effect::new(
        "out of core",
        true,
        &format!(
            "surfels kept in files; everything that grows with the scene held within {}",
            crate::outcore::budget::format_bytes(budget)
        ),
    ));
    Ok((report, staged))
}

/// Writes the results file from `each` (which calls its argument for every surfel in canonical
/// order) and, when the results fit `budget`, the PLY and the picture, into `staged`.
fn write_streamed_outputs(
    cmd: &SolveCommand,
    staged: &Staging,
    info: &crate::outcore::source::SourceInfo,
    budget: u64,
    each: impl FnOnce(
        &mut dyn FnMut(&Surfel, &[[f32; 3]; 2]) -> Result<(), OocError>,
    ) -> Result<(), OocError>,
) -> Result<(), AppError> {
    let results_path = staged.path().join(crate::output::RESULTS_FILE);
    let fail = |e: crate::output::OutputError| AppError::Failure(e.to_string());
    let mut writer = ResultsWriter::create(&results_path, &info.grid, info.count).map_err(fail)?;
    each(&mut |s, b| {
        writer
            .push(&crate::output::results::Record::from_surfel(s, *b))
            .map_err(|e| OocError::BadData {
                source_name: results_path.display().to_string(),
                what: e.to_string(),
            })
    })
    .map_err(ooc_error)?;
    writer.finish().map_err(fail)?;
    // The picture and the PLY need every surfel in memory: only when that fits the budget.
    let in_memory_bytes = info.count * 400;
    if in_memory_bytes <= budget {
        let results = read_results(&results_path).map_err(|e| AppError::Failure(e.to_string()))?;
        let (set, solution) = from_results(&results);
        drop(results);
        write_previews(staged.path(), &set, &solution, cmd.image_size)?;
    } else {
        tracing::warn!(
            "{} surfels: the PLY and the picture are not written within --memory {}; use \
             `voxrad-shard export` and `voxrad render` with more memory",
            info.count,
            crate::outcore::budget::format_bytes(budget)
        );
    }
    Ok(())
}

/// Bytes the in-memory solver holds per surfel (surfel set, solver arrays, voxelization pieces at
/// their peak), measured by `benches/throughput.rs` (80 + about 280) plus a margin.
const BYTES_PER_SURFEL: f64 = 500.0;

/// Refuses, before any allocation, a solve that cannot fit in this machine's memory (a typo in
/// `--resolution` would otherwise end in the kernel killing the process hours later). Estimates
/// the surfel count from the surface area (a tunnel-free surface holds up to about two voxels per
/// voxel-sized patch) and the per-direction line arrays from the grid.
fn check_memory(scene: &crate::scene::Scene, cmd: &SolveCommand) -> Result<(), AppError> {
    let Ok(grid) = crate::voxel::voxelize::grid_for(scene, cmd.grid) else {
        return Ok(()); // voxelize reports the problem itself
    };
    let area: f64 = scene.triangles.iter().map(|t| t.area()).sum();
    let surfels = 2.0 * area / (grid.voxel_size * grid.voxel_size);
    let [x, y, z] = grid.dims.map(|d| d as f64);
    let longest = x.max(y).max(z);
    let lines = (x.max(y) + longest) * (y.max(z) + longest);
    let threads = if cmd.solve.threads == 0 {
        rayon::current_num_threads()
    } else {
        cmd.solve.threads
    } as f64;
    let need = surfels * BYTES_PER_SURFEL + lines * 4.0 * (threads + 1.0);
    let Some(available) = available_memory_bytes() else {
        return Ok(());
    };
    if need > available as f64 {
        let gib = |b: f64| b / (1u64 << 30) as f64;
        let fits = (longest * (available as f64 / need).sqrt())
            .floor()
            .max(2.0);
        return Err(AppError::BadInput(format!(
            "{}: at this grid ({} x {} x {} voxels of {:.4} scene units) the solve would need about \
             {:.1} GiB ({:.2e} surfels), but only {:.1} GiB of memory is available; use \
             --resolution {} or less",
            cmd.scene.display(),
            grid.dims[0],
            grid.dims[1],
            grid.dims[2],
            grid.voxel_size,
            gib(need),
            surfels,
            gib(available as f64),
            fits
        )));
    }
    Ok(())
}

/// `MemAvailable` from `/proc/meminfo` (Linux), in bytes.
fn available_memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

fn write_outputs(
    out: &Path,
    set: &SurfelSet,
    solution: &Solution,
    size: (u32, u32),
) -> Result<(), AppError> {
    let fail = |e: crate::output::OutputError| AppError::Failure(e.to_string());
    write_results(&out.join(crate::output::RESULTS_FILE), set, solution).map_err(fail)?;
    write_previews(out, set, solution, size)
}

/// `mpirun -n P voxrad solve SCENE --distribute data --memory SIZE`: every rank holds its share
/// of the scene in work files under the out directory, within `budget` (see
/// `distribute::ooc`); rank 0 writes the outputs and the checkpoints (those of the one-process
/// out-of-core solve, so either resumes the other's). An OBJ scene is first converted to a
/// shard set by every rank, each in its own work directory, within the budget.
fn run_solve_data_out_of_core(
    cmd: &SolveCommand,
    comm: &dyn Comm,
    budget: u64,
    started: Instant,
) -> Result<Report, AppError> {
    let start_rss = crate::output::report::peak_rss_bytes();
    create_out_dir(&cmd.out)?;
    if comm.rank() == 0 {
        checkpoint::remove_leftovers(&cmd.out);
    }
    let (_converted, shards) = if cmd.scene.is_dir() {
        (None, cmd.scene.clone())
    } else {
        let prefix = format!(".voxrad-shards-rank{}-", comm.rank());
        let (work, shards, _) = convert_obj(cmd, budget, &prefix)?;
        (Some(work), shards)
    };
    let source = ShardSetSource::open(&shards).map_err(ooc_error)?;
    let read_seconds = started.elapsed().as_secs_f64();
    // Simulate only what the scene calls for, as the one-process solvers do.
    let analysis = analyse_source(&source, budget)?;
    let mut shaped = analysis.shape(&cmd.solve);
    if shaped.direct != crate::solve::direct::DirectPass::Off && comm.rank() == 0 {
        // Not in this mode yet: said here and in the report, never dropped in silence.
        tracing::warn!(
            "the direct-light pass is not built for the data mode out of core yet: the small \
             emitters' light is gathered along the solve's {} directions only, where it aliases \
             into stripes (the Cornell box at resolution 128: 5.1 % mean error against 1.8 % \
             with the pass); one process with --memory, or --distribute data without \
             --memory, runs it",
            DirectionSet::with_count(shaped.directions).len()
        );
    }
    shaped.direct = crate::solve::direct::DirectPass::Off;
    let directions = DirectionSet::with_count(shaped.directions);
    let identity = out_of_core_identity(&source, &directions, &shaped, budget)?;
    let (resume, state) = open_checkpoint_on_rank0(cmd, comm, &identity)?;
    if comm.rank() == 0 {
        say_where_it_starts(cmd, &checkpoint::path_in(&cmd.out), state.is_some());
    }
    let mut saver = Saver::new(
        &cmd.out,
        identity,
        comm.rank() == 0,
        cmd.checkpoint.every,
        comm.size(),
        state.as_ref().map(|s| s.iteration),
    );
    let checkpoints = crate::distribute::ooc::DataOocCheckpoints {
        saver: &mut saver,
        resume,
        state,
    };
    let t = Instant::now();
    let solution = crate::distribute::ooc::solve_data_out_of_core(
        &source,
        &directions,
        &shaped,
        comm,
        budget,
        &cmd.out,
        Some(checkpoints),
    )
    .map_err(ooc_error)?;
    let solve_seconds = t.elapsed().as_secs_f64();
    let mut stats = solution.stats.clone();
    tracing::info!(
        iterations = stats.iterations,
        converged = stats.converged,
        residual = stats.residual,
        bytes_read = solution.bytes_read,
        bytes_written = solution.bytes_written,
        "solved out of core over {} ranks",
        comm.size()
    );
    let t = Instant::now();
    let info = source.info();
    let staged = if comm.rank() == 0 {
        let staged = stage(&cmd.out)?;
        write_streamed_outputs(cmd, &staged, info, budget, |f| {
            solution.for_each(&source, f)
        })?;
        Some(staged)
    } else {
        None
    };
    let write_seconds = t.elapsed().as_secs_f64();
    // Every rank's peak, after its last work.
    let ranks = comm.size();
    let mut peaks = vec![0.0; 2 * ranks];
    peaks[comm.rank()] = crate::output::report::peak_rss_bytes() as f64;
    peaks[ranks + comm.rank()] = start_rss as f64;
    comm.sum_in_place(&mut peaks);
    let starts = peaks.split_off(ranks);
    if let Some(data) = stats.data.as_mut() {
        for (r, rank) in data.out_of_core.iter_mut().enumerate() {
            rank.peak_rss_bytes = peaks[r] as u64;
            rank.start_rss_bytes = starts[r] as u64;
        }
    }
    let mut report = Report::from_counts(
        run_info(cmd, comm, info),
        solution.voxels,
        solution.surfels,
        info.grid.voxel_size,
        &stats,
    );
    let Some(staged) = staged else {
        // Only rank 0 writes the report.
        return Ok(report);
    };
    report.set_phase("read", read_seconds);
    report.set_phase("setup", solution.setup_seconds);
    report.set_phase("solve", solve_seconds);
    report.set_phase("reduce", stats.reduce_seconds);
    report.set_phase("write", write_seconds);
    report.out_of_core = Some(OutOfCoreReport::new(
        budget,
        solution.bytes_read,
        solution.bytes_written,
        solution.bands,
        solution.surfels * stats.directions as u64 * stats.iterations as u64,
    ));
    report.effects = analysis.effects(
        &cmd.solve,
        &stats,
        Some("the data mode out of core has no direct-light pass yet; its light is gathered along the solve's directions (one process with --memory, or --distribute data without --memory, runs it)"),
    );
    report.effects.push(Effect::new(
        "out of core",
        true,
        &format!(
            "every rank held its share of the surfels in files, within {} per rank",
            crate::outcore::budget::format_bytes(budget)
        ),
    ));
    report.set_total(started.elapsed().as_secs_f64());
    // What a node must have: the largest rank.
    report.peak_rss_bytes = peaks.iter().copied().fold(0.0, f64::max) as u64;
    report
        .write(staged.path())
        .map_err(|e| AppError::Failure(e.to_string()))?;
    drop(solution);
    publish(staged)?;
    checkpoint::remove_finished(&cmd.out);
    Ok(report)
}

/// Under `--resume`, the checkpoint in the out directory: rank 0 opens it and checks it against
/// the run (the file, if any, returned there), and every rank gets the state it holds; every
/// rank returns the same outcome, so none is left waiting in a collective call.
fn open_checkpoint_on_rank0(
    cmd: &SolveCommand,
    comm: &dyn Comm,
    identity: &Identity,
) -> Result<(Option<CheckpointFile>, Option<checkpoint::State>), AppError> {
    let path = checkpoint::path_in(&cmd.out);
    let (mut status, mut failure, mut file) = (0u64, None, None);
    if cmd.checkpoint.resume && comm.rank() == 0 && path.exists() {
        let opened = CheckpointFile::open(&path).and_then(|f| {
            checkpoint::check(&path, &f.header, identity, cmd.solve.max_iterations).map(|_| f)
        });
        match opened {
            Ok(f) => {
                file = Some(f);
                status = 1;
            }
            Err(e) => {
                failure = Some(e);
                status = 2;
            }
        }
    }
    match comm.max_u64(status) {
        0 => return Ok((None, None)),
        2 => {
            return Err(checkpoint_error(failure.unwrap_or_else(|| {
                checkpoint::let_rank_0_speak_first();
                CheckpointError::Bad {
                    path: path.clone(),
                    what: "rank 0 could not read it (see rank 0's message)".to_string(),
                }
            })))
        }
        _ => {}
    }
    // The state, from rank 0 to all (whole numbers and f64s: a sum with zeros keeps them).
    let mut words = [0.0f64; 7];
    let mut changes = Vec::new();
    if let Some(f) = &file {
        let state = &f.header.state;
        let (history, count, last_ratio) = state.extrapolation.parts();
        changes = history.to_vec();
        words = [
            state.iteration as f64,
            state.previous_change.is_some() as u8 as f64,
            state.previous_change.unwrap_or(0.0),
            count as f64,
            last_ratio.is_some() as u8 as f64,
            last_ratio.unwrap_or(0.0),
            changes.len() as f64,
        ];
    }
    comm.sum_in_place(&mut words);
    changes.resize(words[6] as usize, 0.0);
    comm.sum_in_place(&mut changes);
    // A checkpoint from inside an iteration (the one-process solver's, between two main axes)
    // is continued from that iteration's start: the same radiosity, so the same answer.
    let state = checkpoint::State {
        iteration: words[0] as u64,
        ranks: comm.size() as u32,
        previous_change: (words[1] == 1.0).then_some(words[2]),
        extrapolation: crate::checkpoint::ExtrapolationState::from_parts(
            changes,
            words[3] as usize,
            (words[4] == 1.0).then_some(words[5]),
        ),
        within: None,
        data_groups: 0,
    };
    Ok((file, Some(state)))
}

fn run_info(
    cmd: &SolveCommand,
    comm: &dyn Comm,
    info: &crate::outcore::source::SourceInfo,
) -> RunInfo {
    RunInfo {
        scene: cmd.scene.display().to_string(),
        mode: Mode::Data { compress: false }.name().to_string(),
        ranks: comm.size(),
        resolution: info.grid.dims.iter().copied().max().unwrap_or(0),
        tolerance: cmd.solve.tolerance.unwrap_or(0.0),
    }
}

/// The PLY and the picture.
fn write_previews(
    out: &Path,
    set: &SurfelSet,
    solution: &Solution,
    size: (u32, u32),
) -> Result<(), AppError> {
    let fail = |e: crate::output::OutputError| AppError::Failure(e.to_string());
    ply::write_ply(&out.join(crate::output::PLY_FILE), set, solution).map_err(fail)?;
    let camera = auto_camera(set, solution);
    render_png(
        &out.join(RENDER_FILE),
        set,
        solution,
        &camera,
        size.0,
        size.1,
    )
    .map_err(fail)?;
    Ok(())
}

/// Rebuilds a surfel set and solution from a results file, for rendering.
fn from_results(results: &Results) -> (SurfelSet, Solution) {
    let surfels = results
        .records
        .iter()
        .map(|r| Surfel {
            voxel: r.voxel,
            point: r.point,
            normal: r.normal,
            normal_id: 0,
            group: 0,
            area: r.area,
            material: [0, 0],
            extent: [[0.0; 3], [1.0; 3]],
        })
        .collect();
    let radiosity = results.records.iter().map(|r| r.radiosity).collect();
    let set = SurfelSet {
        grid: results.grid,
        surfels,
        normals: Vec::new(),
        materials: Vec::new(),
    };
    (
        set,
        Solution {
            radiosity,
            stats: Default::default(),
        },
    )
}

fn load_results(dir: &Path) -> Result<Results, AppError> {
    let path = dir.join(crate::output::RESULTS_FILE);
    if !path.exists() {
        return Err(AppError::BadInput(format!(
            "{}: no results file; is {} the --out directory of a finished `voxrad solve`?",
            path.display(),
            dir.display()
        )));
    }
    read_results(&path).map_err(|e| AppError::BadInput(e.to_string()))
}

/// A scene the `generate` command can write.
#[derive(Clone, Copy, Debug)]
pub enum GenerateScene {
    Cornell,
    Room {
        furniture: usize,
        seed: u64,
    },
    Building {
        rooms: (usize, usize, usize),
        seed: u64,
    },
    SealedRooms,
    Furnace,
    /// Two facing unit squares at distance 1 (emitter `E` = 1, receiver `rho` = 0.5).
    ParallelSquares,
    Office,
    WindowRoom,
    Corridor,
    ThinSlab {
        /// Thickness in voxels at resolution 128.
        thickness: f64,
        /// Degrees about y and about x.
        tilt: [f64; 2],
        light: crate::gen::SlabLight,
    },
    /// A twin of a furnace hard case under light from one place.
    HardTwin(crate::gen::HardTwin),
}

/// The scene and its probes: the generator's own for the interiors, else 300 points from
/// [`crate::study::probe_points`] (seed `0x5eed`, labelled with their material's name).
fn generated(which: GenerateScene) -> crate::gen::Interior {
    let scene = match which {
        GenerateScene::Cornell => crate::gen::cornell_box(),
        GenerateScene::Room { furniture, seed } => crate::gen::room(5.0, seed, furniture),
        GenerateScene::Building {
            rooms: (x, z, floors),
            seed,
        } => crate::gen::building(x, z, floors, seed),
        GenerateScene::SealedRooms => crate::gen::sealed_rooms(),
        GenerateScene::Furnace => crate::gen::furnace(1.0, 0.5),
        GenerateScene::ParallelSquares => {
            crate::gen::parallel_squares_reflecting(1.0, 1.0, 1.0, 0.5)
        }
        GenerateScene::Office => return crate::gen::office(),
        GenerateScene::WindowRoom => return crate::gen::window_room(),
        GenerateScene::Corridor => return crate::gen::corridor(),
        GenerateScene::ThinSlab {
            thickness,
            tilt,
            light,
        } => return crate::gen::thin_slab(thickness, tilt, light),
        GenerateScene::HardTwin(which) => return crate::gen::hard_twin(which),
    };
    let probes = crate::study::probe_points(&scene, 300, 0x5eed)
        .into_iter()
        .map(|(point, normal)| {
            // The material of the triangle the point was drawn on (the closest coplanar one).
            let surface = scene
                .triangles
                .iter()
                .filter(|t| {
                    let n = t.cross().normalize();
                    n.dot(normal) > 1.0 - 1e-9 && (point - t.vertices[0]).dot(n).abs() < 1e-9
                })
                .map(|t| scene.materials[t.material as usize].name.clone())
                .next()
                .unwrap_or_default();
            crate::gen::Probe {
                point,
                normal,
                surface,
            }
        })
        .collect();
    crate::gen::Interior { scene, probes }
}

fn write_text(path: &Path, text: &str) -> Result<(), AppError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    };
    crate::gen::obj_writer::write_atomically(&dir, path, |w| {
        std::io::Write::write_all(w, text.as_bytes())
    })
    .map_err(|e| AppError::Failure(format!("cannot write {}: {e}", path.display())))
}

/// `voxrad generate KIND --out FILE.obj [--probes P.csv] [--surfaces S.csv]`: writes the scene,
/// optionally its probe points (`x,y,z,nx,ny,nz`) and their surface labels (`probe,surface`),
/// and returns the triangle count.
pub fn run_generate(
    which: GenerateScene,
    out: &Path,
    probes: Option<&Path>,
    surfaces: Option<&Path>,
) -> Result<usize, AppError> {
    if out
        .extension()
        .is_none_or(|e| !e.eq_ignore_ascii_case("obj"))
    {
        return Err(AppError::BadInput(format!(
            "{}: the output must be an .obj file",
            out.display()
        )));
    }
    let crate::gen::Interior {
        scene,
        probes: points,
    } = generated(which);
    crate::gen::write_obj(&scene, out)
        .map_err(|e| AppError::Failure(format!("cannot write {}: {e}", out.display())))?;
    if let Some(path) = probes {
        write_text(path, &crate::gen::interiors::probes_csv(&points))?;
    }
    if let Some(path) = surfaces {
        write_text(path, &crate::gen::interiors::surfaces_csv(&points))?;
    }
    Ok(scene.triangles.len())
}

/// `voxrad render DIR --out IMG [--camera ...]`.
pub fn run_render(
    dir: &Path,
    out: &Path,
    camera: Option<&str>,
    size: (u32, u32),
) -> Result<(), AppError> {
    let results = load_results(dir)?;
    let (set, solution) = from_results(&results);
    let camera = match camera {
        Some(text) => Camera::parse(text).map_err(|e| AppError::BadInput(e.to_string()))?,
        None => auto_camera(&set, &solution),
    };
    render_png(out, &set, &solution, &camera, size.0, size.1)
        .map_err(|e| AppError::Failure(e.to_string()))
}

/// `voxrad probe DIR --points P.csv`: rows on standard output (or into `out`).
pub fn run_probe(dir: &Path, points: &Path, out: Option<&Path>) -> Result<(), AppError> {
    let results = load_results(dir)?;
    let rows = probe::probe(&results, points).map_err(|e| AppError::BadInput(e.to_string()))?;
    match out {
        Some(path) => {
            probe::write_probe_csv(path, &rows).map_err(|e| AppError::Failure(e.to_string()))
        }
        None => {
            let stdout = std::io::stdout();
            let mut lock = stdout.lock();
            probe::write_rows(&mut lock, &rows, false)
                .map_err(|e| AppError::Failure(format!("cannot write to standard output: {e}")))
        }
    }
}

/// `voxrad study SCENE --out DIR [--quick | --presets]`: SCENE is a built-in name (`furnace`,
/// `cornell`), an .obj file, or a directory of reference data (`scene.obj`, `reference.csv`).
/// Writes `study.csv`, `study.md` and `study.png` and returns the study.
pub fn run_study(
    scene: &str,
    out: &Path,
    quick: bool,
    presets: bool,
    threads: usize,
) -> Result<crate::study::Study, AppError> {
    use crate::study::{Plan, StudyScene};
    let load = |path: &Path| {
        load_obj(path).map_err(|e| {
            if e.is_bad_input() {
                AppError::BadInput(e.to_string())
            } else {
                AppError::Failure(e.to_string())
            }
        })
    };
    let path = Path::new(scene);
    let studied = match StudyScene::builtin(scene) {
        Some(s) => s,
        None if path.is_dir() => {
            let reference = crate::study::reference::Reference::load(path)
                .map_err(|e| AppError::BadInput(e.to_string()))?;
            StudyScene {
                name: scene.to_string(),
                scene: load(&path.join("scene.obj"))?,
                analytic: None,
                path_traced: Some(reference),
            }
        }
        None if path.exists() => StudyScene {
            name: scene.to_string(),
            scene: load(path)?,
            analytic: None,
            path_traced: None,
        },
        None => {
            return Err(AppError::BadInput(format!(
                "{scene}: neither a built-in scene (furnace, cornell), an existing .obj file nor \
                 a directory of reference data"
            )))
        }
    };
    let mut plan = if quick {
        Plan::quick()
    } else if presets {
        Plan::presets_only()
    } else {
        Plan::full()
    };
    plan.threads = threads;
    let study = crate::study::run(&studied, &plan, |r| {
        tracing::info!(
            knob = r.knob,
            resolution = r.settings.resolution,
            directions = r.directions_used,
            tolerance = r.settings.tolerance,
            iterations = r.iterations,
            seconds = format!("{:.2}", r.seconds),
            mean_error = format!("{:.2e}", r.mean_error),
            "study run"
        );
    })
    .map_err(|e| AppError::BadInput(format!("{scene}: {e}")))?;
    crate::study::write(&study, out).map_err(AppError::Failure)?;
    Ok(study)
}

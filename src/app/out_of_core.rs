//! `voxrad solve` out of core on one process: a shard set, or an OBJ scene converted into a
//! temporary one, solved within `--memory` (`crate::outcore`), its outputs streamed.

use super::*;

/// The out-of-core solve, with checkpoints in the out directory, from the one there under
/// `--resume` (checked against the run before any work file is made).
/// [`crate::solve::effects::analyse_sides`] of the surfels `source` streams.
pub(super) fn analyse_source(
    source: &dyn SurfelSource,
    budget: u64,
) -> Result<crate::solve::effects::Analysis, AppError> {
    let info = source.info();
    let window = crate::outcore::MemoryPlan::new(budget, info.grid.dims, 1, 0)
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

pub(super) fn solve_out_of_core_in(
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
    // Between two directions too (see `outcore::solver`).
    .within(true)
    .write_factor(cmd.checkpoint.write_factor);
    let checkpoints = OocCheckpoints {
        saver: &mut saver,
        resume,
    };
    let parent = work_parent(cmd)?;
    solve_out_of_core_checkpointed(source, directions, options, budget, &parent, checkpoints)
        .map_err(ooc_error)
}

/// What names an out-of-core run in its checkpoints (one process or the data mode: the same
/// radiosity, so either resumes the other's).
pub(super) fn out_of_core_identity(
    source: &dyn SurfelSource,
    directions: &DirectionSet,
    options: &SolveOptions,
    budget: u64,
) -> Result<Identity, AppError> {
    let info = source.info();
    let window = crate::outcore::MemoryPlan::new(budget, info.grid.dims, 1, 0)
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
        chebyshev: options.chebyshev,
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

/// `voxrad solve SCENE.obj --memory SIZE`: the scene is converted to a temporary shard set (the
/// streaming conversion of `voxrad-shard convert`, within the same budget) and solved from it.
pub(super) fn run_solve_obj_out_of_core(
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
/// `prefix`) inside the out directory (or `--work-dir`'s, [`work_parent`]): the streaming conversion of `voxrad-shard convert`,
/// within `budget`. Returns the directory (removed when dropped), the set and its summary.
pub(super) fn convert_obj(
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
    let parent = work_parent(cmd)?;
    let work = tempfile::Builder::new()
        .prefix(prefix)
        .tempdir_in(&parent)
        .map_err(|e| {
            AppError::Failure(format!(
                "cannot create a work directory in {}: {e}",
                parent.display()
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

/// Solves `source` out of core and writes the results file (and, when the results fit the
/// budget, the PLY and the picture) into a staging directory; returns the report, not yet
/// written, and the staged outputs.
pub(super) fn solve_out_of_core_to(
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
    report.set_phase("write", write_seconds);
    report.effects = analysis.effects(&cmd.solve, &stats.solve);
    report.add_out_of_core(
        budget,
        stats.bytes_read,
        stats.bytes_written,
        stats.bands,
        stats.surfels,
        &stats.solve,
        &format!(
            "surfels kept in files; everything that grows with the scene held within {}",
            crate::outcore::budget::format_bytes(budget)
        ),
    );
    Ok((report, staged))
}

/// Bytes a surfel the baked meshes need at their peak (see `write_streamed_outputs`).
const BAKE_BYTES_PER_SURFEL: u64 = 1000;

/// Writes the results file from `each` (which calls its argument for every surfel in canonical
/// order) and, when the results fit `budget`, the PLY and the picture, into `staged`.
pub(super) fn write_streamed_outputs(
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
    let mut writer = ResultsWriter::create(&results_path, &info.grid, info.count, &info.materials)
        .map_err(fail)?;
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
        // The bake holds the results, the mesh and one plane's bookkeeping at a time: about
        // 720 bytes a surfel measured on a building of 298,511 surfels (214 MB).
        let mesh = if !cmd.scene.is_file() {
            None
        } else if info.count * BAKE_BYTES_PER_SURFEL <= budget {
            let scene = load_scene_for_baking(&cmd.scene)?;
            Some(write_baked(staged.path(), &scene, &results)?)
        } else {
            tracing::warn!(
                "{} surfels: the baked meshes are not written within --memory {}; use `voxrad \
                 bake` with more memory",
                info.count,
                crate::outcore::budget::format_bytes(budget)
            );
            None
        };
        let (set, solution) = from_results(&results);
        drop(results);
        write_previews(
            staged.path(),
            &set,
            &solution,
            mesh.as_ref(),
            cmd.image_size,
        )?;
    } else {
        tracing::warn!(
            "{} surfels: the PLY, the picture and the baked meshes are not written within \
             --memory {}; use `voxrad-shard export`, `voxrad render` and `voxrad bake` with \
             more memory",
            info.count,
            crate::outcore::budget::format_bytes(budget)
        );
    }
    Ok(())
}

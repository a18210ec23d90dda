//! `voxrad solve` in memory: read and voxelize the scene (or read a shard set whole), shape
//! the options to what it calls for, solve on one process or under MPI in every mode, write the
//! results, previews and report. A solve that cannot fit this machine's memory is refused first.

use super::*;

/// The in-memory solve of an OBJ scene (or, under MPI, a shard set every rank reads whole):
/// read, voxelize, shape the options to the scene, solve, write the outputs and the report.
pub(super) fn solve_in_memory_from_scene(
    cmd: &SolveCommand,
    comm: &dyn Comm,
    mode: Mode,
    started: Instant,
) -> Result<Report, AppError> {
    // The scene's triangles are kept for the baked mesh (a shard set has none).
    let (set, scene, read_seconds, voxelize_seconds) = if cmd.scene.is_dir() {
        // Distributed: every rank reads the whole shard set (its own copy, or a shared one)
        // into memory.
        let set = load_shard_set(&cmd.scene)?;
        (set, None, started.elapsed().as_secs_f64(), 0.0)
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
        (set, Some(scene), read_seconds, t.elapsed().as_secs_f64())
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
        write_outputs(
            staging.path(),
            &set,
            &solution,
            scene.as_ref(),
            cmd.image_size,
        )?;
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
    report.effects = analysis.effects(&cmd.solve, stats);
    report.set_phase("read", read_seconds);
    report.set_phase("voxelize", voxelize_seconds);
    report.set_phase("write", write_seconds);
    report.set_total(started.elapsed().as_secs_f64());
    // The other ranks leave their cores to rank 0's writing threads meanwhile.
    comm.wait_quietly();
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
pub(super) fn solve_in_memory(
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
        .with_chebyshev(options.chebyshev)
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
    .within(true)
    .write_factor(cmd.checkpoint.write_factor);
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

/// A whole shard set read into memory, in the set's own order (each shard checked as it is
/// read).
pub(super) fn load_shard_set(dir: &Path) -> Result<SurfelSet, AppError> {
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
pub(super) fn run_solve_shard_set(
    cmd: &SolveCommand,
    started: Instant,
) -> Result<Report, AppError> {
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

/// Bytes the in-memory solver holds per surfel (surfel set, solver arrays, voxelization pieces at
/// their peak), measured by `benches/throughput.rs` (80 + about 280) plus a margin.
pub(super) const BYTES_PER_SURFEL: f64 = 500.0;

/// Refuses, before any allocation, a solve that cannot fit in this machine's memory (a typo in
/// `--resolution` would otherwise end in the kernel killing the process hours later). Estimates
/// the surfel count from the surface area (a tunnel-free surface holds up to about two voxels per
/// voxel-sized patch) and the per-direction line arrays from the grid.
pub(super) fn check_memory(
    scene: &crate::scene::Scene,
    cmd: &SolveCommand,
) -> Result<(), AppError> {
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
pub(super) fn available_memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// The results file, the previews and, from an OBJ scene, the baked meshes.
pub(super) fn write_outputs(
    out: &Path,
    set: &SurfelSet,
    solution: &Solution,
    scene: Option<&crate::scene::Scene>,
    size: (u32, u32),
) -> Result<(), AppError> {
    let fail = |e: crate::output::OutputError| AppError::Failure(e.to_string());
    write_results(&out.join(crate::output::RESULTS_FILE), set, solution).map_err(fail)?;
    let mesh = match scene {
        Some(scene) => {
            let results = Results::from_solution(set, solution).map_err(fail)?;
            Some(write_baked(out, scene, &results)?)
        }
        None => {
            tracing::info!(
                "a shard set holds no triangles: no baked mesh (`voxrad bake DIR --scene \
                 SCENE.obj` makes one)"
            );
            None
        }
    };
    write_previews(out, set, solution, mesh.as_ref(), size)
}

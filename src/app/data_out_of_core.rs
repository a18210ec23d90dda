//! `mpirun ... voxrad solve --distribute data|hybrid --memory SIZE`: every rank holds its share
//! of the scene in work files (`crate::distribute::ooc`); rank 0 writes the outputs and
//! checkpoints.

use super::*;

/// `mpirun -n P voxrad solve SCENE --distribute data --memory SIZE` (`groups` 1; the hybrid
/// mode with more): every rank holds its share of the scene (of its group's copy of it) in
/// work files under the out directory, within `budget` (see `distribute::ooc`); rank 0 writes
/// the outputs and the checkpoints (at iteration boundaries those of the one-process
/// out-of-core solve, so either resumes the other's; inside an iteration a layout by groups that
/// a run of as many groups continues). An OBJ scene is first converted to a shard set by every
/// rank, each in its own work directory, within the budget.
pub(super) fn run_solve_data_out_of_core(
    cmd: &SolveCommand,
    comm: &dyn Comm,
    groups: usize,
    budget: u64,
    started: Instant,
) -> Result<Report, AppError> {
    let start_rss = crate::output::report::peak_rss_bytes();
    create_out_dir(&cmd.out)?;
    if comm.rank() == 0 {
        checkpoint::remove_leftovers(&cmd.out);
    }
    // Under --work-dir each node has its own (a local disk): every rank clears it, before any
    // rank makes a work directory there.
    let work_parent = work_parent(cmd)?;
    if work_parent != cmd.out {
        checkpoint::remove_leftovers(&work_parent);
    }
    // No rank makes its work directories before rank 0 has removed a killed run's (it would
    // take a new one for a leftover).
    comm.max_u64(0);
    let (_converted, shards) = if cmd.scene.is_dir() {
        (None, cmd.scene.clone())
    } else {
        let prefix = format!(".voxrad-shards-rank{}-", comm.rank());
        let (work, shards, _) = convert_obj(cmd, budget, &prefix)?;
        (Some(work), shards)
    };
    // Rank 0 reads the whole set (the analysis below, the closure verdict, the direct-light
    // pass, the results); another rank reads only its slice, so its node may hold only the
    // shards of that slice (staged on a node-local disk).
    let source = if comm.rank() == 0 {
        ShardSetSource::open(&shards)
    } else {
        ShardSetSource::open_present(&shards)
    }
    .map_err(ooc_error)?;
    let read_seconds = started.elapsed().as_secs_f64();
    // Simulate only what the scene calls for, as the one-process solvers do; rank 0 reads the
    // scene's materials for every rank.
    let analysis = analysis_from_rank0(comm, &source, budget)?;
    let shaped = analysis.shape(&cmd.solve);
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
    )
    // Inside iterations too, as every path (`distribute::ooc::within`).
    .within(true)
    .write_factor(cmd.checkpoint.write_factor);
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
        groups,
        budget,
        &work_parent,
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
    // The other ranks leave their cores to rank 0's writing threads meanwhile.
    comm.wait_quietly();
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
        run_info(cmd, comm, groups, info),
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
    report.effects = analysis.effects(&cmd.solve, &stats);
    report.add_out_of_core(
        budget,
        solution.bytes_read,
        solution.bytes_written,
        solution.bands,
        solution.surfels,
        &stats,
        &format!(
            "every rank held its share of the surfels in files, within {} per rank",
            crate::outcore::budget::format_bytes(budget)
        ),
    );
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
pub(super) fn open_checkpoint_on_rank0(
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
    let mut words = [0.0f64; 15];
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
            // Not inside an iteration the solver now walks in another order.
            (state.within.is_some() && !state.walked_otherwise()) as u8 as f64,
            state.within.unwrap_or(0) as f64,
            state.data_groups as f64,
            state.axis_in_progress as u8 as f64,
            // The Chebyshev semi-iteration's state (its update count is a whole number well
            // below 2^53, its ratio an f64 kept exactly by a sum with zeros).
            state.extrapolation.chebyshev.is_some() as u8 as f64,
            state.extrapolation.chebyshev.map_or(0.0, |c| c.0),
            state.extrapolation.chebyshev.map_or(0.0, |c| c.1 as f64),
            state.sums_in_f32 as u8 as f64,
        ];
    }
    comm.sum_in_place(&mut words);
    changes.resize(words[6] as usize, 0.0);
    comm.sum_in_place(&mut changes);
    // Where inside an iteration it stands: the solver continues there when the layout is its
    // own (`distribute::ooc::within`), else from that iteration's start (the same radiosity,
    // so the same answer).
    let state = checkpoint::State {
        iteration: words[0] as u64,
        ranks: comm.size() as u32,
        previous_change: (words[1] == 1.0).then_some(words[2]),
        extrapolation: crate::checkpoint::ExtrapolationState {
            chebyshev: (words[11] == 1.0).then_some((words[12], words[13] as u64)),
            ..crate::checkpoint::ExtrapolationState::from_parts(
                changes,
                words[3] as usize,
                (words[4] == 1.0).then_some(words[5]),
            )
        },
        within: (words[7] == 1.0).then_some(words[8] as u64),
        data_groups: words[9] as u32,
        axis_in_progress: words[10] == 1.0,
        sums_in_f32: words[14] == 1.0,
        walked_forwards: false,
    };
    Ok((file, Some(state)))
}

pub(super) fn run_info(
    cmd: &SolveCommand,
    comm: &dyn Comm,
    groups: usize,
    info: &crate::outcore::source::SourceInfo,
) -> RunInfo {
    let mode = match groups {
        1 => Mode::Data { compress: false },
        _ => Mode::Hybrid {
            groups,
            compress: false,
        },
    };
    RunInfo {
        scene: cmd.scene.display().to_string(),
        mode: mode.name().to_string(),
        ranks: comm.size(),
        resolution: info.grid.dims.iter().copied().max().unwrap_or(0),
        tolerance: cmd.solve.tolerance.unwrap_or(0.0),
    }
}

/// [`analyse_source`] on rank 0, the same on every rank: the others receive it (added over
/// ranks, to which they bring zeros; every field is exact in an f64).
fn analysis_from_rank0(
    comm: &dyn Comm,
    source: &ShardSetSource,
    budget: u64,
) -> Result<crate::solve::effects::Analysis, AppError> {
    let mut a = if comm.rank() == 0 {
        analyse_source(source, budget)?
    } else {
        crate::solve::effects::Analysis {
            emitters: false,
            reflective: false,
            grey: false,
            max_reflectance: 0.0,
            emitting_surfels: 0,
            surfels: 0,
            longest_axis: 0,
            inside_sides: 0,
        }
    };
    let flag = |b: bool| if b { 1.0 } else { 0.0 };
    let mut fields = [
        flag(a.emitters),
        flag(a.reflective),
        flag(a.grey),
        a.max_reflectance,
        a.emitting_surfels as f64,
        a.surfels as f64,
        a.longest_axis as f64,
        a.inside_sides as f64,
    ];
    comm.sum_in_place(&mut fields);
    a.emitters = fields[0] > 0.0;
    a.reflective = fields[1] > 0.0;
    a.grey = fields[2] > 0.0;
    a.max_reflectance = fields[3];
    a.emitting_surfels = fields[4] as usize;
    a.surfels = fields[5] as usize;
    a.longest_axis = fields[6] as u32;
    a.inside_sides = fields[7] as usize;
    Ok(a)
}

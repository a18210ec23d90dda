//! The out-of-core solver, a sweep of the one iteration loop (`solve::iterate`): directions
//! grouped by main axis (walked backwards in even iterations, [`walk_of_iteration`]), each
//! solved band by band ([`super::band`]); then the light gathered in
//! the three copies is brought to canonical order, `B = E + rho H / S(n)` is computed there,
//! and the new radiosity is sent to each copy, in its order, just before that copy's directions
//! ([`super::scatter`]): the copies share one radiosity file. As in memory, a grey
//! scene gathers one channel, and the tail extrapolation (`solve::accelerate`) runs on the
//! canonical file chunk by chunk, from the radiosity the update replaced (kept in one more work
//! file). Every surfel is updated by `solve::update`, as in every other loop.
//!
//! **The direct-light pass** ([`super::direct`]) runs once after the first update (`B = E`),
//! into a direct-light file in canonical order that every update reads (`B` gains `rho` times
//! it); the axis copies then receive `B - E` instead of `B`, written beside the canonical
//! radiosity at the start of each iteration, and the bands gather only the reflected light, as
//! in memory.
//!
//! **Directions gathered together.** Lines of the same slope along `v` put every surfel in the
//! same column, so such directions (the walk puts them next to each other; a cube direction
//! set has about `2 N + 1` of them in a row) have the same bands. One pass gathers them
//! together ([`gathered_together`]): each band's records and light are read, and its light
//! written, once, and the directions' lines are searched (their links recorded), or their
//! links replayed, on it one after the other in walk order, the same terms in the same order
//! as direction after direction. The steps of the directions after the first do nothing, and a
//! checkpoint waits for the pass's end.
//!
//! Checkpoints ([`solve_out_of_core_checkpointed`]) hold the canonical radiosity file and the
//! stopping rule's last change; everything else in the work files is rebuilt on resume (the axis
//! copies from the source, the radiosity they share from the canonical file). Inside an iteration
//! (`Saver::within`) a checkpoint can be written between any two passes, when one is due
//! or on a stop signal ([`Position`]: the axes folded and the directions done of the next).
//! Between two main axes it adds the canonical sum of the light gathered by the axes done (the
//! sum file's f32 values, written as f64). Inside an axis it also holds that axis's light so far,
//! brought to canonical order into an array of its own (`State::axis_in_progress`): folded into
//! the sum early, it would be added in another order than the uninterrupted run adds it. A
//! resume puts the sum back, scatters the axis's light back into its copy's order and goes on
//! with the next direction, adding to it; the f32 values, kept exactly through the checkpoint's
//! f64, give the same bits.
//!
//! That light is whole on disk between any two passes because the two shared gathered files
//! are used in turn (`WorkSet::gathered`): a pass reads the light of the directions before it
//! from one and writes it, with its own, to the other. Stop signals are heard between
//! directions (the loop's agreement) and between bands inside a pass (on a large scene one
//! direction can take minutes); a pass stopped so is abandoned, and the file it read from still
//! holds the directions before it.

use super::band::{BandBuffers, BandTimes, CopyFiles, DirectionPass};
use super::budget::MemoryPlan;
use super::files::{
    decode_gathered, decode_light32, decode_radiosity, encode_light32, encode_radiosity, Gathered,
    IoCounters, Radiosity, RecordFile, SeqReader, SeqWriter, GATHER_LEN, LIGHT32_LEN,
    RADIOSITY_LEN,
};
use super::framed::{FrameBuffers, FramedStatics};
use super::links::LinkStore;
use super::packed_index::IndexReader;
use super::scatter::{ChunkReader, Scatter};
use super::source::SurfelSource;
use super::workset::{self, AxisCopy, WorkSet};
use super::OocError;
use crate::checkpoint::{CheckpointError, CheckpointFile, Saver, State};
use crate::geometry::directions::{Direction, DirectionSet};
use crate::solve::closed::{ClosureSums, Scales};
use crate::solve::iterate::{iterate, Start, Sweep};
use crate::solve::normalize::cosine_sums;
use crate::solve::update::{add_power, carried, update_surfel};
use crate::solve::{SolveOptions, SolveStats};
use crate::voxel::Surfel;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// What an out-of-core solve did, beyond the in-memory solver's statistics.
#[derive(Clone, Debug, Default)]
pub struct OocStats {
    pub solve: SolveStats,
    pub voxels: u64,
    pub surfels: u64,
    pub budget_bytes: u64,
    /// Bytes read from and written to the shard set and work files.
    pub bytes_read: u64,
    pub bytes_written: u64,
    /// Seconds making the axis copies, reading bands, writing gathered light, and bringing
    /// results between orders at the end of each iteration.
    pub setup_seconds: f64,
    pub read_seconds: f64,
    pub write_seconds: f64,
    pub update_seconds: f64,
    /// Bands solved (over all directions and iterations), and the columns among them too big
    /// for one band, solved in blocks.
    pub bands: u64,
    pub tiled_columns: u64,
    /// Bands replayed from kept links, and the groups their light was read and written in
    /// (several bands of a direction at once where the budget holds them).
    pub replayed_bands: u64,
    pub replay_groups: u64,
    /// Passes that gathered several directions together (searching or replaying), and the
    /// directions they gathered beyond one each (see `gathered_together`).
    pub joint_passes: u64,
    pub joint_directions: u64,
}

/// The result: statistics and the work set whose canonical radiosity file holds the answer.
pub struct OocSolution {
    pub stats: OocStats,
    work: WorkSet,
    io_bytes: usize,
}

impl OocSolution {
    /// Calls `f(surfel, radiosity)` for every surfel of `source` in canonical order.
    pub fn for_each<F>(&self, source: &dyn SurfelSource, mut f: F) -> Result<(), OocError>
    where
        F: FnMut(&Surfel, &Radiosity) -> Result<(), OocError>,
    {
        let mut radiosity =
            SeqReader::<RADIOSITY_LEN>::open(&self.work.canonical_radiosity, self.io_bytes)?;
        for s in source.stream(self.io_bytes as u64)? {
            let s = s?;
            let b = decode_radiosity(&radiosity.expect_record()?);
            f(&s, &b)?;
        }
        Ok(())
    }

    /// The radiosity of every surfel, in canonical order (for tests and small scenes).
    pub fn radiosity(&self) -> Result<Vec<Radiosity>, OocError> {
        let mut reader =
            SeqReader::<RADIOSITY_LEN>::open(&self.work.canonical_radiosity, self.io_bytes)?;
        let mut out = Vec::with_capacity(self.work.count as usize);
        while let Some(r) = reader.next_record()? {
            out.push(decode_radiosity(&r));
        }
        Ok(out)
    }
}

/// The checkpoints of one out-of-core solve: where they go, and the one it starts from.
pub struct OocCheckpoints<'a> {
    pub saver: &'a mut Saver,
    /// Opened and checked against the run already (`checkpoint::check`).
    pub resume: Option<CheckpointFile>,
}

/// Solves `source` out of core with work files in a temporary directory under `work_parent`.
pub fn solve_out_of_core(
    source: &dyn SurfelSource,
    directions: &DirectionSet,
    options: &SolveOptions,
    budget_bytes: u64,
    work_parent: &Path,
) -> Result<OocSolution, OocError> {
    solve_in_pool(source, directions, options, budget_bytes, work_parent, None)
}

/// As [`solve_out_of_core`], saving checkpoints at iteration boundaries and starting from
/// `checkpoints.resume` if given; stops between directions on SIGTERM or SIGINT with
/// [`OocError::Interrupted`].
pub fn solve_out_of_core_checkpointed(
    source: &dyn SurfelSource,
    directions: &DirectionSet,
    options: &SolveOptions,
    budget_bytes: u64,
    work_parent: &Path,
    checkpoints: OocCheckpoints,
) -> Result<OocSolution, OocError> {
    solve_in_pool(
        source,
        directions,
        options,
        budget_bytes,
        work_parent,
        Some(checkpoints),
    )
}

fn solve_in_pool(
    source: &dyn SurfelSource,
    directions: &DirectionSet,
    options: &SolveOptions,
    budget_bytes: u64,
    work_parent: &Path,
    checkpoints: Option<OocCheckpoints>,
) -> Result<OocSolution, OocError> {
    let threads = if options.threads == 0 {
        rayon::current_num_threads()
    } else {
        options.threads
    };
    one_malloc_arena();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| OocError::Threads {
            threads,
            message: e.to_string(),
        })?;
    pool.install(|| {
        run(
            source,
            directions,
            options,
            budget_bytes,
            work_parent,
            (threads, &pool),
            checkpoints,
        )
    })
}

/// The order the directions are solved in: grouped by main axis `m` (each axis reads its own
/// copy), and within an axis by the slope of their lines along `v` (then along `u`), so that
/// consecutive directions shift the line columns `j` of every layer little. The data mode out of
/// core walks the same order (its answer is this solver's bit for bit), where columns are what
/// ranks own: few surfels change rank from one direction to the next.
pub fn walk_by_axis(directions: &DirectionSet) -> Vec<Vec<usize>> {
    (0..3)
        .map(|m| {
            let mut axis: Vec<usize> = (0..directions.len())
                .filter(|&k| crate::geometry::lines::axes(directions.directions[k].vector).0 == m)
                .collect();
            let slope = |k: usize| {
                let d = directions.directions[k].vector;
                let (main, u, v) = crate::geometry::lines::axes(d);
                // Lines run through the layers in increasing order of the main axis.
                let c = d[main].abs() as f64;
                let sign = d[main].signum() as f64;
                (sign * d[v] as f64 / c, sign * d[u] as f64 / c)
            };
            axis.sort_by(|&x, &y| slope(x).partial_cmp(&slope(y)).unwrap().then(x.cmp(&y)));
            axis
        })
        .collect()
}

/// One iteration's walk: its main axes in the order they are solved, each with its directions
/// in the order they are solved.
pub type Walk = Vec<(usize, Vec<usize>)>;

/// Whether iteration `iteration` (counted from 1) walks backwards (see [`walk_of_iteration`]).
pub fn walks_backwards(iteration: usize) -> bool {
    iteration % 2 == 0
}

/// The walk of iteration `iteration` (counted from 1) over `by_axis` ([`walk_by_axis`]): odd
/// iterations walk it as it is, even ones backwards (the last axis first, its directions from
/// the last). Every iteration after the first so begins on the main axis, and with the
/// direction, that the one before ended on: the data mode out of core finds its held records
/// in that axis's copy order already and sorts them once fewer per iteration
/// (`distribute::ooc`). Every out-of-core path walks these, so that their answers stay the same
/// bits; resuming inside an iteration takes the walk of the iteration resumed.
pub fn walk_of_iteration(by_axis: &[Vec<usize>], iteration: usize) -> Walk {
    let mut walk: Walk = by_axis.iter().cloned().enumerate().collect();
    if walks_backwards(iteration) {
        walk.reverse();
        for (_, axis) in &mut walk {
            axis.reverse();
        }
    }
    walk
}

/// Directions gathered together at most: their links files are read or written side by side,
/// each through its share of one direction's buffer.
pub(crate) const MOST_TOGETHER: usize = 16;

/// The directions a pass from direction `k` of an axis's walk `axis` gathers: that one alone,
/// or with the directions after it that can share its pass, band by band, each band's records
/// and light read and written once for all of them instead of once each. They must have the
/// same bands (`DirectionPass::band_cuts`) holding the same surfels in the same order: lines
/// of the same slope along `v` (the walk puts them next to each other) put every surfel in the
/// same column. And their links must be all kept (replayed) or none (searched, and recorded).
/// Each band's lines are gathered direction after direction in walk order, so each surfel adds
/// the same terms in the same order as in passes of one direction.
pub(crate) fn gathered_together(
    pass: &DirectionPass,
    directions: &DirectionSet,
    axis: &[usize],
    k: usize,
    links: &LinkStore,
) -> Vec<usize> {
    let first = axis[k];
    let mut together = vec![first];
    let mut columns = Vec::new();
    let vector = |d: usize| directions.directions[d].vector;
    let Some(cuts) = pass.band_cuts(&directions.directions[first], &mut columns) else {
        return together;
    };
    let slope = v_slope(vector(first));
    let kept = links.is_kept(first);
    for &d in &axis[k + 1..] {
        let (b, c) = v_slope(vector(d));
        if together.len() == MOST_TOGETHER || links.is_kept(d) != kept || b * slope.1 != slope.0 * c
        {
            break;
        }
        if pass
            .band_cuts(&directions.directions[d], &mut columns)
            .as_ref()
            != Some(&cuts)
        {
            break;
        }
        together.push(d);
    }
    together
}

/// The slope along `v` of the lines of direction `vector`, as `(b, c)` for `b / c` (`c > 0`,
/// the main axis's component): the column shift of every layer depends on it alone
/// (`geometry::lines`).
pub(crate) fn v_slope(vector: [i64; 3]) -> (i64, i64) {
    let (main, _, v) = crate::geometry::lines::axes(vector);
    let sign = vector[main].signum();
    (sign * vector[v], sign * vector[main])
}

/// Makes glibc's malloc serve every thread from one arena. By default each thread may get its
/// own arena, which reserves 64 MiB of address space: under an address-space limit below that,
/// creating it fails, and glibc retries (an `mmap` that fails) on many later allocations. Under
/// a 48 MiB limit that made a solve ten times slower, mostly in the kernel. The solver's hot
/// loops do not allocate, so one arena costs nothing measurable.
///
/// glibc fixes the arena limit when a second thread first allocates, so this must come before
/// any thread is started: `voxrad solve` calls it first thing for a solve out of core, and the
/// solvers again (for library callers). Called only after the signal watchdog had started,
/// it did not take on one build (the building of `tests/memory_limit.rs` under a 32 MiB limit
/// spent 330 s instead of 12 in its set-up, in failed `mmap`s of new arenas).
pub fn one_malloc_arena() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `mallopt` only changes allocator settings; M_ARENA_MAX takes any positive count.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, 1);
    }
}

fn run(
    source: &dyn SurfelSource,
    directions: &DirectionSet,
    options: &SolveOptions,
    budget_bytes: u64,
    work_parent: &Path,
    (threads, pool): (usize, &rayon::ThreadPool),
    mut checkpoints: Option<OocCheckpoints>,
) -> Result<OocSolution, OocError> {
    let info = source.info();
    let plan = MemoryPlan::new(budget_bytes, info.grid.dims, threads, info.count)?;
    tracing::info!(
        budget = super::budget::format_bytes(budget_bytes),
        band_surfels = plan.band_surfels,
        sort_records = plan.sort_records,
        chunk_surfels = plan.chunk_surfels,
        "out-of-core plan"
    );
    let mut io = IoCounters::default();
    let started = Instant::now();
    // What the solve's own files add to the work set's: the direct-light files counted
    // wherever the pass may run, until the emitting surfels are counted below.
    let direct_may_run =
        options.direct.may_run(directions.len()) && info.materials.iter().any(|m| m.is_emitter());
    let also = workset::solve_files_per_surfel(options.accelerate, direct_may_run);
    let work = workset::build(source, &plan, work_parent, also, &mut io)?;
    let mut stats = OocStats {
        voxels: work.voxels,
        surfels: work.count,
        budget_bytes,
        setup_seconds: started.elapsed().as_secs_f64(),
        ..Default::default()
    };
    let t = Instant::now();
    let cosine_sum = cosine_sums(&info.normals, directions);
    stats.solve.normalize_seconds = t.elapsed().as_secs_f64();
    stats.solve.directions = directions.len();
    stats.solve.threads = threads;

    // B = E to start with; tells whether anything emits.
    let t = Instant::now();
    let first = update(
        source,
        &work,
        &plan,
        &cosine_sum,
        (false, 3),
        None,
        None,
        (UpdatePass::Update(&Scales::ONE), 1.0),
        &mut io,
    )?;
    stats.update_seconds += t.elapsed().as_secs_f64();
    let any_light = first.sums.emitted.iter().any(|&e| e > 0.0);
    let verdict = closure_verdict(source, &plan, &mut io)?;
    // The direct light, once (see `super::direct`); the iterations then gather only `B - E`.
    let shape = crate::solve::direct::Shape {
        emitting: first.emitting as usize,
        surfels: work.count as usize,
        longest_axis: info.grid.dims.into_iter().max().unwrap_or(0),
        directions: directions.len(),
    };
    let dense = options.direct.resolve(shape).filter(|_| any_light);
    // Again with the static records at the size they were written and the direct-light pass
    // decided: the first check counted those records' size from one order of them.
    let also = workset::solve_files_per_surfel(options.accelerate, dense.is_some());
    workset::check_free_space(work_parent, work.disk_still_needed(also))?;
    let direct = match dense {
        Some(count) => Some(super::direct::gather_direct_out_of_core(
            source,
            &DirectionSet::with_count(count),
            &plan,
            pool,
            work.dir.path(),
            &mut io,
        )?),
        _ => None,
    };
    let t = Instant::now();
    let mut lit = lit_file(source, &work, &plan, direct.is_some(), &mut io)?;
    stats.update_seconds += t.elapsed().as_secs_f64();
    // As `solve::jacobi`: one channel for a grey scene, checked here on the materials used.
    let channels = if options.grey && first.grey { 1 } else { 3 };
    stats.solve.channels = channels;
    // The radiosity an update replaces, for the tail extrapolation.
    let previous = if options.accelerate {
        let path = work.dir.path().join("radiosity-previous.bin");
        RecordFile::create(&path)?.set_len(work.count * RADIOSITY_LEN as u64)?;
        Some(path)
    } else {
        None
    };

    let by_axis = walk_by_axis(directions);
    // Each copy's files twice: a pass of an axis reads the light of the directions before it
    // from one gathered file and writes to the other: `files[m][w]` writes file `w` (see
    // `WorkSet` and `OutOfCore::light_file`).
    let frame_buffers = FrameBuffers::shared();
    let files: Vec<[CopyFiles; 2]> = work
        .copies
        .iter()
        .map(|c| {
            let statics = Arc::new(FramedStatics::open(
                &c.statics,
                &c.statics_index,
                work.count,
                &frame_buffers,
            )?);
            Ok([
                CopyFiles::open_from(c, &statics, &work.gathered[1], &work.gathered[0])?,
                CopyFiles::open_from(c, &statics, &work.gathered[0], &work.gathered[1])?,
            ])
        })
        .collect::<Result<_, OocError>>()?;
    // Both walks (odd and even iterations) with where their axes start.
    let walks = [1, 2].map(|iteration| {
        let walk = walk_of_iteration(&by_axis, iteration);
        let spans = AxisSpans::new(&walk);
        (walk, spans)
    });
    // The checkpoints, where they share the work files' disk, take their room before the links
    // do: a building of 1.2 x 10^8 surfels wrote 14 GB checkpoints (8.5 GB since their sums
    // are f32), and with the links they filled the disk.
    let checkpoint_growth = checkpoints.as_ref().map_or(0, |c| {
        let per_surfel = workset::checkpoint_bytes_per_surfel(2);
        workset::checkpoint_growth(c.saver.path(), work.dir.path(), work.count, per_surfel)
    });
    if let Some(free) = workset::free_bytes(work.dir.path()) {
        let needed = work.disk_still_needed(also) + checkpoint_growth;
        if checkpoint_growth > 0 && free < needed {
            tracing::warn!(
                free = super::budget::format_bytes(free),
                needed = super::budget::format_bytes(needed),
                "the work files and two checkpoints do not fit on the disk: checkpoints that \
                 do not fit are not written, and the solve goes on without them"
            );
        }
    }
    let links = LinkStore::new(
        work.dir.path(),
        directions.len(),
        super::links::allowance(
            work.dir.path(),
            options.links_disk,
            work.disk_still_needed(also) + checkpoint_growth,
            1,
        ),
        work.count,
        plan.io_bytes,
    );
    let mut start = Start::fresh();
    // Where the iteration resumed from a mid-iteration checkpoint stands.
    let mut resume_at = Position::default();
    if let Some(file) = checkpoints.as_mut().and_then(|c| c.resume.take()) {
        let t = Instant::now();
        // The walk of the iteration resumed.
        let resumed = file.header.state.iteration as usize + 1;
        let (walk, spans) = &walks[walks_backwards(resumed) as usize];
        resume_at = restore(
            &file,
            previous.as_deref(),
            &work,
            &plan,
            (walk, spans),
            &mut io,
        )?;
        lit = lit_file(source, &work, &plan, direct.is_some(), &mut io)?;
        stats.update_seconds += t.elapsed().as_secs_f64();
        let done = spans.done(resume_at);
        start = Start::resumed(
            &file.header.state,
            &file.path,
            done as usize,
            &mut stats.solve,
        );
        if resume_at != Position::default() {
            tracing::info!(
                iteration = start.iteration,
                within = done,
                axis = resume_at.axes,
                axis_directions = resume_at.directions,
                "continuing inside an iteration from the checkpoint's partial sums"
            );
        }
    }
    let mut sweep = OutOfCore {
        source,
        directions,
        work: &work,
        plan: &plan,
        files,
        walks,
        backwards: false,
        cosine_sum,
        channels,
        threads,
        previous,
        direct: direct.as_ref().map(|d| d.path.clone()),
        at: resume_at,
        light_file: resume_at.directions.saturating_sub(1) % 2,
        gathered_until: 0,
        summed: false,
        histogram: None,
        buffers: BandBuffers::default(),
        links,
        times: BandTimes::default(),
        io,
        last: first,
        lit: Some(lit),
        lit_copy: None,
        update_seconds: 0.0,
        closed: verdict.closed,
        scales: Scales::ONE,
    };
    let saver = checkpoints.map(|c| c.saver);
    iterate(
        &mut sweep,
        options,
        &crate::comm::SingleProcess,
        saver,
        start,
        any_light,
        &mut stats.solve,
    )?;
    let OutOfCore {
        times,
        io,
        last,
        update_seconds,
        links,
        scales,
        ..
    } = sweep;
    stats.solve.closure = Some(crate::solve::stats::ClosureStats { verdict, scales });
    stats.solve.links = Some(links.stats(&crate::comm::SingleProcess));
    stats.update_seconds += update_seconds;
    stats.solve.emitted_power = last.sums.emitted;
    stats.solve.absorbed_power = last.sums.absorbed;
    if let Some(d) = direct {
        // As every loop: the direct light's power after the reflected one's.
        for (a, d) in stats
            .solve
            .absorbed_power
            .iter_mut()
            .zip(last.sums.absorbed_direct)
        {
            *a += d;
        }
        stats.solve.direct = Some(d.stats);
    }
    stats.solve.dispatch_seconds = times.dispatch;
    stats.solve.propagate_seconds = times.propagate;
    stats.read_seconds = times.read;
    stats.write_seconds = times.write;
    stats.bands = times.bands;
    stats.tiled_columns = times.tiled_columns;
    stats.replayed_bands = times.replayed_bands;
    stats.replay_groups = times.replay_groups;
    stats.joint_passes = times.joint_passes;
    stats.joint_directions = times.joint_directions;
    stats.bytes_read = io.read;
    stats.bytes_written = io.written;
    // The links' files go with the store; the rest but the answer with this.
    drop(links);
    work.keep_only_the_answer();
    Ok(OocSolution {
        stats,
        work,
        io_bytes: plan.io_bytes,
    })
}

/// The out-of-core store (the scene in three axis copies and canonical files on disk) on one
/// process, as the iteration loop drives it: a step is one direction of the walk by main axis
/// (and, after an axis's last direction, the fold of its light into the canonical sum).
struct OutOfCore<'a> {
    source: &'a dyn SurfelSource,
    directions: &'a DirectionSet,
    work: &'a WorkSet,
    plan: &'a MemoryPlan,
    files: Vec<[CopyFiles; 2]>,
    /// The walks of odd and even iterations ([`walk_of_iteration`]), with where their axes
    /// start.
    walks: [(Walk, AxisSpans); 2],
    /// This iteration walks backwards (the second of `walks`).
    backwards: bool,
    cosine_sum: Vec<f64>,
    channels: usize,
    threads: usize,
    /// The radiosity an update replaces (for the tail extrapolation).
    previous: Option<std::path::PathBuf>,
    /// The direct-light file, when the pass ran.
    direct: Option<std::path::PathBuf>,
    /// The light gathered so far in this iteration.
    at: Position,
    /// The gathered file that holds the light of the axis's directions done (`at.directions >
    /// 0`): each pass writes the other one. Resuming inside an axis, the light is put back
    /// into file `(directions - 1) % 2`.
    light_file: usize,
    /// The steps of this iteration gathered: beyond the step in progress where directions
    /// were gathered together ([`gathered_together`]).
    gathered_until: usize,
    /// Whether the canonical sum holds any axis's light of this iteration.
    summed: bool,
    /// The row histogram of the axis in progress.
    histogram: Option<(usize, Vec<u32>)>,
    buffers: BandBuffers,
    /// Each direction's partner links, kept in files (`super::links`).
    links: LinkStore,
    times: BandTimes,
    io: IoCounters,
    /// The last update (its energy).
    last: Update,
    /// The file (in canonical order) of what the lines carry of the current radiosity; `None`
    /// after an update, until the next iteration begins.
    lit: Option<PathBuf>,
    /// The copy whose order the shared radiosity file (`AxisCopy::radiosity`) holds `lit` in.
    lit_copy: Option<usize>,
    update_seconds: f64,
    /// The scene's light is sealed in: each update scales the light by `scales`
    /// (`solve::closed`), found in a pass over the files before it.
    closed: bool,
    scales: Scales,
}

impl OutOfCore<'_> {
    /// This iteration's walk.
    fn walk(&self) -> &Walk {
        &self.walks[self.backwards as usize].0
    }

    /// Where this iteration's axes start.
    fn spans(&self) -> &AxisSpans {
        &self.walks[self.backwards as usize].1
    }

    /// The place in this iteration's walk of the main axis of step `step`, and the index in it.
    fn place(&self, step: usize) -> (usize, usize) {
        let done = step as u64;
        let starts = &self.spans().starts;
        let p = (0..3)
            .find(|&p| done < starts[p + 1])
            .expect("a step of the iteration");
        (p, (done - starts[p]) as usize)
    }
}

impl OutOfCore<'_> {
    /// One pass of [`update`] over the canonical files (`omega`: the Chebyshev weight, 1 for a
    /// plain update).
    fn update_canonical(&mut self, pass: UpdatePass, omega: f64) -> Result<Update, OocError> {
        update(
            self.source,
            self.work,
            self.plan,
            &self.cosine_sum,
            (self.summed, self.channels),
            self.previous.as_deref(),
            self.direct.as_deref(),
            (pass, omega),
            &mut self.io,
        )
    }

    /// The radiosity before last, which a checkpoint of `state` holds while its Chebyshev
    /// semi-iteration runs.
    fn older_for(&self, state: &State) -> Option<&Path> {
        self.previous
            .as_deref()
            .filter(|_| state.extrapolation.chebyshev.is_some())
    }
}

impl Sweep for OutOfCore<'_> {
    type Error = OocError;

    fn steps(&self) -> usize {
        self.directions.len()
    }

    fn updates(&self) -> u64 {
        self.work.count * self.directions.len() as u64
    }

    fn begin(&mut self, iteration: usize, from: usize) -> Result<(), OocError> {
        self.backwards = walks_backwards(iteration);
        if self.lit.is_none() {
            let t = Instant::now();
            self.lit = Some(lit_file(
                self.source,
                self.work,
                self.plan,
                self.direct.is_some(),
                &mut self.io,
            )?);
            self.lit_copy = None;
            self.update_seconds += t.elapsed().as_secs_f64();
        }
        if from == 0 {
            self.at = Position::default();
        }
        self.gathered_until = from;
        debug_assert_eq!(self.spans().done(self.at), from as u64);
        // Whether the canonical sum holds any axis's light yet (else the next fold starts it).
        self.summed = self.walk()[..self.at.axes]
            .iter()
            .any(|(_, a)| !a.is_empty());
        Ok(())
    }

    fn step(&mut self, step: usize) -> Result<bool, OocError> {
        if step < self.gathered_until {
            // Gathered together with an earlier direction, in its pass.
            return Ok(true);
        }
        let (p, k) = self.place(step);
        let (m, axis) = self.walk()[p].clone();
        if self.lit_copy != Some(m) {
            // The copies share one radiosity file: it is sent this copy's order at the first
            // direction of its axis (or the first after a resume), before the histogram and a
            // band take the memory.
            let t = Instant::now();
            let lit = self.lit.as_deref().expect("an iteration begun");
            send_to_copy(self.work, self.plan, lit, m, &mut self.io)?;
            self.update_seconds += t.elapsed().as_secs_f64();
            self.lit_copy = Some(m);
        }
        let copy = &self.work.copies[m];
        if self.histogram.as_ref().is_none_or(|(axis, _)| *axis != m) {
            self.histogram = Some((m, copy.load_histogram(self.plan)?));
        }
        let (_, histogram) = self.histogram.as_ref().expect("just loaded");
        // The axis's first direction writes file 0 and reads nothing; each pass after it reads
        // the light from the file that holds it and writes the other.
        let write = if k == 0 { 0 } else { 1 - self.light_file };
        // Between passes only the file that holds the light is kept at its length: the other
        // is emptied after the pass that read it, and given its length back here, before the
        // pass that writes it. So a checkpoint or a fold between passes, whose buckets take
        // about as much again, does not find both on the disk (24 bytes a surfel).
        resize_gathered(&self.work.gathered[write], self.work.count)?;
        let pass = DirectionPass {
            copy,
            files: &self.files[m][write],
            histogram,
            dims: self.source.info().grid.dims,
            plan: self.plan,
            threads: self.threads,
            channels: self.channels,
            first: k == 0,
            stops_on_signal: true,
        };
        let together = gathered_together(&pass, self.directions, &axis, k, &self.links);
        self.links.begin_together(&together)?;
        let ds: Vec<&Direction> = together
            .iter()
            .map(|&d| &self.directions.directions[d])
            .collect();
        pass.run_together(
            &ds,
            &mut self.links.band_links(),
            &mut self.buffers,
            &mut self.io,
            &mut self.times,
        )?;
        // The pass may have stopped early on a signal: its light is incomplete, and the file it
        // read from holds the directions before it, whole.
        let stopped = crate::interrupt::requested().is_some();
        self.links.end(!stopped);
        if stopped {
            return Ok(false);
        }
        // The file this pass read (or, at an axis's first pass, the one it did not use).
        resize_gathered(&self.work.gathered[1 - write], 0)?;
        let done = k + together.len();
        self.times.joint_passes += (together.len() > 1) as u64;
        self.times.joint_directions += (together.len() - 1) as u64;
        self.light_file = write;
        self.gathered_until = step + together.len();
        self.at = Position {
            axes: p,
            directions: done,
        };
        if done == axis.len() {
            // What comes next (the fold, a checkpoint, the update) takes the memory a band
            // holds.
            self.histogram = None;
            drop(std::mem::take(&mut self.buffers));
            // This axis's light joins the canonical sum before the next axis reuses the files;
            // the file it is folded from is emptied after it.
            let t = Instant::now();
            let last_file = &self.work.gathered[self.light_file];
            fold_gathered(
                copy,
                last_file,
                self.work,
                self.plan,
                !self.summed,
                &mut self.io,
            )?;
            resize_gathered(last_file, 0)?;
            self.update_seconds += t.elapsed().as_secs_f64();
            self.summed = true;
            self.at = Position {
                axes: p + 1,
                directions: 0,
            };
        }
        Ok(true)
    }

    fn can_save_within(&self, done: usize) -> bool {
        // After the last direction the iteration's boundary is next; inside directions gathered
        // together, the light holds the later ones already.
        done < self.directions.len() && done >= self.gathered_until
    }

    fn save_within(
        &mut self,
        saver: &mut Saver,
        state: State,
        done: usize,
    ) -> Result<(), CheckpointError> {
        debug_assert_eq!(self.spans().done(self.at), done as u64);
        // The save's permutation takes the memory a band holds: let the band's arrays go (the
        // next direction makes them again).
        self.buffers = BandBuffers::default();
        let older = self.older_for(&state).map(Path::to_path_buf);
        if self.at.directions > 0 {
            // Fields, not `self.walk()`: the save also takes `self.io`.
            let (walk, spans) = &self.walks[self.backwards as usize];
            save_in_axis(
                saver,
                state,
                (spans, self.at, self.light_file),
                &self.work.copies[walk[self.at.axes].0],
                (self.summed, older.as_deref()),
                (self.work, self.plan),
                &mut self.io,
            )
        } else {
            let at = (done as u64, older.as_deref());
            save_between_axes(saver, state, at, self.work, self.plan)
        }
    }

    fn save_boundary(&mut self, saver: &mut Saver, state: State) -> Result<(), CheckpointError> {
        let older = self.older_for(&state).map(Path::to_path_buf);
        save(saver, state, older.as_deref(), self.work, self.plan)
    }

    fn keeps_older(&self) -> bool {
        self.previous.is_some()
    }

    fn end(&mut self, omega: f64) -> Result<[f64; 4], OocError> {
        self.histogram = None;
        drop(std::mem::take(&mut self.buffers));
        let t = Instant::now();
        if self.closed {
            let mut sums = ClosureSums::new(&self.source.info().materials);
            self.update_canonical(UpdatePass::Closure(&mut sums), 1.0)?;
            self.scales = sums.scales(self.channels);
        }
        let scales = self.scales;
        let result = self.update_canonical(UpdatePass::Update(&scales), omega)?;
        self.update_seconds += t.elapsed().as_secs_f64();
        self.last = result;
        self.lit = None;
        self.lit_copy = None;
        let sums = result.sums;
        Ok([sums.change, sums.total, sums.falling, sums.residual])
    }

    fn extrapolate(&mut self, factor: f64) -> Result<(), OocError> {
        let t = Instant::now();
        let previous = self
            .previous
            .as_deref()
            .expect("kept with the extrapolation on");
        extrapolate_canonical(
            self.source,
            self.work,
            self.plan,
            previous,
            factor,
            &mut self.io,
        )?;
        self.update_seconds += t.elapsed().as_secs_f64();
        Ok(())
    }
}

/// A place inside an iteration where the light gathered so far is whole on disk: the first
/// `axes` main axes (in the order of the iteration's walk) folded into the canonical sum, and the first
/// `directions` directions of the next axis in its gathered files (in file
/// `(directions - 1) % 2`, see `WorkSet::gathered`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Position {
    axes: usize,
    directions: usize,
}

/// Where each main axis's directions lie in an iteration's order: a [`Position`] as the count
/// of directions done that a checkpoint stores, and back.
struct AxisSpans {
    /// Directions before each axis, and after the last (four entries).
    starts: Vec<u64>,
}

impl AxisSpans {
    fn new(walk: &[(usize, Vec<usize>)]) -> Self {
        let mut starts = vec![0u64];
        for (_, axis) in walk {
            starts.push(starts.last().copied().unwrap_or(0) + axis.len() as u64);
        }
        AxisSpans { starts }
    }

    /// Directions of the iteration done at `at`.
    fn done(&self, at: Position) -> u64 {
        self.starts[at.axes.min(self.starts.len() - 1)] + at.directions as u64
    }

    /// The position `done` directions into an iteration: inside a main axis (`in_axis`, at
    /// least one of its directions done and one left), or else at the end of one. `None` if
    /// `done` is no such place.
    fn position(&self, done: u64, in_axis: bool) -> Option<Position> {
        let axes = self.starts.len() - 1;
        if in_axis {
            (0..axes)
                .find(|&m| self.starts[m] < done && done < self.starts[m + 1])
                .map(|m| Position {
                    axes: m,
                    directions: (done - self.starts[m]) as usize,
                })
        } else {
            (0..axes)
                .find(|&m| self.starts[m + 1] == done)
                .map(|m| Position {
                    axes: m + 1,
                    directions: 0,
                })
        }
    }
}

/// Copies the `LEN`-byte records of a work file into a checkpoint being written.
fn copy_records<const LEN: usize>(
    path: &Path,
    plan: &MemoryPlan,
    w: &mut dyn std::io::Write,
) -> std::io::Result<()> {
    let mut reader = SeqReader::<LEN>::open(path, plan.io_bytes).map_err(std::io::Error::other)?;
    while let Some(record) = reader.next_record().map_err(std::io::Error::other)? {
        w.write_all(&record)?;
    }
    Ok(())
}

/// Saves a checkpoint whose radiosity is the canonical radiosity file, streamed through the
/// plan's I/O buffer.
fn save(
    saver: &mut Saver,
    state: crate::checkpoint::State,
    older: Option<&Path>,
    work: &WorkSet,
    plan: &MemoryPlan,
) -> Result<(), crate::checkpoint::CheckpointError> {
    saver.save(state, plan.io_bytes, |w| {
        copy_radiosity(older, work, plan, w)
    })
}

/// Writes the canonical radiosity file, then `older` (the radiosity before last, while the
/// Chebyshev semi-iteration runs), to a checkpoint's payload.
fn copy_radiosity(
    older: Option<&Path>,
    work: &WorkSet,
    plan: &MemoryPlan,
    w: &mut dyn std::io::Write,
) -> std::io::Result<()> {
    copy_records::<RADIOSITY_LEN>(&work.canonical_radiosity, plan, w)?;
    match older {
        Some(path) => copy_records::<RADIOSITY_LEN>(path, plan, w),
        None => Ok(()),
    }
}

// Same layout as a checkpoint's partial sums in f32 (`State::sums_in_f32`, which these
// checkpoints set): f32 x 6 per surfel, side-major, LE. The readers hand them out in f64.
const _: () = assert!(crate::checkpoint::file::PARTIAL32_LEN == LIGHT32_LEN);

/// Saves a checkpoint inside an iteration, `done` directions into it (the end of a main axis):
/// the canonical radiosity file, then the canonical sum of the light gathered so far.
fn save_between_axes(
    saver: &mut Saver,
    mut state: crate::checkpoint::State,
    (done, older): (u64, Option<&Path>),
    work: &WorkSet,
    plan: &MemoryPlan,
) -> Result<(), crate::checkpoint::CheckpointError> {
    state.within = Some(done);
    state.sums_in_f32 = true;
    saver.save(state, plan.io_bytes, |w| {
        copy_radiosity(older, work, plan, w)?;
        copy_records::<LIGHT32_LEN>(&work.canonical_gathered, plan, w)
    })
}

/// Saves a checkpoint inside main axis `at.axes`, `at.directions` of its directions done
/// (`copy` is that axis's copy): the canonical radiosity file, the canonical sum of the axes
/// before it (zeros when `summed` is false: none gathered yet, and the file holds an older
/// iteration's), then the light of the axis's directions done, brought from its gathered file to
/// canonical order as [`fold_gathered`] brings it, but into an array of its own (added to the
/// sum, it would round otherwise than the uninterrupted run, which adds the whole axis at once).
#[allow(clippy::too_many_arguments)]
fn save_in_axis(
    saver: &mut Saver,
    mut state: crate::checkpoint::State,
    (axes, at, light_file): (&AxisSpans, Position, usize),
    copy: &AxisCopy,
    (summed, older): (bool, Option<&Path>),
    (work, plan): (&WorkSet, &MemoryPlan),
    io: &mut IoCounters,
) -> Result<(), crate::checkpoint::CheckpointError> {
    state.within = Some(axes.done(at));
    state.axis_in_progress = true;
    state.sums_in_f32 = true;
    let gathered = &work.gathered[light_file];
    saver.save(state, plan.io_bytes, |w| {
        copy_radiosity(older, work, plan, w)?;
        if summed {
            copy_records::<LIGHT32_LEN>(&work.canonical_gathered, plan, w)?;
        } else {
            let zeros = vec![0u8; plan.io_bytes.max(LIGHT32_LEN) / LIGHT32_LEN * LIGHT32_LEN];
            let mut left = work.count * LIGHT32_LEN as u64;
            while left > 0 {
                let len = left.min(zeros.len() as u64) as usize;
                w.write_all(&zeros[..len])?;
                left -= len as u64;
            }
        }
        let mut canonical = Canonical::new(copy, gathered, work, plan, "checkpoint-axis", io)
            .map_err(std::io::Error::other)?;
        let mut bytes = Vec::new();
        while let Some((_, values)) = canonical.next_chunk().map_err(std::io::Error::other)? {
            // The axis light records' f32 values, exactly.
            bytes.resize(values.len() * LIGHT32_LEN, 0);
            for (h, slot) in values.iter().zip(bytes.chunks_exact_mut(LIGHT32_LEN)) {
                encode_light32(h, slot);
            }
            w.write_all(&bytes)?;
        }
        canonical.finish(io);
        Ok(())
    })
}

/// Puts a checkpoint's radiosity (the canonical order's, checked against its checksum before
/// anything is solved from it) into the canonical radiosity file (the caller sends it to the
/// axis copies); in a mid-iteration checkpoint, its sum into the canonical sum and the light of
/// the axis in progress, if it has one, into that axis's gathered file, in its copy's order.
/// Returns where in the iteration the light it holds stands (the default at a boundary).
fn restore(
    file: &CheckpointFile,
    previous: Option<&Path>,
    work: &WorkSet,
    plan: &MemoryPlan,
    (walk, axes): (&Walk, &AxisSpans),
    io: &mut IoCounters,
) -> Result<Position, OocError> {
    let bad = |what: String| OocError::BadData {
        source_name: file.path.display().to_string(),
        what,
    };
    let state = &file.header.state;
    // The data and hybrid modes out of core keep their sums by group, in their own order of
    // directions: their iteration starts again here (from the same radiosity, so the same
    // answer).
    let within = state.within.filter(|&done| {
        if state.walked_otherwise() {
            tracing::info!(
                "the checkpoint is {done} directions into iteration {}, written by a voxrad \
                 that walked the directions of that iteration in another order; that \
                 iteration starts from its beginning",
                state.iteration + 1
            );
            return false;
        }
        let own = state.data_groups == 0;
        if !own {
            tracing::info!(
                "the checkpoint is {done} steps into iteration {} of the data or hybrid mode out \
                 of core; this solve cannot continue inside it, so that iteration starts from \
                 its beginning",
                state.iteration + 1
            );
        }
        own
    });
    let at = match within {
        None => Position::default(),
        Some(done) => {
            if file.header.partial_ranks() != 1 {
                return Err(bad(format!(
                    "it holds the partial sums of {} ranks, an out-of-core solve keeps one",
                    file.header.partial_ranks()
                )));
            }
            match axes.position(done, state.axis_in_progress) {
                Some(at) => at,
                None if state.axis_in_progress => {
                    return Err(bad(format!(
                        "it is {done} directions into an iteration, not inside a main axis as \
                         it says (damaged?)"
                    )))
                }
                None => {
                    return Err(bad(format!(
                        "it is {done} directions into an iteration, not at the end of a main \
                         axis, and holds no light of the axis in progress (damaged?)"
                    )))
                }
            }
        }
    };
    // Same layout: f32 x 6 per surfel, side-major, little-endian.
    const _: () = assert!(crate::checkpoint::file::RADIOSITY_LEN == RADIOSITY_LEN);
    if file.header.identity.surfels != work.count {
        return Err(bad(format!(
            "it holds {} surfels, the scene {}",
            file.header.identity.surfels, work.count
        )));
    }
    let n = work.count;
    let mut out = SeqWriter::create(&work.canonical_radiosity, plan.io_bytes)?;
    // The sum file is rewritten only if the checkpoint has a sum (it keeps its length else).
    let mut sums = match within {
        None => None,
        Some(_) => Some(SeqWriter::create(&work.canonical_gathered, plan.io_bytes)?),
    };
    // The axis's light goes to its copy's order, where each canonical surfel sits in it.
    let mut axis = match at.directions {
        0 => None,
        _ => {
            let copy = &work.copies[walk[at.axes].0];
            let chunk = plan.chunk_surfels.min(n).max(1);
            let buffer = plan.bucket_buffer(n.div_ceil(chunk));
            let scatter =
                Scatter::<LIGHT32_LEN>::new(work.dir.path(), "checkpoint-axis", n, chunk, buffer)?;
            let positions = IndexReader::open(&copy.positions, plan.io_bytes)?;
            Some((scatter, positions))
        }
    };
    // The radiosity before last (the Chebyshev semi-iteration's) goes back to the file an
    // update keeps it in.
    let mut older = match (file.header.radiosity_arrays() > 1, previous) {
        (false, _) => None,
        (true, Some(path)) => Some(SeqWriter::create(path, plan.io_bytes)?),
        (true, None) => {
            return Err(bad(
                "it holds a Chebyshev semi-iteration's state, and this solve does not \
                 extrapolate"
                    .to_string(),
            ))
        }
    };
    file.read_payload::<OocError>(
        plan.io_bytes,
        |piece| out.write(piece),
        |piece| match older.as_mut() {
            Some(o) => o.write(piece),
            None => Ok(()),
        },
        |piece| match sums.as_mut() {
            // f64 as the checkpoint's readers hand them out, f32 in the sum file, which held
            // these values.
            Some(s) => {
                let mut record = [0u8; LIGHT32_LEN];
                for value in piece.chunks_exact(GATHER_LEN) {
                    encode_light32(&decode_gathered(value), &mut record);
                    s.write(&record)?;
                }
                Ok(())
            }
            None => Ok(()),
        },
        |piece| {
            let Some((scatter, positions)) = axis.as_mut() else {
                return Ok(());
            };
            // The axis's light as the band rounded it (f32 in the file since format version
            // 7, handed out in f64): the axis light record holds it exactly.
            let mut record = [0u8; LIGHT32_LEN];
            for value in piece.chunks_exact(GATHER_LEN) {
                let p = positions.expect_value()? as u64;
                encode_light32(&decode_gathered(value), &mut record);
                scatter.push(p, &record)?;
            }
            Ok(())
        },
    )?;
    io.written += out.finish()?;
    io.read += n * RADIOSITY_LEN as u64;
    if let Some(o) = older {
        io.written += o.finish()?;
        io.read += n * RADIOSITY_LEN as u64;
    }
    if let Some(s) = sums {
        io.written += s.finish()?;
        io.read += n * GATHER_LEN as u64;
    }
    if let Some((scatter, _)) = axis {
        io.read += n * (4 + GATHER_LEN as u64);
        let mut chunks = scatter.into_chunks()?;
        // Where the next direction of the axis reads the light of those before it.
        let into = &work.gathered[(at.directions - 1) % 2];
        let mut out = SeqWriter::create(into, plan.io_bytes)?;
        let chunk = plan.chunk_surfels.min(n).max(1) as usize;
        let mut values = vec![[0u8; LIGHT32_LEN]; chunk];
        while let Some((_, len)) = chunks.next_chunk(|at, value| values[at] = *value)? {
            for v in &values[..len as usize] {
                out.write(v)?;
            }
        }
        io.written += out.finish()? + chunks.written;
        io.read += chunks.read;
    }
    Ok(at)
}

/// Whether the scene of `source` is closed (`solve::enclosure`), the check taking at most half
/// the working memory (the rest of the budget is free while it runs).
pub(crate) fn closure_verdict(
    source: &dyn SurfelSource,
    plan: &MemoryPlan,
    io: &mut IoCounters,
) -> Result<crate::solve::enclosure::Verdict, OocError> {
    source.enclosure(plan.working / 2, plan.io_bytes as u64, io)
}

/// What a pass of [`update`] does.
enum UpdatePass<'a> {
    /// Updates `B` with a closed scene's scales (else 1).
    Update(&'a Scales),
    /// Adds a closed scene's sums only and writes nothing.
    Closure(&'a mut ClosureSums),
}

/// What one update of the radiosity found.
#[derive(Clone, Copy, Debug, Default)]
struct Update {
    sums: UpdateSums,
    /// Every material on a surfel side has three equal channels (see `solve::effects`).
    grey: bool,
    /// Surfels with an emitting side (what the direct pass's decision reads).
    emitting: u64,
}

pub use crate::solve::update::UpdateSums;

/// The light of a gathered file (in an axis copy's order) in canonical order, chunk by chunk:
/// a permutation by the copy's canonical indices ([`Scatter`]), its first pass made by
/// [`Canonical::new`].
struct Canonical {
    chunks: ChunkReader<LIGHT32_LEN>,
    /// One chunk's values (`chunk` surfels at most), reused.
    values: Vec<Gathered>,
    chunk: u64,
}

impl Canonical {
    /// Scatters `gathered` (in `copy`'s order) into bucket files named after `name`.
    fn new(
        copy: &AxisCopy,
        gathered: &Path,
        work: &WorkSet,
        plan: &MemoryPlan,
        name: &str,
        io: &mut IoCounters,
    ) -> Result<Self, OocError> {
        let n = work.count;
        let chunk = plan.chunk_surfels.min(n).max(1);
        let buffer = plan.bucket_buffer(n.div_ceil(chunk));
        let mut scatter = Scatter::<LIGHT32_LEN>::new(work.dir.path(), name, n, chunk, buffer)?;
        let mut ids = IndexReader::open(&copy.ids, plan.io_bytes)?;
        let mut values = SeqReader::<LIGHT32_LEN>::open(gathered, plan.io_bytes)?;
        while let Some(id) = ids.next_value()? {
            let value = values.expect_record()?;
            scatter.push(id as u64, &value)?;
        }
        ids.count_into(io);
        io.read += n * LIGHT32_LEN as u64;
        Ok(Canonical {
            chunks: scatter.into_chunks()?,
            values: Vec::new(),
            chunk,
        })
    }

    /// The next chunk of canonical surfels: its first index and the light of each.
    fn next_chunk(&mut self) -> Result<Option<(u64, &[Gathered])>, OocError> {
        let values = &mut self.values;
        values.clear();
        values.resize(self.chunk as usize, [[0.0; 3]; 2]);
        let Some((start, len)) = self
            .chunks
            .next_chunk(|at, value| values[at] = decode_light32(value))?
        else {
            return Ok(None);
        };
        Ok(Some((start, &self.values[..len as usize])))
    }

    /// Counts the bucket files' bytes.
    fn finish(self, io: &mut IoCounters) {
        io.written += self.chunks.written;
        io.read += self.chunks.read;
    }
}

/// Adds the light gathered in `copy`'s order (the shared gathered file `gathered` of its last
/// direction) to the canonical sum, or starts the sum with it (`first`).
fn fold_gathered(
    copy: &AxisCopy,
    gathered: &Path,
    work: &WorkSet,
    plan: &MemoryPlan,
    first: bool,
    io: &mut IoCounters,
) -> Result<(), OocError> {
    let mut canonical = Canonical::new(copy, gathered, work, plan, "gathered", io)?;
    let sum_file = RecordFile::open(&work.canonical_gathered)?;
    // With the chunk's values, what a permutation chunk may hold (`CHUNK_BYTES_PER_SURFEL`).
    let mut bytes = Vec::new();
    while let Some((start, values)) = canonical.next_chunk()? {
        bytes.resize(values.len() * LIGHT32_LEN, 0);
        if !first {
            sum_file.read_at(start * LIGHT32_LEN as u64, &mut bytes, io)?;
        }
        for (h, slot) in values.iter().zip(bytes.chunks_exact_mut(LIGHT32_LEN)) {
            let mut total = *h;
            if !first {
                let before = decode_light32(slot);
                for (t, b) in total.iter_mut().flatten().zip(before.iter().flatten()) {
                    // This axis's light plus the earlier axes' sum: a fixed order.
                    *t += *b;
                }
            }
            encode_light32(&total, slot);
        }
        sum_file.write_at(start * LIGHT32_LEN as u64, &bytes, io)?;
    }
    canonical.finish(io);
    Ok(())
}

/// `B = E + rho H / S(n)` in canonical order, `H` the canonical sum of gathered light (none
/// gathered yet: `H = 0`); then the new `B` is sent to every copy, one copy at a time.
///
/// `channels` is 1 when only the first channel was gathered (a grey scene): the other two are
/// the same numbers. With `previous`, the radiosity it replaces is kept there (for the tail
/// extrapolation, and as the radiosity before last of the Chebyshev semi-iteration, whose
/// weight `omega` is when not 1: the update then reads it first). The caller sends the new
/// radiosity to the copies ([`send_to_copies`]).
///
/// With [`UpdatePass::Closure`] it reads the same files and only adds a closed scene's sums
/// (`solve::closed`), writing nothing: the pass before such a scene's update.
#[allow(clippy::too_many_arguments)]
fn update(
    source: &dyn SurfelSource,
    work: &WorkSet,
    plan: &MemoryPlan,
    cosine_sum: &[f64],
    (gathered, channels): (bool, usize),
    previous: Option<&Path>,
    direct: Option<&Path>,
    (mut pass, omega): (UpdatePass, f64),
    io: &mut IoCounters,
) -> Result<Update, OocError> {
    let writes = matches!(pass, UpdatePass::Update(..));
    let chebyshev = writes && omega != 1.0;
    let info = source.info();
    // The replaced radiosity is kept only by a pass that replaces it.
    let kept = previous
        .filter(|_| writes)
        .map(RecordFile::open)
        .transpose()?;
    let direct = direct.map(RecordFile::open).transpose()?;
    let mut d_bytes = vec![
        0u8;
        if direct.is_some() {
            chunk_len(plan, work) * LIGHT32_LEN
        } else {
            0
        }
    ];
    let mut used = vec![false; info.materials.len()];
    let n = work.count;
    let chunk = chunk_len(plan, work) as u64;
    let canonical = RecordFile::open(&work.canonical_radiosity)?;
    let canonical_gathered = RecordFile::open(&work.canonical_gathered)?;
    let mut stream = source.stream(plan.io_bytes as u64)?;
    let area_unit = info.grid.voxel_size * info.grid.voxel_size;
    let mut result = Update::default();
    let mut h_bytes = vec![0u8; chunk as usize * LIGHT32_LEN];
    let mut bytes = vec![0u8; chunk as usize * RADIOSITY_LEN];
    // The replaced radiosity of a chunk, when it is kept.
    let mut old = Vec::with_capacity(if kept.is_some() { bytes.len() } else { 0 });
    // The radiosity before last of a chunk, for a Chebyshev update.
    let mut older = vec![0u8; if chebyshev { bytes.len() } else { 0 }];
    if chebyshev && kept.is_none() {
        return Err(OocError::BadData {
            source_name: source.describe(),
            what: "a Chebyshev update without the radiosity before last (internal)".to_string(),
        });
    }
    let mut start = 0u64;
    while start < n {
        let len = chunk.min(n - start);
        let h_slots = &mut h_bytes[..len as usize * LIGHT32_LEN];
        if gathered {
            canonical_gathered.read_at(start * LIGHT32_LEN as u64, h_slots, io)?;
        } else {
            h_slots.fill(0);
        }
        let prev = &mut bytes[..len as usize * RADIOSITY_LEN];
        canonical.read_at(start * RADIOSITY_LEN as u64, prev, io)?;
        let d_slots = &mut d_bytes[..if direct.is_some() {
            len as usize * LIGHT32_LEN
        } else {
            0
        }];
        if let Some(direct) = &direct {
            direct.read_at(start * LIGHT32_LEN as u64, d_slots, io)?;
        }
        let mut d_slots = d_slots.chunks_exact(LIGHT32_LEN);
        if kept.is_some() {
            old.clear();
            old.extend_from_slice(prev);
        }
        let older_slots = &mut older[..if chebyshev { prev.len() } else { 0 }];
        if let (true, Some(kept)) = (chebyshev, &kept) {
            kept.read_at(start * RADIOSITY_LEN as u64, older_slots, io)?;
        }
        let mut older_slots = older_slots.chunks_exact(RADIOSITY_LEN);
        for (slot, h_slot) in prev
            .chunks_exact_mut(RADIOSITY_LEN)
            .zip(h_slots.chunks_exact(LIGHT32_LEN))
        {
            let before_last = older_slots.next().map(decode_radiosity);
            let s = stream.next().ok_or_else(|| OocError::BadData {
                source_name: source.describe(),
                what: "it ended before its stated count of surfels".to_string(),
            })??;
            for m in s.material {
                used[m as usize] = true;
            }
            let emission = s
                .material
                .map(|m| info.materials[m as usize].emission.map(|e| e as f32));
            result.emitting += crate::solve::direct::emits(&emission) as u64;
            let d = d_slots.next().map(decode_light32);
            let sides = s.material.map(|m| &info.materials[m as usize]);
            let (h, norm) = (decode_light32(h_slot), cosine_sum[s.normal_id as usize]);
            let scales = match &mut pass {
                UpdatePass::Update(scales) => *scales,
                UpdatePass::Closure(sums) => {
                    let b = decode_radiosity(slot);
                    sums.add(
                        &emission,
                        &carried(&b, &emission, direct.is_some()),
                        &h,
                        d.as_ref(),
                        channels,
                        norm,
                        s.area as f64,
                    );
                    continue;
                }
            };
            let b_new = update_surfel(
                &sides.map(|m| m.emission.map(|e| e as f32)),
                &sides.map(|m| m.reflectance),
                h,
                d.as_ref(),
                channels,
                &decode_radiosity(slot),
                before_last.as_ref().map(|b| (b, omega)),
                norm,
                s.area as f64,
                scales,
                &mut result.sums,
            );
            add_power(
                sides,
                h,
                d.as_ref(),
                channels,
                norm,
                s.area as f64,
                area_unit,
                scales,
                &mut result.sums,
            );
            encode_radiosity(&b_new, slot);
        }
        if writes {
            if let Some(kept) = &kept {
                kept.write_at(start * RADIOSITY_LEN as u64, &old, io)?;
            }
            canonical.write_at(start * RADIOSITY_LEN as u64, prev, io)?;
        }
        io.read += len * crate::storage::RECORD_LEN as u64;
        start += len;
    }
    // The stream's end checks the last shard's checksum.
    if let Some(item) = stream.next() {
        item?;
        return Err(OocError::BadData {
            source_name: source.describe(),
            what: "it holds more surfels than its stated count".to_string(),
        });
    }
    result.grey = info
        .materials
        .iter()
        .zip(&used)
        .all(|(m, &u)| !u || m.is_grey());
    Ok(result)
}

/// Adds the geometric tail `factor * (B - B_previous)` to the canonical radiosity, chunk by
/// chunk, with `accelerate::extrapolate`'s rules (never below `E`, never lowering a rising
/// value); `previous` holds the radiosity the last update replaced.
fn extrapolate_canonical(
    source: &dyn SurfelSource,
    work: &WorkSet,
    plan: &MemoryPlan,
    previous: &Path,
    factor: f64,
    io: &mut IoCounters,
) -> Result<(), OocError> {
    let info = source.info();
    let n = work.count;
    // Five radiosity-sized arrays per surfel of a chunk (bytes and decoded, now and before, and
    // the emission), inside the permutation chunk's share of the budget.
    let per_surfel = 5 * RADIOSITY_LEN as u64;
    let chunk = (plan.chunk_surfels * super::budget::CHUNK_BYTES_PER_SURFEL / per_surfel)
        .min(n)
        .max(1) as usize;
    let canonical = RecordFile::open(&work.canonical_radiosity)?;
    let kept = RecordFile::open(previous)?;
    let mut stream = source.stream(plan.io_bytes as u64)?;
    let mut bytes = vec![0u8; chunk * RADIOSITY_LEN];
    let mut old_bytes = vec![0u8; chunk * RADIOSITY_LEN];
    let (mut current, mut old, mut emission) = (
        Vec::with_capacity(chunk),
        Vec::with_capacity(chunk),
        Vec::with_capacity(chunk),
    );
    let mut start = 0u64;
    while start < n {
        let len = (chunk as u64).min(n - start) as usize;
        let (now, was) = (
            &mut bytes[..len * RADIOSITY_LEN],
            &mut old_bytes[..len * RADIOSITY_LEN],
        );
        canonical.read_at(start * RADIOSITY_LEN as u64, now, io)?;
        kept.read_at(start * RADIOSITY_LEN as u64, was, io)?;
        current.clear();
        current.extend(now.chunks_exact(RADIOSITY_LEN).map(decode_radiosity));
        old.clear();
        old.extend(was.chunks_exact(RADIOSITY_LEN).map(decode_radiosity));
        emission.clear();
        for _ in 0..len {
            let s = stream.next().ok_or_else(|| OocError::BadData {
                source_name: source.describe(),
                what: "it ended before its stated count of surfels".to_string(),
            })??;
            emission.push(
                s.material
                    .map(|m| info.materials[m as usize].emission.map(|e| e as f32)),
            );
        }
        crate::solve::accelerate::extrapolate(&mut current, &old, &emission, factor);
        for (b, slot) in current.iter().zip(now.chunks_exact_mut(RADIOSITY_LEN)) {
            encode_radiosity(b, slot);
        }
        canonical.write_at(start * RADIOSITY_LEN as u64, now, io)?;
        io.read += len as u64 * crate::storage::RECORD_LEN as u64;
        start += len as u64;
    }
    Ok(())
}

/// Sets a gathered file to hold `surfels` records (0 frees its disk; records added read as zero).
fn resize_gathered(path: &Path, surfels: u64) -> Result<(), OocError> {
    RecordFile::open(path)?.set_len(surfels * LIGHT32_LEN as u64)
}

/// Surfels per chunk of an update.
fn chunk_len(plan: &MemoryPlan, work: &WorkSet) -> usize {
    plan.chunk_surfels.min(work.count).max(1) as usize
}

/// The file, in canonical order, of what the lines carry: the canonical radiosity `B`, or with
/// the direct pass the reflected part `B - E` (as `solve::direct::DirectLight::reflected` makes
/// it), written beside it here. Each copy is sent it before its directions ([`send_to_copy`]).
fn lit_file(
    source: &dyn SurfelSource,
    work: &WorkSet,
    plan: &MemoryPlan,
    direct: bool,
    io: &mut IoCounters,
) -> Result<PathBuf, OocError> {
    if !direct {
        return Ok(work.canonical_radiosity.clone());
    }
    let info = source.info();
    let reflected = work.dir.path().join("radiosity-reflected.bin");
    let mut out = SeqWriter::create(&reflected, plan.io_bytes)?;
    let mut radiosity = SeqReader::<RADIOSITY_LEN>::open(&work.canonical_radiosity, plan.io_bytes)?;
    let mut record = [0u8; RADIOSITY_LEN];
    for s in source.stream(plan.io_bytes as u64)? {
        let s = s?;
        let b = decode_radiosity(&radiosity.expect_record()?);
        let mut r: Radiosity = [[0.0; 3]; 2];
        for side in 0..2 {
            let e = info.materials[s.material[side] as usize].emission;
            for ch in 0..3 {
                r[side][ch] = (b[side][ch] as f64 - e[ch] as f32 as f64) as f32;
            }
        }
        encode_radiosity(&r, &mut record);
        out.write(&record)?;
    }
    io.read += work.count * (RADIOSITY_LEN + crate::storage::RECORD_LEN) as u64;
    io.written += out.finish()?;
    Ok(reflected)
}

/// Sends the canonical values of `from` (radiosity-sized records) to copy `m`'s radiosity file,
/// in that copy's order.
fn send_to_copy(
    work: &WorkSet,
    plan: &MemoryPlan,
    from: &Path,
    m: usize,
    io: &mut IoCounters,
) -> Result<(), OocError> {
    let n = work.count;
    let chunk = plan.chunk_surfels.min(n).max(1);
    let buffer = plan.bucket_buffer(n.div_ceil(chunk));
    let copy = &work.copies[m];
    let mut scatter = Scatter::<RADIOSITY_LEN>::new(
        work.dir.path(),
        &format!("radiosity-{}", copy.main),
        n,
        chunk,
        buffer,
    )?;
    let mut positions = IndexReader::open(&copy.positions, plan.io_bytes)?;
    let mut radiosity = SeqReader::<RADIOSITY_LEN>::open(from, plan.io_bytes)?;
    while let Some(p) = positions.next_value()? {
        scatter.push(p as u64, &radiosity.expect_record()?)?;
    }
    positions.count_into(io);
    io.read += n * RADIOSITY_LEN as u64;
    let mut reader = scatter.into_chunks()?;
    let mut out = SeqWriter::create(&copy.radiosity, plan.io_bytes)?;
    let mut values: Vec<[u8; RADIOSITY_LEN]> = vec![[0u8; RADIOSITY_LEN]; chunk as usize];
    while let Some((_, len)) = reader.next_chunk(|at, value| values[at] = *value)? {
        for v in &values[..len as usize] {
            out.write(v)?;
        }
    }
    io.written += out.finish()? + reader.written;
    io.read += reader.read;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn even_iterations_walk_backwards_from_where_the_odd_ones_end() {
        let directions = DirectionSet::with_count(49);
        let by_axis = walk_by_axis(&directions);
        let steps = |walk: &Walk| -> Vec<(usize, usize)> {
            walk.iter()
                .flat_map(|(m, axis)| axis.iter().map(move |&d| (*m, d)))
                .collect()
        };
        let odd = steps(&walk_of_iteration(&by_axis, 1));
        let even = steps(&walk_of_iteration(&by_axis, 2));
        // Every direction once, each on its own main axis.
        let mut seen: Vec<usize> = odd.iter().map(|&(_, d)| d).collect();
        seen.sort_unstable();
        assert_eq!(seen, (0..directions.len()).collect::<Vec<_>>());
        for &(m, d) in &odd {
            assert!(by_axis[m].contains(&d));
        }
        // The even walk is the odd one backwards: it begins on the axis and with the direction
        // the odd one ends with, and the odd one after it with the even one's last.
        assert_eq!(even, odd.iter().rev().copied().collect::<Vec<_>>());
        assert_eq!(even[0], *odd.last().unwrap());
        assert_eq!(steps(&walk_of_iteration(&by_axis, 3)), odd);
        assert!(!walks_backwards(1) && walks_backwards(2) && !walks_backwards(3));
        // Where an even iteration's axes end, as a checkpoint counts its directions.
        let spans = AxisSpans::new(&walk_of_iteration(&by_axis, 2));
        let last = by_axis[2].len() as u64;
        assert_eq!(
            spans.position(last, false),
            Some(Position {
                axes: 1,
                directions: 0
            })
        );
    }

    #[test]
    fn positions_inside_and_at_the_end_of_main_axes() {
        // Axes of 3, 0 and 4 directions.
        let axes = AxisSpans::new(&walk_of_iteration(
            &[vec![7, 8, 9], vec![], vec![1, 2, 3, 4]],
            1,
        ));
        let at = |axes, directions| Position { axes, directions };
        assert_eq!(axes.position(2, true), Some(at(0, 2)));
        assert_eq!(axes.position(5, true), Some(at(2, 2)));
        // The end of an axis is no place inside one, and the inside no axis's end.
        assert_eq!(axes.position(3, true), None);
        assert_eq!(axes.position(0, true), None);
        assert_eq!(axes.position(2, false), None);
        assert_eq!(axes.position(3, false), Some(at(1, 0)));
        for done in 1..7 {
            for inside in [true, false] {
                if let Some(p) = axes.position(done, inside) {
                    assert_eq!(axes.done(p), done);
                }
            }
        }
        // The empty axis's end is the first's: resumed there, the third axis comes next.
        assert_eq!(axes.done(at(2, 0)), 3);
        assert_eq!(axes.done(at(3, 0)), 7);
    }
}

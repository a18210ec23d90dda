//! The out-of-core iteration loop: directions grouped by main axis, each solved band by band
//! ([`super::band`]); then the light gathered in the three copies is brought to canonical order,
//! `B = E + rho H / S(n)` is computed there with the stopping rule of `solve::jacobi`, and the
//! new radiosity is sent back to the copies ([`super::scatter`]).

use super::band::{BandBuffers, BandTimes, CopyFiles, DirectionPass};
use super::budget::MemoryPlan;
use super::files::{
    decode_gathered, decode_radiosity, encode_radiosity, Gathered, IoCounters, Radiosity,
    RecordFile, SeqReader, SeqWriter, GATHER_LEN, RADIOSITY_LEN,
};
use super::scatter::Scatter;
use super::source::SurfelSource;
use super::workset::{self, WorkSet};
use super::OocError;
use crate::geometry::directions::DirectionSet;
use crate::solve::jacobi::error_estimate;
use crate::solve::normalize::cosine_sums;
use crate::solve::{SolveOptions, SolveStats};
use crate::voxel::Surfel;
use std::path::Path;
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
    /// Bands solved (over all directions and iterations).
    pub bands: u64,
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

/// Solves `source` out of core with work files in a temporary directory under `work_parent`.
pub fn solve_out_of_core(
    source: &dyn SurfelSource,
    directions: &DirectionSet,
    options: &SolveOptions,
    budget_bytes: u64,
    work_parent: &Path,
) -> Result<OocSolution, OocError> {
    let threads = if options.threads == 0 {
        rayon::current_num_threads()
    } else {
        options.threads
    };
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
            threads,
        )
    })
}

fn run(
    source: &dyn SurfelSource,
    directions: &DirectionSet,
    options: &SolveOptions,
    budget_bytes: u64,
    work_parent: &Path,
    threads: usize,
) -> Result<OocSolution, OocError> {
    let info = source.info();
    let plan = MemoryPlan::new(budget_bytes, info.grid.dims, threads)?;
    tracing::info!(
        budget = super::budget::format_bytes(budget_bytes),
        band_surfels = plan.band_surfels,
        sort_records = plan.sort_records,
        chunk_surfels = plan.chunk_surfels,
        "out-of-core plan"
    );
    let mut io = IoCounters::default();
    let started = Instant::now();
    let work = workset::build(source, &plan, work_parent, &mut io)?;
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
    let first = update(source, &work, &plan, &cosine_sum, false, &mut io)?;
    stats.update_seconds += t.elapsed().as_secs_f64();
    let any_light = first.emitted.iter().any(|&e| e > 0.0);

    // Directions by main axis, in set order within an axis.
    let by_axis: Vec<Vec<usize>> = (0..3)
        .map(|m| {
            (0..directions.len())
                .filter(|&k| crate::geometry::lines::axes(directions.directions[k].vector).0 == m)
                .collect()
        })
        .collect();
    let files: Vec<CopyFiles> = work
        .copies
        .iter()
        .map(CopyFiles::open)
        .collect::<Result<_, _>>()?;
    let mut buffers = BandBuffers::default();
    let mut times = BandTimes::default();
    let mut previous_change: Option<f64> = None;
    let mut last = first;
    let progress = crate::progress::bar(directions.len() as u64, "iteration 1");
    let solve_started = Instant::now();
    for iteration in 1..=options.max_iterations {
        if !any_light {
            stats.solve.converged = true;
            break;
        }
        progress.reset();
        progress.set_message(format!("iteration {iteration}"));
        let mut gathered_any = false;
        for (m, copy) in work.copies.iter().enumerate() {
            if by_axis[m].is_empty() {
                continue;
            }
            let histogram = copy.load_histogram(&plan)?;
            for (k, &d) in by_axis[m].iter().enumerate() {
                let pass = DirectionPass {
                    copy,
                    files: &files[m],
                    histogram: &histogram,
                    dims: info.grid.dims,
                    plan: &plan,
                    threads,
                    first: k == 0,
                };
                pass.run(&directions.directions[d], &mut buffers, &mut io, &mut times)?;
                progress.inc(1);
            }
            gathered_any = true;
        }
        let used: Vec<bool> = by_axis.iter().map(|b| !b.is_empty()).collect();
        stats.solve.updates += work.count * directions.len() as u64;
        let t = Instant::now();
        let result = update_with(
            source,
            &work,
            &plan,
            &cosine_sum,
            &used,
            gathered_any,
            &mut io,
        )?;
        stats.update_seconds += t.elapsed().as_secs_f64();
        let relative = if result.total > 0.0 {
            result.change / result.total
        } else {
            0.0
        };
        let estimate = error_estimate(relative, previous_change);
        stats.solve.iterations = iteration;
        stats.solve.last_change = relative;
        stats.solve.residual = estimate;
        tracing::info!(
            iteration,
            change = format!("{relative:.3e}"),
            estimated_error = format!("{estimate:.3e}"),
            seconds = format!("{:.1}", solve_started.elapsed().as_secs_f64()),
            "iteration done"
        );
        previous_change = Some(relative);
        last = result;
        if options.tolerance.is_some_and(|tol| estimate <= tol) {
            stats.solve.converged = true;
            break;
        }
    }
    progress.finish_and_clear();
    if options.tolerance.is_none() {
        stats.solve.converged =
            stats.solve.residual <= SolveOptions::default().tolerance.unwrap_or(0.0);
    }
    stats.solve.emitted_power = last.emitted;
    stats.solve.absorbed_power = last.absorbed;
    stats.solve.dispatch_seconds = times.dispatch;
    stats.solve.propagate_seconds = times.propagate;
    stats.read_seconds = times.read;
    stats.write_seconds = times.write;
    stats.bands = times.bands;
    stats.bytes_read = io.read;
    stats.bytes_written = io.written;
    Ok(OocSolution {
        stats,
        work,
        io_bytes: plan.io_bytes,
    })
}

/// What one update of the radiosity found.
#[derive(Clone, Copy, Debug, Default)]
struct Update {
    change: f64,
    total: f64,
    emitted: [f64; 3],
    absorbed: [f64; 3],
}

/// The first update: `B = E` everywhere.
fn update(
    source: &dyn SurfelSource,
    work: &WorkSet,
    plan: &MemoryPlan,
    cosine_sum: &[f64],
    gathered: bool,
    io: &mut IoCounters,
) -> Result<Update, OocError> {
    update_with(source, work, plan, cosine_sum, &[false; 3], gathered, io)
}

/// `B = E + rho H / S(n)` in canonical order, from the gathered files of the copies marked
/// `used` (none: `H = 0`), then the new `B` sent to every copy.
fn update_with(
    source: &dyn SurfelSource,
    work: &WorkSet,
    plan: &MemoryPlan,
    cosine_sum: &[f64],
    used: &[bool],
    gathered: bool,
    io: &mut IoCounters,
) -> Result<Update, OocError> {
    let info = source.info();
    let n = work.count;
    let chunk = plan.chunk_surfels.min(n).max(1);
    let chunks = n.div_ceil(chunk);
    // Four scatters at once (gathered light in, radiosity out to three copies) share the
    // buckets' half of the working memory.
    let buffer = plan.bucket_buffer(4 * chunks);
    // 1. The gathered light of every copy, to canonical chunks.
    let mut gathered_chunks = if gathered {
        let mut scatter =
            Scatter::<GATHER_LEN>::new(work.dir.path(), "gathered", n, chunk, buffer)?;
        for (copy, _) in work.copies.iter().zip(used).filter(|(_, &u)| u) {
            let mut ids = SeqReader::<4>::open(&copy.ids, plan.io_bytes)?;
            let mut values = SeqReader::<GATHER_LEN>::open(&copy.gathered, plan.io_bytes)?;
            while let Some(id) = ids.next_record()? {
                let value = values.expect_record()?;
                scatter.push(u32::from_le_bytes(id) as u64, &value)?;
            }
            io.read += n * (4 + GATHER_LEN as u64);
        }
        Some(scatter.into_chunks()?)
    } else {
        None
    };
    // 2. Canonical pass.
    let mut out_scatters = Vec::with_capacity(3);
    let mut positions = Vec::with_capacity(3);
    for copy in &work.copies {
        out_scatters.push(Scatter::<RADIOSITY_LEN>::new(
            work.dir.path(),
            &format!("radiosity-{}", copy.main),
            n,
            chunk,
            buffer,
        )?);
        positions.push(SeqReader::<4>::open(&copy.positions, plan.io_bytes)?);
    }
    let canonical = RecordFile::open(&work.canonical_radiosity)?;
    let mut stream = source.stream(plan.io_bytes as u64)?;
    let area_unit = info.grid.voxel_size * info.grid.voxel_size;
    let mut result = Update::default();
    let mut h: Vec<Gathered> = Vec::new();
    let mut bytes = vec![0u8; chunk as usize * RADIOSITY_LEN];
    let mut start = 0u64;
    while start < n {
        let len = chunk.min(n - start);
        h.clear();
        h.resize(len as usize, [[0.0; 3]; 2]);
        if let Some(reader) = gathered_chunks.as_mut() {
            reader.next_chunk(|at, value| {
                let add = decode_gathered(value);
                for (t, a) in h[at].iter_mut().flatten().zip(add.iter().flatten()) {
                    *t += a;
                }
            })?;
        }
        let prev = &mut bytes[..len as usize * RADIOSITY_LEN];
        canonical.read_at(start * RADIOSITY_LEN as u64, prev, io)?;
        for (k, slot) in prev.chunks_exact_mut(RADIOSITY_LEN).enumerate() {
            let s = stream.next().ok_or_else(|| OocError::BadData {
                source_name: source.describe(),
                what: "it ended before its stated count of surfels".to_string(),
            })??;
            let previous = decode_radiosity(slot);
            let norm = cosine_sum[s.normal_id as usize];
            let area = s.area as f64;
            let mut b_new: Radiosity = [[0.0; 3]; 2];
            for side in 0..2 {
                let m = &info.materials[s.material[side] as usize];
                for ch in 0..3 {
                    let e = m.emission[ch] as f32 as f64;
                    let b = e + m.reflectance[ch] * h[k][side][ch] / norm;
                    result.change += area * (b - previous[side][ch] as f64).abs();
                    result.total += area * b;
                    b_new[side][ch] = b as f32;
                    result.emitted[ch] += m.emission[ch] * area * area_unit;
                    result.absorbed[ch] +=
                        (1.0 - m.reflectance[ch]) * h[k][side][ch] / norm * area * area_unit;
                }
            }
            encode_radiosity(&b_new, slot);
            let mut value = [0u8; RADIOSITY_LEN];
            value.copy_from_slice(slot);
            for (scatter, pos) in out_scatters.iter_mut().zip(positions.iter_mut()) {
                let p = u32::from_le_bytes(pos.expect_record()?);
                scatter.push(p as u64, &value)?;
            }
        }
        canonical.write_at(start * RADIOSITY_LEN as u64, prev, io)?;
        io.read += len * (crate::storage::RECORD_LEN as u64 + 12);
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
    if let Some(reader) = gathered_chunks {
        io.written += reader.written;
        io.read += reader.read;
    }
    drop(h);
    // 3. The new radiosity to each copy, in copy order.
    for (copy, scatter) in work.copies.iter().zip(out_scatters) {
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
    }
    Ok(result)
}

//! The data and hybrid modes (paper, sections 4 and 5): ranks own whole lines, and surfels
//! travel to the rank that owns their line as the directions turn.
//!
//! Every rank holds a share of the surfels with their radiosity and the light they have gathered
//! so far in this iteration (`Held`). Per direction, in the walk order of `DirectionSet` (octant by
//! octant, neighbours on the sphere one after another):
//!
//! 1. **balance**: the elastic distribution of the direction's lines over the group's ranks
//!    ([`balance`](super::balance)), found from histograms added over ranks in the first
//!    iteration and remembered for the later ones;
//! 2. **fill**: the surfels whose line now belongs to another rank are packed per destination,
//!    in the order they are held (sorted along the direction's octant order), and compressed with
//!    zstd where that pays;
//! 3. **exchange**: one all-to-all with variable counts;
//! 4. **merge**: the kept surfels and the received packs, each sorted, are merged k-way into the
//!    octant order (a full sort only when the octant order changes, four times per iteration);
//! 5. **dispatch and propagate**: the in-memory solver's, on the held surfels, which now hold
//!    every line they touch whole. The first time, the partner links are written down
//!    ([`HeldLinks`], within the links budget); later iterations replay them instead (the
//!    held surfels and their order are the same each time, only their slots differ).
//!
//! **The direct-light pass** (`solve::direct`) runs once before the iterations, as on one
//! process: every rank holds the scene, so its dense directions are dealt over the world and its
//! light summed across it; the lines then carry `B - E` and the update adds `rho` times the
//! direct light, surfel by surfel.
//!
//! A surfel's gathered light is accumulated in direction order, on whichever rank holds it, and
//! each line is processed from the same surfels in the same order as on one process: the data
//! mode gives the single-process radiosity bit for bit (the stopping rule's sums are added in
//! another grouping, which can only move a borderline stop by one iteration; the direct pass's
//! light is summed across ranks, as in the directions mode, and agrees to rounding).
//!
//! **Checkpoints.** At an iteration boundary the radiosity is gathered by id and rank 0 writes
//! it. Inside an iteration the whole world agrees between two steps (one direction of every
//! group) on a stop signal and on saving; a save holds each rank's light of the surfels it holds,
//! by id. A resume rebuilds every rank's surfels from the first iteration's distributions of the
//! directions done (found again: they depend on the scene only), so the rest of the iteration
//! sees the same lines in the same order and the result is the uninterrupted run's bits.
//!
//! **Hybrid.** The ranks form `G` groups of equal size; group `g` takes the `g`-th contiguous
//! block of directions (contiguous, so that the directions a group walks stay close) and spreads
//! the data over its ranks. At the end of an iteration every group brings its surfels to one
//! canonical distribution (blocks of surfel ids), so that the `k`-th rank of every group holds
//! the same surfels; those ranks add their gathered light, in group order, and all update `B`.
//!
//! In this in-memory form every rank reads and voxelizes the whole scene (the surfel set is the
//! input of this function) and keeps the scene tables; only the solver's per-surfel state is
//! distributed. With `--memory` the data mode runs out of core instead (`super::ooc`): each rank
//! reads only its slice of the scene and holds its share in work files within the budget.

mod checkpoints;
mod exchange;
mod held;
mod links;
mod wire;

use crate::checkpoint::{CheckpointError, Gathered, Radiosity, Saver, State};
use crate::comm::Comm;
use crate::distribute::balance::{self, Distribution, Projection};
use crate::geometry::directions::DirectionSet;
use crate::geometry::lines::LineFrame;
use crate::geometry::order;
use crate::solve::direct::{gather_direct, DirectLight, SenderBalance};
use crate::solve::dispatch::{dispatch, Lines, OrderedEntry};
use crate::solve::iterate::{iterate, Start, Sweep};
use crate::solve::jacobi::{
    gather_all_lines, material_tables, worker_pool, Checkpoints, SolveError, SolveOptions,
};
use crate::solve::links::{gather_and_record, rank_budget};
use crate::solve::normalize::cosine_sums;
use crate::solve::propagate::{prop_surfels, DirectionInput, PropSurfel};
use crate::solve::{Solution, SolveStats};
use crate::voxel::SurfelSet;
use held::{Held, RECORD_BYTES};
use links::HeldLinks;
use rayon::prelude::*;
use std::time::Instant;
use wire::{compare, merge_two, seal, unseal};

pub use crate::solve::stats::{DataStats, PhaseSeconds, RankOutOfCore};

/// How the data is distributed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DataOptions {
    /// Direction groups: 1 is the data mode, more the hybrid mode (`comm.size() / groups`
    /// ranks per group).
    pub groups: usize,
    /// Compress the exchanged packs with zstd. It shrinks them several times but costs a few
    /// nanoseconds per byte: it pays on a network slower than the compressor, not over shared
    /// memory.
    pub compress: bool,
}

/// Solves `set` in the data mode or the hybrid mode (see [`DataOptions`]). Every rank returns
/// the whole radiosity.
pub fn solve_data(
    set: &SurfelSet,
    directions: &DirectionSet,
    options: &SolveOptions,
    comm: &dyn Comm,
    data: DataOptions,
    checkpoints: Option<Checkpoints>,
) -> Result<Solution, SolveError> {
    let DataOptions { groups, compress } = data;
    let size = comm.size();
    if groups == 0 || size % groups != 0 {
        return Err(SolveError::Groups {
            groups,
            ranks: size,
        });
    }
    let (threads, pool) = worker_pool(options)?;
    let per_group = size / groups;
    let group = comm.rank() / per_group;
    // Both splits are collective: every rank makes them, in this order.
    let group_comm = comm.split(group);
    let peers = comm.split(group_comm.rank());
    let mut solver = DataSolver::new(set, directions, options, threads, &pool, groups, group);
    solver.compress = compress;
    // The direct light, once, as the one-process solver gathers it: every rank holds the whole
    // scene here, so the pass deals its directions over the world (see `solve::direct`).
    solver.direct = options
        .direct
        .directions_for(set, directions.len())
        .map(|dense| {
            gather_direct(
                set,
                &solver.surfels,
                &solver.emission,
                &dense,
                SenderBalance::PerDirection,
                comm,
                &pool,
            )
        });
    solver.run(comm, group_comm.as_ref(), peers.as_ref(), checkpoints)
}

/// The scene-wide tables every rank keeps, and the solve's settings.
struct DataSolver<'a> {
    set: &'a SurfelSet,
    directions: &'a DirectionSet,
    options: &'a SolveOptions,
    threads: usize,
    pool: &'a rayon::ThreadPool,
    groups: usize,
    group: usize,
    compress: bool,
    frames: Vec<LineFrame>,
    projections: Vec<Projection>,
    cosine_sum: Vec<f64>,
    emission: Vec<[[f32; 3]; 2]>,
    reflectance: Vec<[[f64; 3]; 2]>,
    surfels: Vec<PropSurfel>,
    channels: usize,
    /// The direct light of every surfel by id (`solve::direct`); the lines then carry `B - E`.
    direct: Option<DirectLight>,
}

/// Per-rank bookkeeping of the phases and of what moved.
#[derive(Default)]
struct Tally {
    seconds: PhaseSeconds,
    /// Surfels this rank sent away, per direction (summed over iterations).
    moved: Vec<f64>,
    bytes_packed: u64,
    bytes_sent: u64,
}

impl<'a> DataSolver<'a> {
    fn new(
        set: &'a SurfelSet,
        directions: &'a DirectionSet,
        options: &'a SolveOptions,
        threads: usize,
        pool: &'a rayon::ThreadPool,
        groups: usize,
        group: usize,
    ) -> Self {
        let dims = set.grid.dims;
        let (emission, reflectance) = material_tables(set);
        DataSolver {
            set,
            directions,
            options,
            threads,
            pool,
            groups,
            group,
            compress: false,
            frames: directions
                .directions
                .iter()
                .map(|d| LineFrame::new(d.vector, dims))
                .collect(),
            projections: (0..12)
                .map(|k| Projection::new(k / 3, k % 3, dims))
                .collect(),
            cosine_sum: pool.install(|| cosine_sums(&set.normals, directions)),
            emission,
            reflectance,
            surfels: prop_surfels(set),
            channels: if options.grey && crate::solve::effects::is_grey(set) {
                1
            } else {
                3
            },
            direct: None,
        }
    }

    /// The crossing plane and axes of direction `k` (by octant order and cube face).
    fn projection(&self, k: usize) -> &Projection {
        let v = self.directions.directions[k].vector;
        &self.projections[order::order_of(v) * 3 + balance::walk_face(v)]
    }

    /// The canonical share of rank `rank` of a group of `ranks`: a block of surfel ids.
    fn block(&self, rank: usize, ranks: usize) -> std::ops::Range<usize> {
        let n = self.set.surfels.len();
        n * rank / ranks..n * (rank + 1) / ranks
    }

    fn owner_of_id(&self, id: u32, ranks: usize) -> usize {
        let n = self.set.surfels.len();
        // The inverse of `block`: the last rank whose block starts at or before `id`.
        ((id as usize + 1) * ranks - 1) / n.max(1)
    }

    fn run(
        &self,
        world: &dyn Comm,
        group_comm: &dyn Comm,
        peers: &dyn Comm,
        mut checkpoints: Option<Checkpoints>,
    ) -> Result<Solution, SolveError> {
        let n = self.set.surfels.len();
        let d_count = self.directions.len();
        let (ranks, me) = (group_comm.size(), group_comm.rank());
        let mut sweep = DataSweep {
            solver: self,
            world,
            group_comm,
            peers,
            mine: (d_count * self.group / self.groups..d_count * (self.group + 1) / self.groups)
                .collect(),
            held: Held::default(),
            held_order: None,
            remembered: vec![None; d_count],
            tally: Tally {
                moved: vec![0.0; d_count],
                ..Default::default()
            },
            lines: Lines::default(),
            reflected: Vec::new(),
            previous: Vec::new(),
            links: HeldLinks::new(
                d_count,
                rank_budget(self.options.links_memory, self.set.surfels.len(), world),
            ),
        };
        for id in self.block(me, ranks) {
            let prop = self.surfels[id];
            let slot = sweep
                .held
                .store(id as u32, prop, self.emission[id], [[0.0; 3]; 2]);
            sweep.held.order.push(OrderedEntry {
                voxel: prop.voxel,
                index: slot,
            });
        }
        let mut stats = SolveStats {
            channels: self.channels,
            directions: d_count,
            threads: self.threads,
            ..Default::default()
        };
        let any_light = self
            .emission
            .iter()
            .any(|e| e.iter().flatten().any(|&v| v > 0.0));
        let steps = sweep.steps();
        let mut start = Start::fresh();
        if let Some(mut loaded) = checkpoints.as_mut().and_then(|c| c.resume.take()) {
            // The boundary the checkpoint holds (every rank has the whole of it).
            let resume_within = loaded.take_within(self.groups as u32, world.size());
            let held = &mut sweep.held;
            for e in &held.order {
                let slot = e.index as usize;
                held.radiosity[slot] = loaded.radiosity[held.ids[slot] as usize];
            }
            let mut within = 0;
            match resume_within {
                // Every rank has the same header: all continue inside, or none.
                Some((done, sums)) if (done as usize) < steps => {
                    assert_eq!(sums.len(), n, "a checkpoint is checked against the scene");
                    tracing::info!(
                        iteration = loaded.state.iteration + 1,
                        within = done,
                        "continuing inside an iteration from the checkpoint's partial sums"
                    );
                    let done_here = (done as usize).min(sweep.mine.len());
                    sweep.held_order = self.rebuild_within(
                        &mut sweep.held,
                        &sweep.mine[..done_here],
                        &mut sweep.remembered,
                        group_comm,
                        &loaded.radiosity,
                        &sums,
                    );
                    within = done as usize;
                }
                Some((done, _)) => tracing::warn!(
                    "the checkpoint's position ({done} steps into an iteration of {steps}) does \
                     not fit this run: that iteration starts from its beginning"
                ),
                None => {}
            }
            start = Start::resumed(&loaded.state, &loaded.path, within, &mut stats);
        }
        let saver = checkpoints.map(|c| c.saver);
        iterate(
            &mut sweep,
            self.options,
            world,
            saver,
            start,
            any_light,
            &mut stats,
        )?;
        stats.links = Some(sweep.links.stats(d_count, self.set.surfels.len(), world));
        let DataSweep {
            held,
            remembered,
            tally,
            ..
        } = sweep;
        stats.dispatch_seconds = tally.seconds.dispatch;
        stats.propagate_seconds = tally.seconds.propagate;
        stats.reduce_seconds = tally.seconds.reduce;
        stats.data = Some(self.summary(world, &tally, &remembered, stats.iterations));
        let radiosity = self.finish(&held, world, &mut stats);
        Ok(Solution { radiosity, stats })
    }

    /// Dispatch and propagation of direction `k` over the held surfels. With the direct pass the
    /// lines carry `B - E`, by slot in `reflected` (refilled here: the held surfels change with
    /// every direction).
    fn propagate(
        &self,
        k: usize,
        held: &mut Held,
        lines: &mut Lines,
        reflected: &mut Vec<Radiosity>,
        links: &mut HeldLinks,
        tally: &mut Tally,
    ) {
        let d = &self.directions.directions[k];
        let t0 = Instant::now();
        let Held {
            ids,
            prop,
            radiosity,
            acc,
            order,
            ..
        } = held;
        if self.direct.is_some() {
            // The one-process solver's `DirectLight::reflected`, by slot.
            reflected.resize(radiosity.len(), [[0.0; 3]; 2]);
            for e in order.iter() {
                let slot = e.index as usize;
                reflected[slot] = crate::solve::update::reflected_part(
                    &radiosity[slot],
                    &self.emission[ids[slot] as usize],
                );
            }
        }
        let input = DirectionInput {
            unit: d.unit,
            weight: d.solid_angle / std::f64::consts::PI,
            surfels: prop,
            radiosity: if self.direct.is_some() {
                reflected
            } else {
                radiosity
            },
            channels: self.channels,
        };
        let t1 = self.pool.install(|| {
            if links.replay(k, order, ids, &input, acc) {
                // Nothing dispatched: the replay is this direction's propagation.
                return t0;
            }
            dispatch(order, &self.frames[k], self.threads, lines);
            let t1 = Instant::now();
            if links.tried[k] {
                gather_all_lines(lines, &input, acc, self.threads);
            } else {
                let recorded = gather_and_record(lines, &input, acc, self.threads);
                links.keep(k, recorded, order, ids);
            }
            t1
        });
        tally.seconds.dispatch += (t1 - t0).as_secs_f64();
        tally.seconds.propagate += t1.elapsed().as_secs_f64();
    }

    /// `B = E + rho H / S` on the held surfels; returns the change it makes `[change, total,
    /// falling]` added over the world (group 0 speaks for every surfel once).
    fn update(&self, held: &mut Held, world: &dyn Comm) -> [f64; 3] {
        let mut sums = crate::solve::update::UpdateSums::default();
        for e in &held.order {
            let i = e.index as usize;
            let id = held.ids[i] as usize;
            let s = &self.set.surfels[id];
            held.radiosity[i] = crate::solve::update::update_surfel(
                &self.emission[id],
                &self.reflectance[id],
                held.acc[i],
                crate::solve::update::direct_of(self.direct.as_ref(), id),
                self.channels,
                &held.radiosity[i],
                self.cosine_sum[s.normal_id as usize],
                s.area as f64,
                &mut sums,
            );
        }
        let mut sums = if self.group == 0 {
            [sums.change, sums.total, sums.falling]
        } else {
            [0.0, 0.0, 0.0]
        };
        world.sum_in_place(&mut sums);
        sums
    }

    /// Exchanged fraction, imbalance, bytes and every rank's phase seconds.
    fn summary(
        &self,
        world: &dyn Comm,
        tally: &Tally,
        remembered: &[Option<Distribution>],
        iterations: usize,
    ) -> DataStats {
        let n = self.set.surfels.len().max(1) as f64;
        let mut moved = tally.moved.clone();
        let mut table = vec![0.0; PhaseSeconds::FIELDS * world.size()];
        table[PhaseSeconds::FIELDS * world.rank()..][..PhaseSeconds::FIELDS]
            .copy_from_slice(&tally.seconds.to_array());
        moved.extend_from_slice(&table);
        moved.push(tally.bytes_packed as f64);
        moved.push(tally.bytes_sent as f64);
        world.sum_in_place(&mut moved);
        let d_count = self.directions.len();
        let bytes_sent = moved.pop().unwrap_or(0.0) as u64;
        let bytes_packed = moved.pop().unwrap_or(0.0) as u64;
        let table = moved.split_off(d_count);
        let fractions: Vec<f64> = moved
            .iter()
            .map(|&m| m / (n * iterations.max(1) as f64))
            .collect();
        // Imbalance: every group found its own directions' distributions; gather them all.
        let mut imbalance = vec![0.0; d_count];
        for (k, d) in remembered.iter().enumerate() {
            if let Some(d) = d {
                if world.rank() % (world.size() / self.groups) == 0 {
                    imbalance[k] = d.imbalance();
                }
            }
        }
        world.sum_in_place(&mut imbalance);
        let used: Vec<f64> = imbalance.iter().copied().filter(|&x| x > 0.0).collect();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        let max = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        DataStats {
            groups: self.groups,
            ranks_per_group: world.size() / self.groups,
            exchanged_fraction: mean(&fractions),
            max_exchanged_fraction: max(&fractions),
            exchanged_by_direction: fractions.clone(),
            imbalance: if used.is_empty() { 1.0 } else { mean(&used) },
            max_imbalance: if used.is_empty() { 1.0 } else { max(&used) },
            bytes_packed,
            bytes_sent,
            per_rank: table
                .chunks(PhaseSeconds::FIELDS)
                .map(PhaseSeconds::from_slice)
                .collect(),
            out_of_core: Vec::new(),
        }
    }

    /// The whole radiosity on every rank (group 0's surfels added over the world), and the
    /// energy balance from the last gather.
    fn finish(&self, held: &Held, world: &dyn Comm, stats: &mut SolveStats) -> Vec<[[f32; 3]; 2]> {
        let n = self.set.surfels.len();
        let mut flat = vec![0.0f64; n * 6 + 9];
        let area_unit = self.set.grid.voxel_size * self.set.grid.voxel_size;
        let mut sums = crate::solve::update::UpdateSums::default();
        if self.group == 0 {
            for e in &held.order {
                let i = e.index as usize;
                let id = held.ids[i] as usize;
                let s = &self.set.surfels[id];
                for side in 0..2 {
                    for ch in 0..3 {
                        let c = if self.channels == 1 { 0 } else { ch };
                        flat[id * 6 + side * 3 + ch] = held.radiosity[i][side][c] as f64;
                    }
                }
                // As every loop adds it up (`solve::update::add_power`).
                crate::solve::update::add_power(
                    s.material.map(|m| &self.set.materials[m as usize]),
                    held.acc[i],
                    crate::solve::update::direct_of(self.direct.as_ref(), id),
                    self.channels,
                    self.cosine_sum[s.normal_id as usize],
                    s.area as f64,
                    area_unit,
                    &mut sums,
                );
            }
        }
        flat[n * 6..]
            .copy_from_slice(&[sums.emitted, sums.absorbed, sums.absorbed_direct].concat());
        world.sum_in_place(&mut flat);
        for ch in 0..3 {
            stats.emitted_power[ch] = flat[n * 6 + ch];
            stats.absorbed_power[ch] = flat[n * 6 + 3 + ch] + flat[n * 6 + 6 + ch];
        }
        if let Some(direct) = &self.direct {
            stats.direct = Some(direct.stats.clone());
        }
        flat[..n * 6]
            .chunks_exact(6)
            .map(|c| {
                [
                    [c[0] as f32, c[1] as f32, c[2] as f32],
                    [c[3] as f32, c[4] as f32, c[5] as f32],
                ]
            })
            .collect()
    }
}

/// The data and hybrid modes as the iteration loop drives them: the held surfels of this rank
/// (a store in RAM, by slot), lines dealt over the ranks of a group, groups over directions.
struct DataSweep<'s, 'a> {
    solver: &'s DataSolver<'a>,
    world: &'s dyn Comm,
    group_comm: &'s dyn Comm,
    /// The ranks of the same place in every group (hybrid: their light is added).
    peers: &'s dyn Comm,
    /// This group's directions.
    mine: Vec<usize>,
    held: Held,
    /// The octant order `held` is sorted in (None: by id).
    held_order: Option<usize>,
    /// Each direction's distribution, found in the first iteration.
    remembered: Vec<Option<Distribution>>,
    tally: Tally,
    lines: Lines,
    reflected: Vec<Radiosity>,
    /// The held radiosity the last update replaced, by slot (for the tail extrapolation).
    previous: Vec<Radiosity>,
    links: HeldLinks,
}

impl Sweep for DataSweep<'_, '_> {
    type Error = SolveError;

    fn steps(&self) -> usize {
        // One direction of every group each (a group with one direction fewer idles in the
        // last), so that the whole world can agree between two steps.
        self.solver.directions.len().div_ceil(self.solver.groups)
    }

    fn updates(&self) -> u64 {
        (self.solver.set.surfels.len() * self.solver.directions.len()) as u64
    }

    fn begin(&mut self, from: usize) -> Result<(), SolveError> {
        if from == 0 {
            self.held.acc.iter_mut().for_each(|a| *a = [[0.0; 3]; 2]);
        }
        Ok(())
    }

    fn step(&mut self, step: usize) -> Result<bool, SolveError> {
        let Some(&k) = self.mine.get(step) else {
            return Ok(true);
        };
        let solver = self.solver;
        let d = &solver.directions.directions[k];
        let o = order::order_of(d.vector);
        let t = Instant::now();
        if self.remembered[k].is_none() {
            let previous = self
                .mine
                .iter()
                .rev()
                .skip_while(|&&j| j != k)
                .nth(1)
                .and_then(|&j| self.remembered[j].as_ref())
                .map(Distribution::bands);
            self.remembered[k] = Some(solver.balance(k, &self.held, self.group_comm, previous));
        }
        let distribution = self.remembered[k].as_ref().expect("just filled");
        self.tally.seconds.balance += t.elapsed().as_secs_f64();
        let bins = solver.projection(k).lines(&solver.frames[k], d.vector);
        let table = distribution.table();
        let owner = |voxel: [i32; 3], _id: &dyn Fn() -> u32| {
            let (row, col) = bins.bin(voxel);
            table.owner(row, col)
        };
        solver.redistribute(
            &mut self.held,
            self.held_order,
            o,
            self.group_comm,
            &mut self.tally,
            k,
            owner,
        );
        self.held_order = Some(o);
        solver.propagate(
            k,
            &mut self.held,
            &mut self.lines,
            &mut self.reflected,
            &mut self.links,
            &mut self.tally,
        );
        Ok(true)
    }

    fn can_save_within(&self, done: usize) -> bool {
        // A resume rebuilds the held surfels of the directions done; after the last step the
        // iteration's boundary is next.
        done < self.steps()
    }

    fn save_within(
        &mut self,
        saver: &mut Saver,
        state: State,
        done: usize,
    ) -> Result<(), CheckpointError> {
        self.solver
            .save_within(self.world, saver, state, done, &self.held)
    }

    fn save_boundary(&mut self, saver: &mut Saver, state: State) -> Result<(), CheckpointError> {
        // Collective: every rank gathers, rank 0 writes.
        let radiosity = self.solver.gather_radiosity(&self.held, self.world);
        saver.save_memory(state, &radiosity)
    }

    fn end(&mut self) -> Result<[f64; 3], SolveError> {
        let t = Instant::now();
        let solver = self.solver;
        if solver.groups > 1 {
            // One canonical distribution, then the peers' light added in group order.
            let ranks = self.group_comm.size();
            let block_owner = |_: [i32; 3], id: &dyn Fn() -> u32| solver.owner_of_id(id(), ranks);
            solver.redistribute(
                &mut self.held,
                None,
                0,
                self.group_comm,
                &mut self.tally,
                usize::MAX,
                block_owner,
            );
            self.held_order = None;
            let held = &mut self.held;
            let mut flat: Vec<f64> = held
                .order
                .iter()
                .flat_map(|e| held.acc[e.index as usize].into_iter().flatten())
                .collect();
            self.peers.sum_in_place(&mut flat);
            for (e, v) in held.order.iter().zip(flat.chunks_exact(6)) {
                let a = &mut held.acc[e.index as usize];
                a[0].copy_from_slice(&v[..3]);
                a[1].copy_from_slice(&v[3..]);
            }
        }
        if solver.options.accelerate {
            self.previous.clone_from(&self.held.radiosity);
        }
        let sums = solver.update(&mut self.held, self.world);
        self.tally.seconds.reduce += t.elapsed().as_secs_f64();
        Ok(sums)
    }

    fn extrapolate(&mut self, factor: f64) -> Result<(), SolveError> {
        let t = Instant::now();
        let solver = self.solver;
        let emission: Vec<Radiosity> = self
            .held
            .ids
            .iter()
            .map(|&id| solver.emission[id as usize])
            .collect();
        crate::solve::accelerate::extrapolate(
            &mut self.held.radiosity,
            &self.previous,
            &emission,
            factor,
        );
        self.tally.seconds.reduce += t.elapsed().as_secs_f64();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn canonical_blocks_invert() {
        for n in [1usize, 7, 100, 101] {
            for ranks in 1..6 {
                let set_len = n;
                let block = |r: usize| set_len * r / ranks..set_len * (r + 1) / ranks;
                for r in 0..ranks {
                    for id in block(r) {
                        let owner = ((id + 1) * ranks - 1) / n;
                        assert_eq!(owner, r, "n {n} ranks {ranks} id {id}");
                    }
                }
            }
        }
    }
}

//! The data and hybrid modes (paper, sections 4 and 5): ranks own whole lines, and surfels
//! travel to the rank that owns their line as the directions turn.
//!
//! Every rank has the surfels its lines have held so far, with their radiosity and its own part
//! of their light (`Held`). Per direction, in the walk order of `DirectionSet` (octant by
//! octant, neighbours on the sphere one after another):
//!
//! 1. **balance**: the elastic distribution of the direction's lines over the group's ranks
//!    ([`balance`](super::balance)), found from histograms added over ranks in the first
//!    iteration and remembered for the later ones;
//! 2. **fill**: the surfels whose line now belongs to another rank are packed per destination
//!    (id and radiosity), in the order they are held (sorted along the direction's octant
//!    order), and compressed with zstd where that pays;
//! 3. **exchange**: one all-to-all with variable counts;
//! 4. **merge**: the kept surfels and the received packs, each sorted, are merged k-way into the
//!    octant order (a full sort only when the octant order changes, four times per iteration);
//!    the exchange is written down as the direction's plan (`plan`), which later exchanges
//!    follow without placing a surfel on its bin or comparing two;
//! 5. **dispatch and propagate**: the in-memory solver's, on the held surfels, which now hold
//!    every line they touch whole. The first time, the partner links are written down
//!    ([`HeldLinks`], within the links budget); later iterations replay them instead.
//!
//! **Light stays where it is gathered.** A rank adds what its lines gather to its own part of
//! each surfel's light, by the surfel's place (`Held`), and the parts are added over the world
//! once, at the end of the iteration, on the rank that owns the surfel's radiosity (a block of
//! ids, `Owned`), which updates `B` and sends it back to every rank that has the surfel
//! (`reduce`; a grey scene's parts and radiosity travel as one channel). So once the first
//! iteration has brought each rank every surfel its lines will hold, an iteration whose links
//! every rank of a group kept moves no surfel at all: it is the replay of the links of each
//! direction, then that one exchange. Like the directions mode, a surfel's light is thus added
//! in another grouping than on one process: the answer agrees with the one process's to
//! rounding (on one rank, bit for bit), and it is the same for any thread count and after any
//! resume.
//!
//! **The direct-light pass** (`solve::direct`) runs once before the iterations, as on one
//! process: every rank holds the scene, so its dense directions are dealt over the world and its
//! light summed across it; the lines then carry `B - E` and the update adds `rho` times the
//! direct light, surfel by surfel.
//!
//! **Checkpoints.** At an iteration boundary the owners' radiosity is gathered by id and rank 0
//! writes it. Inside an iteration the whole world agrees between two steps (one direction of
//! every group) on a stop signal and on saving; a save holds each rank's part of the light, by
//! id. A resume rebuilds every rank's surfels from the first iteration's distributions of the
//! directions done (found again: they depend on the scene only), so the rest of the iteration
//! sees the same lines in the same order and the result is the uninterrupted run's bits.
//!
//! **Hybrid.** The ranks form `G` groups of equal size; group `g` takes the `g`-th contiguous
//! block of directions (contiguous, so that the directions a group walks stay close) and spreads
//! the data over its ranks; the end of the iteration adds the parts of every rank of the world
//! alike.
//!
//! In this in-memory form every rank reads and voxelizes the whole scene (the surfel set is the
//! input of this function) and keeps the scene tables; only the solver's per-surfel state is
//! distributed. With `--memory` the data mode runs out of core instead (`super::ooc`): each rank
//! reads only its slice of the scene and holds its share in work files within the budget.

mod checkpoints;
mod exchange;
mod held;
mod links;
mod plan;
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
use crate::solve::kept_links::{Blocks, BLOCK_STEPS};
use crate::solve::links::{gather_and_record, rank_budget, record_links};
use crate::solve::normalize::cosine_sums;
use crate::solve::propagate::{prop_surfels, DirectionInput, PropSurfel};
use crate::solve::{Solution, SolveStats};
use crate::voxel::SurfelSet;
use held::{Held, RECORD_BYTES};
use links::HeldLinks;
use plan::{ExchangePlan, ExchangePlans, Origin};
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
    // The split is collective: every rank makes it.
    let group_comm = comm.split(group);
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
    solver.run(comm, group_comm.as_ref(), checkpoints)
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
    /// Whether the scene's light is sealed in (`solve::closed`).
    closure: crate::solve::enclosure::Verdict,
}

/// Per-rank bookkeeping of the phases and of what moved.
#[derive(Default)]
struct Tally {
    seconds: PhaseSeconds,
    /// Surfels this rank sent away, per direction (summed over iterations).
    moved: Vec<f64>,
    /// Exchanges of each direction (iterations that replay have none).
    exchanges: Vec<u32>,
    bytes_packed: u64,
    bytes_sent: u64,
    /// Bytes of parts of the light and of radiosity this rank sent at the ends of iterations.
    end_bytes: u64,
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
            closure: crate::solve::enclosure::Enclosure::verdict_of_set(set),
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
        mut checkpoints: Option<Checkpoints>,
    ) -> Result<Solution, SolveError> {
        let n = self.set.surfels.len();
        let d_count = self.directions.len();
        let (ranks, me) = (group_comm.size(), group_comm.rank());
        let mut sweep = DataSweep {
            solver: self,
            world,
            group_comm,
            mine: (d_count * self.group / self.groups..d_count * (self.group + 1) / self.groups)
                .collect(),
            held: Held::new(n, self.direct.is_some()),
            owned: Owned::new(self.block(world.rank(), world.size()), &self.emission),
            sharing: Sharing::default(),
            held_order: None,
            from: Origin::Blocks,
            plans: ExchangePlans::new(d_count),
            replaying: false,
            remembered: vec![None; d_count],
            tally: Tally {
                moved: vec![0.0; d_count],
                exchanges: vec![0; d_count],
                ..Default::default()
            },
            lines: Lines::default(),
            links: HeldLinks::new(
                d_count * self.group / self.groups..d_count * (self.group + 1) / self.groups,
                rank_budget(self.options.links_memory, self.set.surfels.len(), world),
            ),
        };
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
            let owned = &mut sweep.owned;
            owned
                .radiosity
                .copy_from_slice(&loaded.radiosity[owned.ids.clone()]);
            if let Some(older) = &loaded.older {
                // The Chebyshev semi-iteration's next update mixes with it.
                owned.previous = older[owned.ids.clone()].to_vec();
            }
            self.meet_block(&mut sweep.held, me, ranks, &loaded.radiosity);
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
                    sweep.from = sweep.mine[..done_here]
                        .last()
                        .map_or(Origin::Blocks, |&k| Origin::After(k));
                    within = done as usize;
                }
                Some((done, _)) => tracing::warn!(
                    "the checkpoint's position ({done} steps into an iteration of {steps}) does \
                     not fit this run: that iteration starts from its beginning"
                ),
                None => {}
            }
            start = Start::resumed(&loaded.state, &loaded.path, within, &mut stats);
        } else {
            self.meet_block(&mut sweep.held, me, ranks, &self.emission);
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
            owned,
            remembered,
            mut tally,
            plans,
            sharing,
            ..
        } = sweep;
        tally.end_bytes = sharing.bytes;
        stats.dispatch_seconds = tally.seconds.dispatch;
        stats.propagate_seconds = tally.seconds.propagate;
        stats.reduce_seconds = tally.seconds.reduce;
        stats.data = Some(self.summary(world, &tally, &remembered, plans.bytes()));
        let radiosity = self.finish(&owned, world, &mut stats);
        Ok(Solution { radiosity, stats })
    }

    /// Gives `held` the canonical block of ids of rank `me` of a group of `ranks`, with their
    /// radiosity from `radiosity` (by id), in id order: where every solve starts.
    fn meet_block(&self, held: &mut Held, me: usize, ranks: usize, radiosity: &[Radiosity]) {
        for id in self.block(me, ranks) {
            let prop = self.surfels[id];
            let place = held.meet(id as u32, prop, radiosity[id], &self.emission[id]);
            held.order.push(OrderedEntry {
                voxel: prop.voxel,
                index: place,
            });
        }
    }

    /// Dispatch and propagation of direction `k` over the held surfels (with the direct pass,
    /// the lines carry `B - E`), or the replay of its links.
    fn propagate(
        &self,
        k: usize,
        held: &mut Held,
        lines: &mut Lines,
        links: &mut HeldLinks,
        tally: &mut Tally,
    ) {
        let d = &self.directions.directions[k];
        let t0 = Instant::now();
        let Held {
            prop,
            radiosity,
            reflected,
            acc,
            order,
            ..
        } = held;
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
        // As in one process (`solve::jacobi`): a direction's first gather may only write its
        // links down, its run being replayed whole at the run's end (`Sweep::step`); any other
        // first gathers the directions waiting, so that each side adds its terms in order.
        let defer = links.defers(k);
        let t1 = self.pool.install(|| {
            if !defer {
                links.settle(input.radiosity, input.channels, acc);
                if links.replay(k, &input, acc) {
                    // Nothing dispatched: the replay is this direction's propagation.
                    return t0;
                }
            }
            dispatch(order, &self.frames[k], self.threads, lines);
            let t1 = Instant::now();
            if defer {
                let recorded = record_links(lines, &input, self.threads, links.spare_words());
                links.keep_deferred(k, recorded, &input, acc);
            } else if links.tried(k) {
                gather_all_lines(lines, &input, acc, self.threads);
            } else {
                let recorded = gather_and_record(lines, &input, acc, self.threads);
                links.keep(k, recorded);
            }
            t1
        });
        tally.seconds.dispatch += (t1 - t0).as_secs_f64();
        tally.seconds.propagate += t1.elapsed().as_secs_f64();
    }

    /// The end of an iteration: every rank's part of the light of each surfel it has goes to
    /// the surfel's owner, which adds the parts in rank order and updates `B = E + rho H / S`;
    /// the new radiosity goes back to every rank that has the surfel. Returns the update's
    /// sums `[change, total, falling]` added over the world. Collective on `world`.
    fn reduce(
        &self,
        held: &mut Held,
        owned: &mut Owned,
        sharing: &mut Sharing,
        world: &dyn Comm,
        omega: f64,
    ) -> [f64; 4] {
        let (size, me) = (world.size(), world.rank());
        // Parts, by owner (each rank sends each surfel it has once: the owner's sum is in rank
        // order whatever order a pack lists them in).
        sharing.sent = vec![Vec::new(); size];
        for (place, &id) in held.ids.iter().enumerate() {
            sharing.sent[self.owner_of_id(id, size)].push(place as u32);
        }
        // Of a grey scene's gathered light only the first channel is read (`update_surfel`,
        // `ClosureSums`, `add_power`): that one is sent.
        let channels = self.channels;
        let part_bytes = 4 + 2 * channels * 8;
        // This rank's own parts are not packed: they are added in place, in their turn among
        // the ranks' (packing and exchanging them and their replies with itself was about a
        // fifth of the end of an iteration at 2 ranks).
        let packs = packs_for_others(&sharing.sent, me, part_bytes, |places, pack| {
            for &place in places {
                let place = place as usize;
                pack.extend_from_slice(&held.ids[place].to_le_bytes());
                for side in &held.acc[place] {
                    for a in &side[..channels] {
                        pack.extend_from_slice(&a.to_le_bytes());
                    }
                }
            }
        });
        // Counted with the own parts, as if sent: the figure tells the surfels a rank has met.
        sharing.bytes += (held.ids.len() * part_bytes) as u64;
        let received = world.exchange(packs);
        owned.acc.iter_mut().for_each(|a| *a = [[0.0; 3]; 2]);
        sharing.asked = Vec::with_capacity(size);
        for (from, pack) in received.iter().enumerate() {
            if from == me {
                let places = &sharing.sent[me];
                let mut ids = Vec::with_capacity(places.len());
                for &place in places {
                    let id = held.ids[place as usize];
                    let sum = &mut owned.acc[id as usize - owned.ids.start];
                    for (to, part) in sum.iter_mut().zip(&held.acc[place as usize]) {
                        for (v, a) in to[..channels].iter_mut().zip(&part[..channels]) {
                            *v += a;
                        }
                    }
                    ids.push(id);
                }
                sharing.asked.push(ids);
                continue;
            }
            let mut ids = Vec::with_capacity(pack.len() / part_bytes);
            for r in pack.chunks_exact(part_bytes) {
                let id = u32::from_le_bytes([r[0], r[1], r[2], r[3]]);
                let sum = &mut owned.acc[id as usize - owned.ids.start];
                let values = sum.iter_mut().flat_map(|side| &mut side[..channels]);
                for (v, bytes) in values.zip(r[4..].chunks_exact(8)) {
                    let mut b = [0u8; 8];
                    b.copy_from_slice(bytes);
                    *v += f64::from_le_bytes(b);
                }
                ids.push(id);
            }
            sharing.asked.push(ids);
        }
        if self.closure.closed {
            // A closed scene's scales, from the light of every owner (`solve::closed`).
            let mut closure = crate::solve::closed::ClosureSums::new(&self.set.materials);
            for (i, id) in owned.ids.clone().enumerate() {
                let s = &self.set.surfels[id];
                closure.add(
                    &self.emission[id],
                    &crate::solve::update::carried(
                        &owned.radiosity[i],
                        &self.emission[id],
                        self.direct.is_some(),
                    ),
                    &owned.acc[i],
                    crate::solve::update::direct_of(self.direct.as_ref(), id),
                    self.channels,
                    self.cosine_sum[s.normal_id as usize],
                    s.area as f64,
                );
            }
            closure.add_over(world);
            owned.scales = closure.scales(self.channels);
        }
        // The value each update replaces is kept (the tail extrapolation's and Chebyshev's
        // `B_{k-1}`).
        let keep = self.options.accelerate;
        if keep && owned.previous.len() != owned.radiosity.len() {
            owned.previous = owned.radiosity.clone();
        }
        let mut sums = crate::solve::update::UpdateSums::default();
        for (i, id) in owned.ids.clone().enumerate() {
            let s = &self.set.surfels[id];
            let current = owned.radiosity[i];
            let older = (omega != 1.0).then(|| (&owned.previous[i], omega));
            let updated = crate::solve::update::update_surfel(
                &self.emission[id],
                &self.reflectance[id],
                owned.acc[i],
                crate::solve::update::direct_of(self.direct.as_ref(), id),
                self.channels,
                &current,
                older,
                self.cosine_sum[s.normal_id as usize],
                s.area as f64,
                &owned.scales,
                &mut sums,
            );
            owned.radiosity[i] = updated;
            if keep {
                owned.previous[i] = current;
            }
        }
        let mut sums = [sums.change, sums.total, sums.falling, sums.residual];
        world.sum_in_place(&mut sums);
        self.share_radiosity(held, owned, sharing, world);
        sums
    }

    /// Sends the owners' radiosity to every rank that has the surfel (the ones each rank sent
    /// its parts of at the last `reduce`). A grey scene's radiosity is the same in every channel
    /// (`update::update_surfel` copies its first): one channel goes. Collective on `world`.
    fn share_radiosity(
        &self,
        held: &mut Held,
        owned: &Owned,
        sharing: &mut Sharing,
        world: &dyn Comm,
    ) {
        let channels = self.channels;
        let reply_bytes = 2 * channels * 4;
        let me = world.rank();
        // This rank's own surfels take their radiosity in place, below.
        let replies = packs_for_others(&sharing.asked, me, reply_bytes, |ids, out| {
            for &id in ids {
                for side in &owned.radiosity[id as usize - owned.ids.start] {
                    debug_assert!(channels == 3 || side.iter().all(|&b| b == side[0]));
                    for f in &side[..channels] {
                        out.extend_from_slice(&f.to_le_bytes());
                    }
                }
            }
        });
        // Counted with the own replies, as the parts are.
        sharing.bytes += (held.ids.len() * reply_bytes) as u64;
        let received = world.exchange(replies);
        // (Nothing before the first end of an iteration has filled the lists.)
        let own_places = sharing.sent.get(me).map_or(&[][..], Vec::as_slice);
        let own_ids = sharing.asked.get(me).map_or(&[][..], Vec::as_slice);
        for (&place, &id) in own_places.iter().zip(own_ids) {
            let mut b = owned.radiosity[id as usize - owned.ids.start];
            if channels == 1 {
                // As a reply carries a grey scene's radiosity: its first channel.
                b = b.map(|side| [side[0]; 3]);
            }
            held.set_radiosity(place as usize, b, &self.emission[id as usize]);
        }
        for (places, pack) in sharing.sent.iter().zip(&received) {
            for (&place, r) in places.iter().zip(pack.chunks_exact(reply_bytes)) {
                let f = |k: usize| f32::from_le_bytes([r[k], r[k + 1], r[k + 2], r[k + 3]]);
                let side = |first: usize| {
                    if channels == 1 {
                        [f(first); 3]
                    } else {
                        [f(first), f(first + 4), f(first + 8)]
                    }
                };
                let b = [side(0), side(4 * channels)];
                let id = held.ids[place as usize] as usize;
                held.set_radiosity(place as usize, b, &self.emission[id]);
            }
        }
    }

    /// Exchanged fraction, imbalance, bytes and every rank's phase seconds.
    fn summary(
        &self,
        world: &dyn Comm,
        tally: &Tally,
        remembered: &[Option<Distribution>],
        plan_bytes: u64,
    ) -> DataStats {
        let n = self.set.surfels.len().max(1) as f64;
        let d_count = self.directions.len();
        let mut moved = tally.moved.clone();
        moved.extend(tally.exchanges.iter().map(|&e| e as f64));
        let mut table = vec![0.0; PhaseSeconds::FIELDS * world.size()];
        table[PhaseSeconds::FIELDS * world.rank()..][..PhaseSeconds::FIELDS]
            .copy_from_slice(&tally.seconds.to_array());
        moved.extend_from_slice(&table);
        moved.push(plan_bytes as f64);
        moved.push(tally.end_bytes as f64);
        moved.push(tally.bytes_packed as f64);
        moved.push(tally.bytes_sent as f64);
        world.sum_in_place(&mut moved);
        let bytes_sent = moved.pop().unwrap_or(0.0) as u64;
        let bytes_packed = moved.pop().unwrap_or(0.0) as u64;
        let end_of_iteration_bytes = moved.pop().unwrap_or(0.0) as u64;
        let plan_bytes = moved.pop().unwrap_or(0.0) as u64;
        let table = moved.split_off(2 * d_count);
        let exchanges = moved.split_off(d_count);
        // Per exchange of the direction (iterations that replay move nothing); every rank of
        // the group counted the exchange.
        let per_group = (world.size() / self.groups) as f64;
        let fractions: Vec<f64> = moved
            .iter()
            .zip(&exchanges)
            .map(|(&m, &e)| m / (n * (e / per_group).max(1.0)))
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
            plan_bytes,
            end_of_iteration_bytes,
            per_rank: table
                .chunks(PhaseSeconds::FIELDS)
                .map(PhaseSeconds::from_slice)
                .collect(),
            out_of_core: Vec::new(),
            quiet_steps_skipped: 0,
        }
    }

    /// The whole radiosity on every rank (the owners' blocks added over the world), and the
    /// energy balance from the last iteration's light.
    fn finish(&self, owned: &Owned, world: &dyn Comm, stats: &mut SolveStats) -> Vec<Radiosity> {
        let n = self.set.surfels.len();
        let mut flat = vec![0.0f64; n * 6 + 9];
        let area_unit = self.set.grid.voxel_size * self.set.grid.voxel_size;
        let mut sums = crate::solve::update::UpdateSums::default();
        for (i, id) in owned.ids.clone().enumerate() {
            let s = &self.set.surfels[id];
            for side in 0..2 {
                for ch in 0..3 {
                    let c = if self.channels == 1 { 0 } else { ch };
                    flat[id * 6 + side * 3 + ch] = owned.radiosity[i][side][c] as f64;
                }
            }
            // As every loop adds it up (`solve::update::add_power`).
            crate::solve::update::add_power(
                s.material.map(|m| &self.set.materials[m as usize]),
                owned.acc[i],
                crate::solve::update::direct_of(self.direct.as_ref(), id),
                self.channels,
                self.cosine_sum[s.normal_id as usize],
                s.area as f64,
                area_unit,
                &owned.scales,
                &mut sums,
            );
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
        stats.closure = Some(crate::solve::stats::ClosureStats {
            verdict: self.closure,
            scales: owned.scales,
        });
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

/// The surfels whose radiosity this rank owns (a block of ids of the world): their radiosity,
/// the light of the last iteration added over the ranks, and the radiosity before the last
/// update (for the tail extrapolation).
struct Owned {
    ids: std::ops::Range<usize>,
    radiosity: Vec<Radiosity>,
    acc: Vec<Gathered>,
    previous: Vec<Radiosity>,
    /// The scales of the last update (a closed scene's; else 1), the same on every rank.
    scales: crate::solve::closed::Scales,
}

impl Owned {
    /// The block `ids`, starting from `B = E`.
    fn new(ids: std::ops::Range<usize>, emission: &[Radiosity]) -> Self {
        Owned {
            radiosity: emission[ids.clone()].to_vec(),
            acc: vec![[[0.0; 3]; 2]; ids.len()],
            previous: Vec::new(),
            scales: crate::solve::closed::Scales::ONE,
            ids,
        }
    }
}

/// One buffer per rank, filled by `fill` from that rank's list (`bytes_each` bytes an item),
/// and an empty one for this rank (`me`), whose own items are taken in place: what the ends of
/// iterations send.
fn packs_for_others(
    lists: &[Vec<u32>],
    me: usize,
    bytes_each: usize,
    mut fill: impl FnMut(&[u32], &mut Vec<u8>),
) -> Vec<Vec<u8>> {
    (lists.iter().enumerate())
        .map(|(rank, list)| {
            let mut pack = Vec::new();
            if rank != me {
                pack.reserve_exact(list.len() * bytes_each);
                fill(list, &mut pack);
            }
            pack
        })
        .collect()
}

/// Who has which surfel, as the last `reduce` found it: the places this rank sent parts of to
/// each owner, and the ids each rank sent parts of here (by source rank), so that the
/// radiosity can be sent back along the same lists.
#[derive(Default)]
struct Sharing {
    sent: Vec<Vec<u32>>,
    asked: Vec<Vec<u32>>,
    /// Bytes this rank sent at ends of iterations (own ones included).
    bytes: u64,
}

/// The data and hybrid modes as the iteration loop drives them: the surfels this rank has,
/// lines dealt over the ranks of a group, groups over directions.
struct DataSweep<'s, 'a> {
    solver: &'s DataSolver<'a>,
    world: &'s dyn Comm,
    group_comm: &'s dyn Comm,
    /// This group's directions.
    mine: Vec<usize>,
    held: Held,
    owned: Owned,
    sharing: Sharing,
    /// The octant order `held.order` is sorted in (None: by id).
    held_order: Option<usize>,
    /// What `held.order` was last distributed by.
    from: Origin,
    /// Each direction's exchange, recorded the first time (`plan`).
    plans: ExchangePlans,
    /// This iteration replays the kept links of every direction of the group, on every rank
    /// of it: no exchange until its end.
    replaying: bool,
    /// Each direction's distribution, found in the first iteration.
    remembered: Vec<Option<Distribution>>,
    tally: Tally,
    lines: Lines,
    links: HeldLinks,
}

impl DataSweep<'_, '_> {
    /// Brings the surfels whose lines direction `k` gives this rank here, by the direction's
    /// plan if one was recorded from where `held` is, else in full (recording the plan).
    fn distribute(&mut self, k: usize) {
        let solver = self.solver;
        let d = &solver.directions.directions[k];
        let o = order::order_of(d.vector);
        if let Some(plan) = self.plans.usable(k, self.from) {
            solver.redistribute_planned(plan, &mut self.held, self.group_comm, &mut self.tally, k);
        } else {
            let t = Instant::now();
            let mut fresh_bins = None;
            if self.remembered[k].is_none() {
                let previous = self
                    .mine
                    .iter()
                    .rev()
                    .skip_while(|&&j| j != k)
                    .nth(1)
                    .and_then(|&j| self.remembered[j].as_ref())
                    .map(Distribution::bands);
                let (distribution, bins) = solver.balance(k, &self.held, self.group_comm, previous);
                self.remembered[k] = Some(distribution);
                fresh_bins = Some(bins);
            }
            let distribution = self.remembered[k].as_ref().expect("just filled");
            self.tally.seconds.balance += t.elapsed().as_secs_f64();
            let t = Instant::now();
            let table = distribution.table();
            // One thread: a bin costs a few nanoseconds, and in rayon's pieces such a pass
            // took three times as long on one thread, and longer on two than alone.
            let owners: Vec<u32> = match fresh_bins {
                // One rank keeps everything.
                _ if self.group_comm.size() == 1 => Vec::new(),
                Some(bins) => bins
                    .iter()
                    .map(|&(r, c)| table.owner(r, c) as u32)
                    .collect(),
                None => {
                    let bins = solver.projection(k).lines(&solver.frames[k], d.vector);
                    self.held
                        .order
                        .iter()
                        .map(|e| {
                            let (r, c) = bins.bin(e.voxel);
                            table.owner(r, c) as u32
                        })
                        .collect()
                }
            };
            self.tally.seconds.fill += t.elapsed().as_secs_f64();
            let plan = solver.redistribute(
                &mut self.held,
                self.held_order,
                o,
                self.group_comm,
                &mut self.tally,
                k,
                self.from,
                &owners,
            );
            self.plans.keep(k, plan);
        }
        self.from = Origin::After(k);
        self.held_order = Some(o);
    }
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

    fn begin(&mut self, _iteration: usize, from: usize) -> Result<(), SolveError> {
        if from == 0 {
            self.held.acc.iter_mut().for_each(|a| *a = [[0.0; 3]; 2]);
        }
        // Replay without exchanges only if every rank of the group kept every direction's
        // links (the exchanges are collective in the group).
        let all_kept = self.links.all_kept();
        self.replaying = self.group_comm.max_u64(u64::from(!all_kept)) == 0;
        // On several ranks, blocks of links where every rank of every group kept every link:
        // the steps at which the light can be saved are then the same on every rank
        // (`solve::kept_links`).
        let blocks = if self.world.size() == 1 {
            Blocks::WhereWhole
        } else if self.world.max_u64(u64::from(!all_kept)) == 0 {
            Blocks::Uniform
        } else {
            Blocks::Off
        };
        self.links.begin_iteration(blocks);
        Ok(())
    }

    fn step(&mut self, step: usize) -> Result<bool, SolveError> {
        if let Some(&k) = self.mine.get(step) {
            if !self.replaying {
                self.distribute(k);
            }
            self.solver.propagate(
                k,
                &mut self.held,
                &mut self.lines,
                &mut self.links,
                &mut self.tally,
            );
        }
        // Every rank ends a run at the same steps (a group dealt fewer directions too).
        if (step + 1) % BLOCK_STEPS == 0 || step + 1 == self.steps() {
            let t = Instant::now();
            let (solver, b) = (self.solver, step / BLOCK_STEPS);
            let (carried, acc) = self.held.carried_and_light();
            let links = &mut self.links;
            if let Some(fuse) = links.agree_on_run(b, self.world, acc.len()) {
                solver
                    .pool
                    .install(|| links.finish_run(b, fuse, carried, solver.channels, acc));
            }
            self.tally.seconds.propagate += t.elapsed().as_secs_f64();
        }
        Ok(true)
    }

    fn settle(&mut self) {
        let solver = self.solver;
        let (carried, acc) = self.held.carried_and_light();
        let links = &mut self.links;
        solver
            .pool
            .install(|| links.settle(carried, solver.channels, acc));
    }

    fn can_save_within(&self, done: usize) -> bool {
        // A resume rebuilds the held surfels of the directions done; after the last step the
        // iteration's boundary is next. Inside a block of links replayed whole, the light holds
        // steps beyond `done`.
        done < self.steps() && self.links.can_save_within(done)
    }

    fn save_within(
        &mut self,
        saver: &mut Saver,
        state: State,
        done: usize,
    ) -> Result<(), CheckpointError> {
        self.solver
            .save_within(self.world, saver, state, done, &self.held, &self.owned)
    }

    fn save_boundary(&mut self, saver: &mut Saver, state: State) -> Result<(), CheckpointError> {
        // Collective: every rank gathers, rank 0 writes (every rank has the same state).
        let owned = &self.owned;
        let radiosity = self
            .solver
            .gather_by_id(owned, &owned.radiosity, self.world);
        let older = state
            .extrapolation
            .chebyshev
            .map(|_| self.solver.gather_by_id(owned, &owned.previous, self.world));
        saver.save_memory(state, &radiosity, older.as_deref())
    }

    fn keeps_older(&self) -> bool {
        self.solver.options.accelerate
    }

    fn end(&mut self, omega: f64) -> Result<[f64; 4], SolveError> {
        // Every run of deferred directions ends within the iteration; nothing is left for later.
        self.settle();
        let t = Instant::now();
        let sums = self.solver.reduce(
            &mut self.held,
            &mut self.owned,
            &mut self.sharing,
            self.world,
            omega,
        );
        self.tally.seconds.reduce += t.elapsed().as_secs_f64();
        Ok(sums)
    }

    fn extrapolate(&mut self, factor: f64) -> Result<(), SolveError> {
        let t = Instant::now();
        let solver = self.solver;
        let owned = &mut self.owned;
        crate::solve::accelerate::extrapolate(
            &mut owned.radiosity,
            &owned.previous,
            &solver.emission[owned.ids.clone()],
            factor,
        );
        solver.share_radiosity(&mut self.held, &self.owned, &mut self.sharing, self.world);
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

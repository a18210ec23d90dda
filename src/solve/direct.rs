//! The direct-light pass: the emitters' own light gathered once, along many directions, from the
//! lines that carry an emitter only.
//!
//! **Why.** Gathering is linear in the radiosity it reads: `H(B) = H(E) + H(B - E)`. The first
//! term is the direct light. From a small bright emitter it is what aliases (a receiver sees a
//! small lamp through one discrete line or none, so the lamp's light falls in stripes), and it
//! does not change from one iteration to the next. So it is gathered once, with a dense direction
//! set, and the iterations gather only the reflected part `B - E` with the normal, coarser set:
//!
//! `B = E + rho * (H_dense(E) / S_dense(n) + H_coarse(B - E) / S_coarse(n))`.
//!
//! Each term is divided by the cosine sum of its own direction set (`normalize`; for the dense
//! term, adjusted as below), so a uniform field is reproduced by each: the furnace stays exactly
//! `E / (1 - rho)`, and the power balance (emitted against absorbed) holds as in a plain solve.
//!
//! **Each emitter sends its power, direction by direction** ([`SenderBalance`]). A receiver's
//! ray is one point sample of where it meets a plane, so along one direction a lamp smaller than
//! a few voxels is hit by a row of receivers more or one fewer than its width calls for; and
//! where its rims sit at the same place against the grid (the twelve lamps of an office), these
//! errors do not average out over directions: the office's lamps, a sixth of a voxel tall at
//! resolution 64, sent 10 % more than their projected area over 20,000 directions, and the room
//! absorbed 10.5 % more than they emitted. So per dense direction, for each emitting plane's
//! side, the power its receivers gathered, `sent = sum A_r |n_r.s| w / S(n_r)` (`w` the share of
//! the ray), is compared with the power its own rays carry, `own = sum A_e |n_e.s| t_e / S(n_e)`
//! (`t_e` the share of the emitter's ray along `s` that meets a surface, 0 where it leaves the
//! scene), and what its receivers gathered from it is scaled by `own / sent` (within
//! [`MAX_SCALE`]). The emitters' lines hold every receiver of an emitter, so this needs nothing
//! beyond the pass's own lines. Where no receiver's ray met an emitter along a direction, its
//! power there goes along the other directions of its [`GROUP`] of consecutive ones (neighbours
//! on the sphere); groups are dealt whole over ranks, so the rank count does not change it.
//!
//! Scaling a sender moves its receivers' gathered weights away from `S(n)`, which a uniform
//! field would notice (a furnace with the pass was 1.3 % off at resolution 8). Each side's
//! direct light is therefore divided by `S(n)` plus what the scales added to its weights: the
//! furnace stays exact, and a receiver that sees a small lamp in a small part of its hemisphere
//! keeps nearly all of the correction.
//!
//! **Cost.** `H_dense(E)` is non-zero only at receivers whose partner on some line emits, and a
//! line carries light from an emitter only if the emitter lies on it. So for each dense direction
//! only the lines through emitting surfels are built, by walking them layer by layer through a
//! table from voxel to surfels, and gathered exactly as `propagate` gathers any line. The pass
//! costs about (emitter lines) x (line length) per direction instead of the whole surfel set;
//! neighbouring lines of one row are walked together, 64 at a time through occupancy bitmaps
//! ([`VoxelTable`]), so the air they cross costs little. On a line only the searches that can
//! end at an emitter's emitting side run, and the emitters' own ([`Context::searches_wanted`],
//! `propagate::Toward`): a line through a lamp crosses a whole building, and a lamp lit on its
//! underside needs no search from the floors above it.
//!
//! **When** ([`DirectPass`]): asked for with a count, or automatically where the emitters are
//! small ([`small_emitters`]: at most 5 % of the surfels emit), capped to what about
//! [`BUDGET_ITERATIONS`] iterations cost ([`affordable_directions`]). Every in-memory solve runs it
//! (one process, and every MPI mode: the dense directions are dealt over all ranks, each of
//! which holds the whole scene), and so does the one-process out-of-core solver, on parts of the
//! scene that hold the emitters' lines (`outcore::direct`, through [`gather_groups`]), which
//! rank 0 of the data mode out of core also runs for every rank (`distribute::ooc::direct`). A
//! stop signal during the pass is answered at the first direction after it.
//!
//! **Determinism.** Directions are taken in blocks; a block's directions run in parallel, each
//! returning its receivers' contributions, which are then added in direction order (while the
//! next block runs): the result does not depend on the thread count, and a resumed solve
//! recomputes it bit for bit.

use super::mix_hash::MixMap;
use super::normalize::cosine;
use super::normalize::cosine_sums;
use super::propagate::{
    find_partners_toward, for_each_link, prefetch, LineScratch, PropSurfel, Toward,
};
use crate::comm::Comm;
use crate::geometry::directions::{Direction, DirectionSet};
use crate::geometry::lines::LineFrame;
use crate::voxel::SurfelSet;
use crate::voxel::{BACK, FRONT};
use rayon::prelude::*;
use std::collections::HashMap;
use std::time::Instant;

/// Light per surfel side and channel, as the solver accumulates it.
type SideLight = [[f64; 3]; 2];

/// What the direct pass did, for the report.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct DirectStats {
    /// Line directions of the dense set.
    pub directions: usize,
    /// Surfels with an emitting side.
    pub emitting_surfels: usize,
    /// Lines gathered, summed over the dense directions (this rank's share).
    pub lines: u64,
    /// Surfels on those lines, summed over the dense directions (this rank's share).
    pub line_surfels: u64,
    /// Wall clock of the pass (cosine sums included).
    pub seconds: f64,
    /// Out of core: the parts the dense directions were taken in (`outcore::direct`); 0 in
    /// memory.
    pub parts: u64,
    /// Out of core: the groups of dense directions whose emitters' lines did not fit one part,
    /// taken in pieces of their lines (`outcore::direct`); 0 in memory.
    pub split_groups: u64,
}

/// The direct light of every surfel side: `H_dense(E) / S_dense(n)`.
#[derive(Clone, Debug)]
pub struct DirectLight {
    pub irradiance: Vec<SideLight>,
    pub stats: DirectStats,
}

impl DirectLight {
    /// The reflected part `B - E` that the iterations gather (f32, as radiosity is stored).
    pub fn reflected(
        &self,
        radiosity: &[[[f32; 3]; 2]],
        emission: &[[[f32; 3]; 2]],
        out: &mut Vec<[[f32; 3]; 2]>,
    ) {
        out.clear();
        out.extend(
            radiosity
                .iter()
                .zip(emission)
                .map(|(b, e)| super::update::reflected_part(b, e)),
        );
    }
}

/// Whether each emitting plane's light is scaled, direction by direction, to the power its own
/// rays carry (see the module header).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SenderBalance {
    /// What every solve does.
    PerDirection,
    /// The plain gather: exactly what a full pass over every line of the dense set gathers
    /// (the tests compare the two to check that the emitters' lines are all the lines needed).
    Off,
}

/// Consecutive directions (neighbours on the sphere) among which a sender's power that no
/// receiver's ray met along one of them (a few percent of a lamp two voxels wide) is sent along
/// the others.
const GROUP: usize = 32;

/// Directions per block (a multiple of [`GROUP`]): enough parallel work per block, a bounded
/// list of contributions. Two blocks' lists are held at once ([`gather_groups`] adds one up
/// while the next runs): 256 directions' as when one block of 128 was held at a time.
const BLOCK: usize = 2 * GROUP;

/// Each sender's scale in each direction of a group: the power its own rays carry over what its
/// receivers gathered from it, times the group's share of its power that no receiver gathered
/// (1 without the balance). `senders` are the group's directions' senders, in order; the scales
/// are indexed like them.
pub(crate) fn group_scales(
    senders: &[&[((u32, usize), Sender)]],
    balance: SenderBalance,
) -> Vec<Vec<f64>> {
    if balance == SenderBalance::Off {
        return senders.iter().map(|d| vec![1.0; d.len()]).collect();
    }
    // By sender: its power over the group, and the part of it along directions where some
    // receiver gathered from it.
    let mut power: HashMap<(u32, usize), (f64, f64)> = HashMap::new();
    for direction in senders {
        for (key, sender) in direction.iter() {
            let sum = power.entry(*key).or_default();
            sum.0 += sender.own;
            if sender.sent > 0.0 {
                sum.1 += sender.own;
            }
        }
    }
    senders
        .iter()
        .map(|direction| {
            direction
                .iter()
                .map(|(key, sender)| {
                    let (all, caught) = power[key];
                    if sender.sent <= 0.0 || sender.own <= 0.0 {
                        return 1.0;
                    }
                    (sender.own / sender.sent * all / caught).clamp(1.0 / MAX_SCALE, MAX_SCALE)
                })
                .collect()
        })
        .collect()
}

/// Adds one contribution (`light` gathered with `weight` from a sender whose scale is `scale`)
/// to a receiver side's running sums: every way of taking the pass adds its terms so.
#[inline]
pub(crate) fn add_scaled(
    sum: &mut [f64; 3],
    shift: &mut f64,
    light: &[f64; 3],
    weight: f64,
    scale: f64,
) {
    for (t, l) in sum.iter_mut().zip(light) {
        *t += l * scale;
    }
    *shift += weight * (scale - 1.0);
}

/// Gathers the direct light of `set` along `directions`, this rank's share of the directions
/// (dealt as `distribute::dealt` deals them), summed over the ranks of `comm`. The work runs on
/// `pool`; every call on `comm` on the calling thread.
pub fn gather_direct(
    set: &SurfelSet,
    surfels: &[PropSurfel],
    emission: &[[[f32; 3]; 2]],
    directions: &DirectionSet,
    balance: SenderBalance,
    comm: &dyn Comm,
    pool: &rayon::ThreadPool,
) -> DirectLight {
    let started = Instant::now();
    let emitters = emitting(emission);
    let cosine_sum = pool.install(|| cosine_sums(&set.normals, directions));
    // Groups of consecutive directions (neighbours on the sphere), dealt over the ranks: a
    // sender's scale is settled over a group, so it does not depend on the rank count.
    let groups = directions.len().div_ceil(GROUP);
    let mine: Vec<usize> = crate::comm::dealt(groups, comm.rank(), comm.size())
        .into_iter()
        .flat_map(|g| g * GROUP..((g + 1) * GROUP).min(directions.len()))
        .collect();
    let mut acc = vec![[[0f64; 3]; 2]; set.surfels.len()];
    // By surfel side: how much the senders' scales moved its gathered weights.
    let mut rescaled = vec![[0f64; 2]; set.surfels.len()];
    let mut stats = DirectStats {
        directions: directions.len(),
        emitting_surfels: emitters.len(),
        ..Default::default()
    };
    let sums = Sums {
        light: &mut acc,
        rescaled: &mut rescaled,
        stats: &mut stats,
    };
    // The pass can take as long as several iterations: a bar of its own.
    let progress = crate::progress::bar(mine.len() as u64, "direct light");
    let on = GatherOn {
        set,
        surfels,
        emission,
        emitters: &emitters,
        cosine_sum: &cosine_sum,
        directions,
        pool,
        bitmap: true,
    };
    gather_groups(&on, &mine, balance, &progress, sums);
    progress.finish_and_clear();
    if comm.size() > 1 {
        let mut flat: Vec<f64> = acc.iter().flatten().flatten().copied().collect();
        flat.extend(rescaled.iter().flatten());
        comm.sum_in_place(&mut flat);
        let (light, shifts) = flat.split_at(acc.len() * 6);
        for (a, v) in acc.iter_mut().flatten().flatten().zip(light) {
            *a = *v;
        }
        for (a, v) in rescaled.iter_mut().flatten().zip(shifts) {
            *a = *v;
        }
    }
    // Each side's gathered weights, rescaled senders included, add up to `S + shift` in a
    // uniform field: dividing by that keeps the furnace exact.
    for ((light, s), shift) in acc.iter_mut().zip(&set.surfels).zip(&rescaled) {
        let norm = cosine_sum[s.normal_id as usize];
        for side in 0..2 {
            light[side]
                .iter_mut()
                .for_each(|v| *v /= norm + shift[side]);
        }
    }
    stats.seconds = started.elapsed().as_secs_f64();
    DirectLight {
        irradiance: acc,
        stats,
    }
}

/// Where [`gather_groups`] adds its light, indexed like the surfels it is given: the light from
/// emitters (before the division by `S + shift`), each side's shift of its gathered weights,
/// and the pass's counts.
pub(crate) struct Sums<'a> {
    pub light: &'a mut [SideLight],
    pub rescaled: &'a mut [[f64; 2]],
    pub stats: &'a mut DirectStats,
}

/// Dense directions per group (a sender's scale is settled over a group): a partial pass adds
/// what the whole pass adds, in the same order, when it takes whole groups, or when it keeps the
/// light of a group's pieces ([`gather_pieces`]) until the group is complete.
pub(crate) const DIRECTIONS_PER_GROUP: usize = GROUP;

/// What the pass gathers on: a scene, or a part of one that holds every surfel on the
/// emitters' lines it is asked for (`outcore::direct`; a line is walked through the surfels
/// present only), with its propagation records, emission and emitting surfels, `S_dense(n)` by
/// normal id, the dense directions and the threads. `bitmap` lets the voxel table keep an
/// occupancy bit per voxel of the grid (up to 32 MiB), which answers the empty voxels a line
/// crosses faster.
pub(crate) struct GatherOn<'a> {
    pub set: &'a SurfelSet,
    pub surfels: &'a [PropSurfel],
    pub emission: &'a [[[f32; 3]; 2]],
    pub emitters: &'a [u32],
    pub cosine_sum: &'a [f64],
    pub directions: &'a DirectionSet,
    pub pool: &'a rayon::ThreadPool,
    pub bitmap: bool,
}

impl GatherOn<'_> {
    fn tables(&self) -> Tables {
        Tables::new(self.set, self.emitters, self.emission.len(), self.bitmap)
    }

    fn context<'b>(&'b self, tables: &'b Tables) -> Context<'b> {
        tables.context(
            self.set,
            self.surfels,
            self.emission,
            self.emitters,
            self.cosine_sum,
        )
    }
}

/// Adds to `sums` the direct light of the dense directions `which` (whole groups, in order)
/// gathered `on` a scene: every receiver's light from its emitting partners, scaled by its
/// sender's balance, in direction order.
pub(crate) fn gather_groups(
    on: &GatherOn,
    which: &[usize],
    balance: SenderBalance,
    progress: &indicatif::ProgressBar,
    mut sums: Sums,
) {
    let tables = on.tables();
    let context = on.context(&tables);
    let (pool, directions) = (on.pool, on.directions);
    // Each block's light is added up, in direction order, while the next block's directions
    // run: the adding is one thread's, and it left the other threads idle (0.25 s of the 5.8 s
    // pass of the Cornell setting on two threads).
    let mut waiting: Option<Vec<DirectionLight>> = None;
    for block in which.chunks(BLOCK) {
        let done = waiting.take();
        let (_, gathered) = pool.install(|| {
            rayon::join(
                || done.map(|done| add_block(&done, balance, &mut sums)),
                || {
                    block
                        .par_iter()
                        .map_init(Buffers::default, |buffers, &k| {
                            context.direction(&directions.directions[k], None, &[], buffers)
                        })
                        .collect::<Vec<_>>()
                },
            )
        });
        progress.inc(block.len() as u64);
        waiting = Some(gathered);
    }
    if let Some(done) = waiting {
        add_block(&done, balance, &mut sums);
    }
}

/// What [`Context`] reads beside the scene: the voxel table, a bit per emitting surfel and the
/// receivers' weights.
struct Tables {
    table: VoxelTable,
    /// Bit `m`: surfel `m` emits on either side. A line through a lamp may hold thousands of
    /// surfels, scattered over the set; the bits stay in the cache.
    emitting: Vec<u64>,
    /// What the senders' balance reads of a receiver, 8 bytes a surfel instead of its 80-byte
    /// record: receivers lie scattered over the set, and this table stays in the caches far
    /// more often.
    receivers: Vec<ReceiverWeight>,
}

impl Tables {
    fn new(set: &SurfelSet, emitters: &[u32], surfel_count: usize, bitmap: bool) -> Self {
        let mut emitting = vec![0u64; surfel_count.div_ceil(64)];
        for &e in emitters {
            emitting[e as usize / 64] |= 1 << (e % 64);
        }
        Tables {
            table: VoxelTable::new(set, bitmap),
            emitting,
            receivers: set
                .surfels
                .iter()
                .map(|s| ReceiverWeight {
                    area: s.area,
                    normal_id: s.normal_id,
                })
                .collect(),
        }
    }

    fn context<'a>(
        &'a self,
        set: &'a SurfelSet,
        surfels: &'a [PropSurfel],
        emission: &'a [[[f32; 3]; 2]],
        emitters: &'a [u32],
        cosine_sum: &'a [f64],
    ) -> Context<'a> {
        Context {
            dims: set.grid.dims,
            receivers: &self.receivers,
            surfels,
            emission,
            emitters,
            emitting: &self.emitting,
            table: &self.table,
            set,
            cosine_sum,
        }
    }
}

/// A piece of a dense direction, for a part of a scene that cannot hold all of the direction's
/// emitters' lines (`outcore::direct`): its lines numbered `lines` (in its [`LineFrame`]), every
/// surfel on them in the part, and the senders' sums over the direction's lines before them.
pub(crate) struct Piece<'a> {
    pub direction: usize,
    pub lines: std::ops::Range<u64>,
    pub carried: &'a [((u32, usize), Sender)],
}

/// The light of each of `pieces` (in order) gathered `on` a part of a scene, as
/// [`gather_groups`] finds it. A piece's senders are its direction's sums up to its last line:
/// the pieces of a direction, taken in order, each carrying the sums of the one before, add the
/// same terms in the same order as the whole direction.
pub(crate) fn gather_pieces(on: &GatherOn, pieces: &[Piece]) -> Vec<DirectionLight> {
    let tables = on.tables();
    let context = on.context(&tables);
    let directions = on.directions;
    on.pool.install(|| {
        pieces
            .par_iter()
            .map_init(Buffers::default, |buffers, piece| {
                context.direction(
                    &directions.directions[piece.direction],
                    Some(piece.lines.clone()),
                    piece.carried,
                    buffers,
                )
            })
            .collect()
    })
}

/// Adds the light of one block's directions (in order) to `sums`, each sender's scaled as its
/// group's balance says. A block starts a group and holds whole groups (but for the last one).
fn add_block(gathered: &[DirectionLight], balance: SenderBalance, sums: &mut Sums) {
    for group in gathered.chunks(GROUP) {
        let senders: Vec<&[((u32, usize), Sender)]> =
            group.iter().map(|d| d.senders.as_slice()).collect();
        let scales = group_scales(&senders, balance);
        for (direction, scales) in group.iter().zip(&scales) {
            sums.stats.lines += direction.lines;
            sums.stats.line_surfels += direction.line_surfels;
            for &(member, side, sender, light, weight) in &direction.contributions {
                let (member, side) = (member as usize, side as usize);
                add_scaled(
                    &mut sums.light[member][side],
                    &mut sums.rescaled[member][side],
                    &light,
                    weight,
                    scales[sender as usize],
                );
            }
        }
    }
}

/// Calls `f` on every voxel of line `line` of `frame` inside a grid of `dims`, in order along
/// `vector`.
pub(crate) fn for_each_voxel_on_line(
    frame: &LineFrame,
    dims: [u32; 3],
    vector: [i64; 3],
    line: u64,
    mut f: impl FnMut([i32; 3]),
) {
    let (i, j) = (line / frame.nj, line % frame.nj);
    let layers = dims[frame.main] as usize;
    let forward = vector[frame.main] > 0;
    for step in 0..layers {
        let layer = if forward { step } else { layers - 1 - step };
        let (su, sv) = frame.layer_shift(layer);
        // Outside the grid on this layer (an oblique line enters it late or leaves early).
        if i < su || j < sv {
            continue;
        }
        let (u, v) = (i - su, j - sv);
        if u >= dims[frame.u] as u64 || v >= dims[frame.v] as u64 {
            continue;
        }
        let mut voxel = [0i32; 3];
        voxel[frame.main] = layer as i32;
        voxel[frame.u] = u as i32;
        voxel[frame.v] = v as i32;
        f(voxel);
    }
}

/// Whether a surfel whose sides emit `e` is an emitter of the pass (a side's `E` is positive).
pub(crate) fn emits(e: &[[f32; 3]; 2]) -> bool {
    e.iter().flatten().any(|&v| v > 0.0)
}

/// The emitting surfels among those of `emission`.
pub(crate) fn emitting(emission: &[[[f32; 3]; 2]]) -> Vec<u32> {
    emission
        .iter()
        .enumerate()
        .filter(|(_, e)| emits(e))
        .map(|(i, _)| i as u32)
        .collect()
}

/// What one direction's emitter lines gave.
#[derive(Default)]
pub(crate) struct DirectionLight {
    pub lines: u64,
    pub line_surfels: u64,
    /// The emitting plane sides met, by (plane group, side), in that order.
    pub senders: Vec<((u32, usize), Sender)>,
    /// Light from emitters: (receiver, its side, index in `senders`, light before the sender's
    /// scale, the weight it was gathered with).
    pub contributions: Vec<(u32, u8, u32, [f64; 3], f64)>,
}

/// Lines of a direction up to which [`emitter_lines`] lists them through a bit per line (4 MiB a
/// thread at most, which the memory budgets leave out); beyond, it sorts their numbers.
const MAX_LINE_BITS: u64 = 1 << 25;

/// The lines of `frame` through `voxels`, each once, in ascending order, into `lines`. `bits` is
/// scratch, a bit per line, all clear before and after, used where the frame has at most
/// `max_bits` lines. Setting the lines' bits and reading back the few hundred words between the
/// first and the last replaced sorting the emitters' line numbers, which was most of the 6 % of
/// a direct pass that finding its lines took (the Cornell box at resolution 256, 2,880 emitting
/// surfels): the pass ran about 5 % faster.
fn emitter_lines(
    frame: &LineFrame,
    voxels: impl Iterator<Item = [i32; 3]>,
    max_bits: u64,
    bits: &mut Vec<u64>,
    lines: &mut Vec<u64>,
) {
    if frame.line_count > max_bits {
        lines.clear();
        lines.extend(voxels.map(|voxel| frame.line_index(voxel)));
        lines.sort_unstable();
        lines.dedup();
        return;
    }
    let words = frame.line_count.div_ceil(64) as usize;
    if bits.len() < words {
        bits.resize(words, 0);
    }
    let (mut first, mut last) = (usize::MAX, 0);
    for voxel in voxels {
        let line = frame.line_index(voxel);
        let word = (line / 64) as usize;
        bits[word] |= 1 << (line % 64);
        first = first.min(word);
        last = last.max(word);
    }
    lines.clear();
    for (w, word) in bits.iter_mut().enumerate().take(last + 1).skip(first) {
        let mut set = std::mem::take(word);
        while set != 0 {
            lines.push(w as u64 * 64 + set.trailing_zeros() as u64);
            set &= set - 1;
        }
    }
}

/// A task's reusable buffers, one line at a time.
#[derive(Default)]
struct Buffers {
    /// This direction's lines through emitters, and the scratch bits that list them
    /// ([`emitter_lines`]).
    line_ids: Vec<u64>,
    line_bits: Vec<u64>,
    /// The surfels of the line being searched, in order along the direction.
    members: Vec<u32>,
    /// The surfels of each line of a bundle ([`VoxelTable::walk_bundle`]).
    bundle: Vec<Vec<u32>>,
    scratch: LineScratch,
    /// The emitters' own searches a line needs besides its spans ([`Context::searches_wanted`]).
    also_ahead: Vec<u32>,
    also_behind: Vec<u32>,
    /// By line position: whether the surfel emits ([`Toward::targets`]).
    targets: Vec<bool>,
    /// This direction's emitting plane sides, and where each is in `senders`.
    senders: Vec<Sender>,
    /// By [`sender_key`]: the solver's hash, not SipHash, which took a twentieth of a direct
    /// pass (a look-up per link from an emitter).
    sender_at: MixMap<usize>,
    /// By line position: the share of its ray ahead and behind that meets a surface.
    totals: Vec<[f64; 2]>,
    /// This direction's light from emitters: (receiver, its side, sender, light before the
    /// sender's scale, the weight it was gathered with).
    contributions: Vec<(u32, u8, u32, [f64; 3], f64)>,
}

/// A sender's key in [`Buffers::sender_at`]: its plane group and side in one `u64`.
pub(crate) fn sender_key(group: u32, side: usize) -> u64 {
    (group as u64) << 1 | side as u64
}

/// The plane group and side of a [`sender_key`].
pub(crate) fn sender_of_key(key: u64) -> (u32, usize) {
    ((key >> 1) as u32, (key & 1) as usize)
}

/// One side of an emitting plane in one direction: the power its receivers gathered from it and
/// the power its own rays carry (both in `A W |n.s| / S(n)`, without the emission).
#[derive(Clone, Copy, Default)]
pub(crate) struct Sender {
    sent: f64,
    own: f64,
}

/// The most a sender's light is scaled up or down in one direction.
const MAX_SCALE: f64 = 4.0;

/// A receiver's area and normal, as the senders' balance weighs what it gathered.
#[derive(Clone, Copy)]
struct ReceiverWeight {
    area: f32,
    normal_id: u32,
}

/// Everything the per-direction work reads.
struct Context<'a> {
    dims: [u32; 3],
    /// By surfel: [`ReceiverWeight`].
    receivers: &'a [ReceiverWeight],
    set: &'a SurfelSet,
    /// `S_dense(n)` by normal id.
    cosine_sum: &'a [f64],
    surfels: &'a [PropSurfel],
    emission: &'a [[[f32; 3]; 2]],
    emitters: &'a [u32],
    /// Bit `m`: surfel `m` emits on either side.
    emitting: &'a [u64],
    table: &'a VoxelTable,
}

impl Context<'_> {
    /// Whether surfel `m` emits on either side.
    #[inline]
    fn emits(&self, m: u32) -> bool {
        self.emitting[m as usize / 64] >> (m % 64) & 1 == 1
    }

    /// The light of direction `d` over its emitters' lines, or over those numbered `lines` only
    /// with the senders' sums so far `carried` (a [`Piece`]).
    fn direction(
        &self,
        d: &Direction,
        lines: Option<std::ops::Range<u64>>,
        carried: &[((u32, usize), Sender)],
        b: &mut Buffers,
    ) -> DirectionLight {
        let frame = LineFrame::new(d.vector, self.dims);
        emitter_lines(
            &frame,
            self.emitters
                .iter()
                .map(|&e| self.surfels[e as usize].voxel),
            MAX_LINE_BITS,
            &mut b.line_bits,
            &mut b.line_ids,
        );
        if let Some(lines) = lines {
            b.line_ids.retain(|line| lines.contains(line));
        }
        let mut out = DirectionLight::default();
        let weight = d.solid_angle / std::f64::consts::PI;
        b.senders.clear();
        b.sender_at.clear();
        b.contributions.clear();
        for &(key, sender) in carried {
            b.sender_at
                .insert(sender_key(key.0, key.1), b.senders.len());
            b.senders.push(sender);
        }
        let mut at = 0;
        while at < b.line_ids.len() {
            let bundle = self.table.bundle_len(&frame, &b.line_ids[at..]);
            self.table.walk_bundle(
                &frame,
                d.vector,
                &b.line_ids[at..at + bundle],
                &mut b.bundle,
            );
            at += bundle;
            for k in 0..bundle {
                // The next line's surfels lie scattered over the whole set (most lines hold a
                // lamp's surfel and one or two far away): asked for while this line is searched,
                // their cache misses overlap its work. The Cornell setting's pass took 3 to 17 %
                // less time, depending on how busy the host was (docs/throughput.md).
                if let Some(next) = b.bundle[..bundle].get(k + 1) {
                    for &m in next {
                        prefetch(self.surfels.as_ptr(), m as usize);
                        prefetch(self.receivers.as_ptr(), m as usize);
                    }
                }
                std::mem::swap(&mut b.members, &mut b.bundle[k]);
                out.lines += 1;
                out.line_surfels += b.members.len() as u64;
                if b.members.len() < 2 {
                    continue;
                }
                let Some((ahead_upto, behind_from)) = self.searches_wanted(d, b) else {
                    continue;
                };
                let toward = Toward {
                    ahead_upto,
                    behind_from,
                    also_ahead: &b.also_ahead,
                    also_behind: &b.also_behind,
                    targets: &b.targets,
                };
                // The line's own surfel indices: the search copies what it reads of each
                // into its buffer, and its links are by line position.
                find_partners_toward(
                    &b.members,
                    self.surfels,
                    d.unit,
                    &mut b.scratch,
                    Some(toward),
                );
                self.balance_line(d, weight, b);
            }
        }
        out.senders = b
            .sender_at
            .iter()
            .map(|(&key, &i)| (sender_of_key(key), b.senders[i]))
            .collect();
        // In a fixed order: the hash map's is not.
        out.senders.sort_by_key(|s| s.0);
        let order: HashMap<(u32, usize), u32> = out
            .senders
            .iter()
            .enumerate()
            .map(|(i, s)| (s.0, i as u32))
            .collect();
        let renumber: Vec<u32> = {
            let mut r = vec![0; b.senders.len()];
            for (&key, &i) in &b.sender_at {
                r[i] = order[&sender_of_key(key)];
            }
            r
        };
        out.contributions = b
            .contributions
            .iter()
            .map(|&(m, side, sender, light, w)| (m, side, renumber[sender as usize], light, w))
            .collect();
        out
    }

    /// The searches of the line in `b.members` whose links the pass uses, as the bounds of a
    /// [`Toward`] with its further positions left in `b.also_ahead` and `b.also_behind`; `None`
    /// if no surfel of the line emits. Only links from an emitting side carry light, and a side
    /// is found by the searches that come toward it: the side of an emitter facing back along the
    /// direction by the searches ahead from the positions before it (up to its voxel), the side
    /// facing along it by the searches behind from the positions after it. Besides those, an
    /// emitter's own search toward each side that emits tells the power that side sends (the
    /// senders' balance, [`Context::balance_line`]). A lamp that emits from its underside only
    /// thus needs no search from the floors above it: a line through a lamp of a building
    /// crosses the whole building, and these searches were about half of the pass there. The
    /// emitters are the line's targets too: of those searches, only the ones whose ray crosses
    /// an emitter's plane run (`Toward::targets`).
    fn searches_wanted(
        &self,
        d: &Direction,
        b: &mut Buffers,
    ) -> Option<(Option<usize>, Option<usize>)> {
        let unit = d.unit.as_vec3();
        let (mut ahead_upto, mut behind_from) = (None, None);
        b.also_ahead.clear();
        b.also_behind.clear();
        b.targets.clear();
        b.targets.extend(b.members.iter().map(|&m| self.emits(m)));
        let mut any = false;
        for (k, &m) in b.members.iter().enumerate() {
            if !self.emits(m) {
                continue;
            }
            any = true;
            // `n.s` in f32, as propagation decides which side faces along the direction.
            let ns = glam::Vec3::from(self.set.surfels[m as usize].normal).dot(unit);
            let side = |forward: bool| if (ns > 0.0) == forward { FRONT } else { BACK };
            let sends = |side: usize| self.emission[m as usize][side].iter().any(|&v| v > 0.0);
            if sends(side(false)) {
                // Seen by the searches ahead from before it; its own search behind.
                ahead_upto = Some(k);
                b.also_behind.push(k as u32);
            }
            if sends(side(true)) {
                behind_from.get_or_insert(k);
                b.also_ahead.push(k as u32);
            }
        }
        any.then_some((ahead_upto, behind_from))
    }

    /// One line's partners (in `b.scratch`): every receiver's light from an emitting partner,
    /// recorded by sender plane and side with the power it carries, and the power the line's
    /// emitting pieces send along their own rays.
    fn balance_line(&self, d: &Direction, weight: f64, b: &mut Buffers) {
        let Buffers {
            members,
            scratch,
            senders,
            sender_at,
            contributions,
            totals,
            ..
        } = b;
        let mut sender_index = |senders: &mut Vec<Sender>, group: u32, side: usize| {
            *sender_at.entry(sender_key(group, side)).or_insert_with(|| {
                senders.push(Sender::default());
                senders.len() - 1
            })
        };
        let surfel = |k: usize| &self.set.surfels[members[k] as usize];
        // The chain total of each position's search ahead (0) and behind (1).
        totals.clear();
        totals.resize(members.len(), [0.0; 2]);
        for_each_link(scratch, d.unit, |link| {
            totals[link.receiver][link.which as usize] += link.share as f64;
            // Most partners do not emit: their bit, in the cache, saves reading their emission
            // from a table far larger than the caches.
            if link.cosine == 0.0 || !self.emits(members[link.partner]) {
                return;
            }
            let e = self.emission[members[link.partner] as usize][link.from_side];
            if e.iter().all(|&v| v <= 0.0) {
                return;
            }
            let r = self.receivers[members[link.receiver] as usize];
            let f = link.cosine * weight * link.share as f64;
            let sender = sender_index(senders, surfel(link.partner).group, link.from_side);
            senders[sender].sent += r.area as f64 * f / self.cosine_sum[r.normal_id as usize];
            contributions.push((
                members[link.receiver],
                link.to_side as u8,
                sender as u32,
                e.map(|v| v as f64 * f),
                f,
            ));
        });
        // `n.s` in f32, as propagation decides which side faces along the direction.
        let unit = d.unit.as_vec3();
        let side_facing = |k: usize, sign: f32| {
            if glam::Vec3::from(surfel(k).normal).dot(unit) * sign > 0.0 {
                FRONT
            } else {
                BACK
            }
        };
        for (k, total) in totals.iter().enumerate() {
            if !self.emits(members[k]) {
                continue;
            }
            let c = surfel(k);
            for (which, side) in [(0, side_facing(k, 1.0)), (1, side_facing(k, -1.0))] {
                if self.emission[members[k] as usize][side]
                    .iter()
                    .all(|&v| v <= 0.0)
                {
                    continue;
                }
                let sender = sender_index(senders, c.group, side);
                senders[sender].own +=
                    c.area as f64 * cosine(c.normal, d.unit) * weight * total[which]
                        / self.cosine_sum[c.normal_id as usize];
            }
        }
    }
}

/// Grids up to this many voxels get occupancy bitmaps ([`bitmap_bytes`]: 96 MiB at most).
pub(crate) const MAX_BITMAP_VOXELS: u64 = 1 << 28;

/// Bytes of [`VoxelTable`]'s occupancy bitmaps for a grid of `voxels`: one bit per voxel, in
/// each of three layouts, and a 4-byte count of the bits set before each 64-bit word.
pub(crate) fn bitmap_bytes(voxels: u64) -> u64 {
    3 * voxels.div_ceil(64) * (8 + 4)
}

/// From a voxel to the range of its surfels (which are adjacent in a surfel set). Most voxels a
/// line crosses are empty (the air of a room): occupancy bitmaps answer those without a hash
/// look-up, where the grid is small enough for them. There is one bitmap per main axis `m` of
/// the lines, voxel `(layer, u, v)` of that axis's frame at bit `(layer * dims[u] + u) *
/// dims[v] + v`: the lines of one row `i` of the frame that cross a layer are then consecutive
/// bits, so a bundle of an emitter's neighbouring lines is tested 64 at a time
/// ([`VoxelTable::walk_bundle`]). Walking each line voxel by voxel took two thirds of a direct
/// pass at resolution 256.
///
/// With the bitmaps, an occupied voxel's surfels are found by its rank among the set bits of its
/// layout (the bits set before its word, counted once, plus those before it in the word) in a
/// table of ranges in bit order: no hash look-up, whose cache misses took about a tenth of a
/// direct pass at resolution 256, and the ranges of one row lie together.
pub(crate) struct VoxelTable {
    /// The ranges by voxel, without the bitmaps.
    map: MixMap<(u32, u32)>,
    dims: [u64; 3],
    by_axis: Option<[Ranked; 3]>,
}

/// One layout's occupancy bitmap and its voxels' surfel ranges by rank.
struct Ranked {
    bits: Vec<u64>,
    /// Bits set in the words before each word.
    before: Vec<u32>,
    /// The surfel range of each set bit, in bit order.
    ranges: Vec<(u32, u32)>,
}

impl Ranked {
    /// The range of the voxel at set bit `at`.
    #[inline(always)]
    fn range(&self, at: u64) -> (u32, u32) {
        let word = (at / 64) as usize;
        let below = self.bits[word] & ((1u64 << (at % 64)) - 1);
        self.ranges[self.before[word] as usize + below.count_ones() as usize]
    }

    #[inline(always)]
    fn is_set(&self, at: u64) -> bool {
        self.bits[(at / 64) as usize] & (1 << (at % 64)) != 0
    }
}

/// Lines of one row walked together by [`VoxelTable::walk_bundle`] (a word of the bitmaps).
const BUNDLE: u64 = 64;

impl VoxelTable {
    fn new(set: &SurfelSet, bitmap: bool) -> Self {
        let mut map: MixMap<(u32, u32)> = MixMap::default();
        let dims = set.grid.dims.map(u64::from);
        let voxels = dims[0] * dims[1] * dims[2];
        let bitmap = bitmap && voxels <= MAX_BITMAP_VOXELS;
        // Each occupied voxel's surfel range, with its bit in each layout where there are
        // bitmaps.
        let mut occupied: Vec<([u64; 3], (u32, u32))> = Vec::new();
        let s = &set.surfels;
        let mut first = 0;
        while first < s.len() {
            let mut end = first + 1;
            while end < s.len() && s[end].voxel == s[first].voxel {
                end += 1;
            }
            let range = (first as u32, end as u32);
            if bitmap {
                let at = [0, 1, 2].map(|main| Self::bit(dims, main, s[first].voxel));
                occupied.push((at, range));
            } else {
                map.insert(Self::key(s[first].voxel), range);
            }
            first = end;
        }
        let by_axis = bitmap.then(|| {
            [0, 1, 2].map(|main| {
                let mut bits = vec![0u64; voxels.div_ceil(64) as usize];
                for (at, _) in &occupied {
                    bits[(at[main] / 64) as usize] |= 1 << (at[main] % 64);
                }
                let mut before = Vec::with_capacity(bits.len());
                let mut count = 0u32;
                for word in &bits {
                    before.push(count);
                    count += word.count_ones();
                }
                occupied.sort_unstable_by_key(|(at, _)| at[main]);
                let ranges = occupied.iter().map(|&(_, range)| range).collect();
                Ranked {
                    bits,
                    before,
                    ranges,
                }
            })
        });
        VoxelTable { map, dims, by_axis }
    }

    /// The bit of `voxel` in the bitmap of main axis `main`.
    #[inline(always)]
    fn bit(dims: [u64; 3], main: usize, voxel: [i32; 3]) -> u64 {
        let (u, v) = ((main + 1) % 3, (main + 2) % 3);
        (voxel[main] as u64 * dims[u] + voxel[u] as u64) * dims[v] + voxel[v] as u64
    }

    /// The surfels of `voxel` (inside the grid), if any.
    #[inline]
    fn surfels_of(&self, voxel: [i32; 3]) -> Option<(u32, u32)> {
        if let Some(maps) = &self.by_axis {
            let at = Self::bit(self.dims, 0, voxel);
            return maps[0].is_set(at).then(|| maps[0].range(at));
        }
        self.map.get(&Self::key(voxel)).copied()
    }

    /// How many of `lines` (sorted line indices of `frame`) from the first on form one bundle:
    /// lines of one row `i` within [`BUNDLE`] columns of the first (1 without the bitmaps).
    fn bundle_len(&self, frame: &LineFrame, lines: &[u64]) -> usize {
        if self.by_axis.is_none() {
            return 1;
        }
        let (i, j0) = (lines[0] / frame.nj, lines[0] % frame.nj);
        lines
            .iter()
            .take_while(|&&l| l / frame.nj == i && l % frame.nj - j0 < BUNDLE)
            .count()
    }

    /// Fills `members[k]` with the surfels of line `lines[k]` of `frame`, in order along
    /// `vector` (the order `dispatch` gives: voxel by voxel along the line, by surfel index
    /// within a voxel): what [`for_each_voxel_on_line`] and [`Self::surfels_of`] find line by
    /// line. The
    /// lines are one bundle ([`Self::bundle_len`]): at each layer the bits of all of them are
    /// read at once, and only occupied voxels are looked up.
    fn walk_bundle(
        &self,
        frame: &LineFrame,
        vector: [i64; 3],
        lines: &[u64],
        members: &mut Vec<Vec<u32>>,
    ) {
        if members.len() < lines.len() {
            members.resize_with(lines.len(), Vec::new);
        }
        members.iter_mut().for_each(Vec::clear);
        let Some(maps) = &self.by_axis else {
            for_each_voxel_on_line(frame, self.dims.map(|d| d as u32), vector, lines[0], |v| {
                if let Some((first, end)) = self.surfels_of(v) {
                    members[0].extend(first..end);
                }
            });
            return;
        };
        let layout = &maps[frame.main];
        let bits = &layout.bits;
        let (i, j0) = (lines[0] / frame.nj, lines[0] % frame.nj);
        // Bit `k` of the bundle: line column `j0 + k`, and where it sits in `lines`.
        let mut wanted = 0u64;
        let mut slot = [0u8; BUNDLE as usize];
        for (n, &l) in lines.iter().enumerate() {
            let k = l % frame.nj - j0;
            wanted |= 1 << k;
            slot[k as usize] = n as u8;
        }
        let (du, dv) = (self.dims[frame.u], self.dims[frame.v]);
        let layers = self.dims[frame.main] as usize;
        let forward = vector[frame.main] > 0;
        for step in 0..layers {
            let layer = if forward { step } else { layers - 1 - step };
            let (su, sv) = frame.layer_shift(layer);
            if i < su || i - su >= du {
                continue;
            }
            let u = i - su;
            // Columns j0 + k with 0 <= j0 + k - sv < dv: bits k in [lo, hi).
            let lo = sv.saturating_sub(j0);
            let hi = (dv + sv).saturating_sub(j0).min(BUNDLE);
            if lo >= hi {
                continue;
            }
            let row = (layer as u64 * du + u) * dv;
            // Bits lo..hi of the bundle are voxels v = j0 + lo - sv .. of this row.
            let first = row + j0 + lo - sv;
            let mut word = read_bits(bits, first, hi - lo) << lo;
            word &= wanted;
            while word != 0 {
                let k = word.trailing_zeros() as u64;
                word &= word - 1;
                // Bit k of the bundle is voxel j0 + k - sv of this row.
                let (start, end) = layout.range(row + j0 + k - sv);
                members[slot[k as usize] as usize].extend(start..end);
            }
        }
    }

    /// Voxel coordinates are below `voxelize::MAX_GRID_EDGE` (2^20), so three fit one key.
    pub(crate) fn key(voxel: [i32; 3]) -> u64 {
        const _: () = assert!(crate::voxel::voxelize::MAX_GRID_EDGE <= 1 << 21);
        voxel[0] as u64 | (voxel[1] as u64) << 21 | (voxel[2] as u64) << 42
    }
}

/// Bits `first..first + count` of `bits` (`count` at most 64) as the low bits of a word.
#[inline(always)]
fn read_bits(bits: &[u64], first: u64, count: u64) -> u64 {
    let (word, shift) = ((first / 64) as usize, first % 64);
    let mut value = bits[word] >> shift;
    if shift > 0 && shift + count > 64 {
        value |= bits[word + 1] << (64 - shift);
    }
    if count < 64 {
        value &= (1 << count) - 1;
    }
    value
}

/// Whether and how a solve runs the direct pass.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DirectPass {
    /// Never (every direction of the solve gathers `B` whole).
    #[default]
    Off,
    /// When the scene's emitters are small ([`small_emitters`]), with about this many dense
    /// line directions, fewer if that would cost more than about [`BUDGET_ITERATIONS`]
    /// iterations ([`affordable_directions`]), none if fewer than twice the solve's own.
    Auto(usize),
    /// Always, with about this many dense line directions.
    On(usize),
}

/// Emitting surfels at most this fraction of all surfels count as small emitters.
pub const SMALL_EMITTER_FRACTION: f64 = 0.05;

/// Whether `emitting` emitting surfels among `surfels` are small emitters: few enough that the
/// pass is cheap (its lines are the emitters'), and small against the scene, where their direct
/// light aliases.
pub fn small_emitters(emitting: usize, surfels: usize) -> bool {
    emitting > 0 && emitting as f64 <= SMALL_EMITTER_FRACTION * surfels as f64
}

/// The most an automatic pass may cost, in iterations of the solve (a solve to 1e-4 runs 10
/// to 20 on the study scenes).
pub const BUDGET_ITERATIONS: f64 = 10.0;

/// Cost of the pass per emitting surfel and layer of a dense direction, against one
/// surfel-direction update of an iteration. Measured on the Cornell box (resolution 32, 20,173
/// dense directions against 193): 0.73 lines per emitting surfel and direction (lines through
/// several emitters are walked once), 7 ns per voxel step against 46 ns per update, so about
/// 1/9; rounded up.
const WALK_STEP_PER_UPDATE: f64 = 1.0 / 8.0;

/// The most dense directions an automatic pass affords: per dense direction it walks about one
/// line per emitting surfel through `longest_axis` layers, and it may cost about
/// [`BUDGET_ITERATIONS`] iterations of `directions` over `surfels`.
pub fn affordable_directions(
    emitting: usize,
    surfels: usize,
    longest_axis: u32,
    directions: usize,
) -> usize {
    let per_direction = (emitting as f64 * longest_axis as f64 * WALK_STEP_PER_UPDATE).max(1.0);
    (BUDGET_ITERATIONS * directions as f64 * surfels as f64 / per_direction) as usize
}

/// What a scene offers the decision: emitting surfels, all surfels, the grid's longest axis
/// (voxels), and the solve's own line directions.
#[derive(Clone, Copy, Debug)]
pub struct Shape {
    pub emitting: usize,
    pub surfels: usize,
    pub longest_axis: u32,
    pub directions: usize,
}

impl Shape {
    pub fn of(set: &SurfelSet, directions: usize) -> Self {
        Shape {
            emitting: super::effects::analyse(set).emitting_surfels,
            surfels: set.surfels.len(),
            longest_axis: set.grid.dims.into_iter().max().unwrap_or(0),
            directions,
        }
    }
}

impl DirectPass {
    /// The dense direction count a solve of a scene of shape `shape` uses, or `None` for no
    /// direct pass.
    pub fn resolve(self, shape: Shape) -> Option<usize> {
        match self {
            DirectPass::Off | DirectPass::Auto(0) | DirectPass::On(0) => None,
            DirectPass::Auto(n) => {
                let affordable = affordable_directions(
                    shape.emitting,
                    shape.surfels,
                    shape.longest_axis,
                    shape.directions,
                );
                let n = n.min(affordable);
                (small_emitters(shape.emitting, shape.surfels) && n >= 2 * shape.directions)
                    .then_some(n)
            }
            DirectPass::On(n) => Some(n),
        }
    }

    /// Whether a solve with `directions` line directions may run the pass on a scene that emits,
    /// before its emitting surfels are counted: what [`Self::resolve`] decides without them.
    pub fn may_run(self, directions: usize) -> bool {
        match self {
            DirectPass::Off | DirectPass::Auto(0) | DirectPass::On(0) => false,
            DirectPass::Auto(n) => n >= 2 * directions,
            DirectPass::On(_) => true,
        }
    }

    /// The dense direction set of a solve of `set` with `directions` line directions, or `None`.
    pub fn directions_for(self, set: &SurfelSet, directions: usize) -> Option<DirectionSet> {
        self.resolve(Shape::of(set, directions))
            .map(DirectionSet::with_count)
    }
}

/// Where the report sends a reader for what the pass gains: the measurements live in the docs,
/// dated and with their commands, not in the binary.
pub const MEASURED_GAIN: &str = "docs/simulation.md (the direct-light pass) and docs/study.md \
     (quality presets) give its measured gain in error and its cost";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn read_bits_takes_any_run_of_up_to_64_bits() {
        let bits = [0xF0F0_F0F0_F0F0_F0F0u64, 0x0123_4567_89AB_CDEF, u64::MAX];
        let bit = |at: u64| (bits[(at / 64) as usize] >> (at % 64)) & 1;
        for first in 0..130u64 {
            for count in 1..=64u64.min(192 - first) {
                let want = (0..count).fold(0u64, |w, k| w | bit(first + k) << k);
                assert_eq!(read_bits(&bits, first, count), want, "{first} {count}");
            }
        }
    }

    #[test]
    fn emitter_lines_are_the_sorted_distinct_lines_of_their_voxels() {
        let dims = [13, 7, 9];
        let voxels: Vec<[i32; 3]> = (0..200)
            .map(|k: i32| [k * 7 % 13, k * 3 % 7, k * 5 % 9])
            .collect();
        let mut bits = Vec::new();
        let mut lines = Vec::new();
        for d in &DirectionSet::with_count(30).directions {
            let frame = LineFrame::new(d.vector, dims);
            // Sorted (no bits allowed) and through the bits.
            for (max_bits, count) in [0, MAX_LINE_BITS]
                .into_iter()
                .flat_map(|m| [0, 1, 37, 200].map(|c| (m, c)))
            {
                emitter_lines(
                    &frame,
                    voxels[..count].iter().copied(),
                    max_bits,
                    &mut bits,
                    &mut lines,
                );
                let mut want: Vec<u64> = voxels[..count]
                    .iter()
                    .map(|&v| frame.line_index(v))
                    .collect();
                want.sort_unstable();
                want.dedup();
                assert_eq!(
                    lines, want,
                    "direction {:?}, {count} voxels, max_bits {max_bits}",
                    d.vector
                );
                assert!(
                    bits.iter().all(|&w| w == 0),
                    "the scratch bits are left clear"
                );
            }
        }
    }

    #[test]
    fn bundles_find_every_line_s_surfels_in_order() {
        // Every line of a few directions through the Cornell box, walked in bundles with the
        // bitmaps, against the same lines walked voxel by voxel through the hash map.
        let set = crate::voxel::voxelize::voxelize(
            &crate::gen::cornell_box(),
            crate::voxel::voxelize::GridSpec::Resolution(24),
        )
        .unwrap();
        let with = VoxelTable::new(&set, true);
        let without = VoxelTable::new(&set, false);
        assert!(with.by_axis.is_some() && without.by_axis.is_none());
        let mut bundle = Vec::new();
        for d in &DirectionSet::with_count(40).directions {
            let frame = LineFrame::new(d.vector, set.grid.dims);
            let lines: Vec<u64> = (0..frame.line_count).collect();
            let mut at = 0;
            while at < lines.len() {
                let n = with.bundle_len(&frame, &lines[at..]);
                with.walk_bundle(&frame, d.vector, &lines[at..at + n], &mut bundle);
                for (k, &line) in lines[at..at + n].iter().enumerate() {
                    let mut want = Vec::new();
                    for_each_voxel_on_line(&frame, set.grid.dims, d.vector, line, |v| {
                        if let Some((first, end)) = without.surfels_of(v) {
                            want.extend(first..end);
                        }
                    });
                    assert_eq!(bundle[k], want, "direction {:?} line {line}", d.vector);
                }
                at += n;
            }
        }
    }

    #[test]
    fn emitter_lines_gather_what_a_full_pass_gathers() {
        // Unbalanced, the pass must gather from the emitters' lines exactly what one iteration
        // over every line of the dense set gathers: `B = E + rho H_dense(E) / S_dense`. The
        // lamps of both scenes emit from one side only, so the pass skips the searches toward
        // their dark sides (`Context::searches_wanted`); the office's hang under housings, by
        // partitions and desks, with open edges.
        assert_pass_gathers_one_iteration(&crate::gen::cornell_box(), 16, 301);
        assert_pass_gathers_one_iteration(&crate::gen::office().scene, 24, 109);
    }

    fn assert_pass_gathers_one_iteration(
        scene: &crate::scene::Scene,
        resolution: u32,
        dense: usize,
    ) {
        let set = crate::voxel::voxelize::voxelize(
            scene,
            crate::voxel::voxelize::GridSpec::Resolution(resolution),
        )
        .unwrap();
        let dense = DirectionSet::with_count(dense);
        let full = crate::solve::solve(
            &set,
            &crate::solve::SolveOptions {
                directions: dense.len(),
                max_iterations: 1,
                tolerance: None,
                threads: 2,
                ..Default::default()
            },
        )
        .unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let surfels = crate::solve::propagate::prop_surfels(&set);
        let (emission, reflectance) = crate::solve::jacobi::material_tables(&set);
        let direct = gather_direct(
            &set,
            &surfels,
            &emission,
            &dense,
            SenderBalance::Off,
            &crate::comm::SingleProcess,
            &pool,
        );
        // A closed scene's full solve scales what it gathered (`solve::closed`); the direct
        // pass's irradiance is compared with the light before that scale.
        let scale = full.stats.closure.map_or([1.0; 3], |c| c.scales.gathered);
        let mut worst = 0f64;
        for i in 0..set.surfels.len() {
            for side in 0..2 {
                for ch in 0..3 {
                    let split = emission[i][side][ch] as f64
                        + reflectance[i][side][ch] * direct.irradiance[i][side][ch];
                    let e = emission[i][side][ch] as f64;
                    let plain = e + (full.radiosity[i][side][ch] as f64 - e) / scale[ch];
                    worst = worst.max((split - plain).abs() / plain.abs().max(1e-3));
                }
            }
        }
        assert!(worst < 1e-5, "worst {worst}");
        assert!(direct.stats.lines > 0);
    }

    fn shape(emitting: usize, surfels: usize, longest_axis: u32, directions: usize) -> Shape {
        Shape {
            emitting,
            surfels,
            longest_axis,
            directions,
        }
    }

    #[test]
    fn automatic_pass_only_for_small_affordable_emitters() {
        // The Cornell box at resolution 32: 48 of 6,718 surfels emit.
        let cornell = shape(48, 6718, 32, 193);
        assert_eq!(DirectPass::Auto(20_000).resolve(cornell), Some(20_000));
        // Every surfel emits (a furnace): no pass.
        assert_eq!(
            DirectPass::Auto(20_000).resolve(shape(100, 100, 8, 49)),
            None
        );
        // Asked for more than the budget: capped to what about ten iterations cost.
        let capped = DirectPass::Auto(1_000_000).resolve(cornell).unwrap();
        assert_eq!(capped, affordable_directions(48, 6718, 32, 193));
        assert!(capped > 20_000 && capped < 1_000_000);
        // Many small lamps in a huge grid: the budget leaves fewer than twice the solve's own
        // directions, no gain.
        assert_eq!(
            DirectPass::Auto(20_000).resolve(shape(40_000, 1_000_000, 4000, 49)),
            None
        );
        // Asked for explicitly: always, as asked; 0 never.
        assert_eq!(
            DirectPass::On(500).resolve(shape(100, 100, 8, 49)),
            Some(500)
        );
        assert_eq!(DirectPass::On(0).resolve(cornell), None);
        assert_eq!(DirectPass::Off.resolve(cornell), None);
    }

    #[test]
    fn voxel_keys_are_distinct_up_to_the_grid_limit() {
        let edge = (1 << 21) - 1;
        let keys = [
            VoxelTable::key([0, 0, 0]),
            VoxelTable::key([edge, 0, 0]),
            VoxelTable::key([0, edge, 0]),
            VoxelTable::key([0, 0, edge]),
            VoxelTable::key([1, 1, 1]),
            VoxelTable::key([edge, edge, edge]),
        ];
        for (i, a) in keys.iter().enumerate() {
            for b in &keys[i + 1..] {
                assert_ne!(a, b);
            }
        }
    }
}

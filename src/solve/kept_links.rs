//! The partner links one rank keeps between iterations for its steps (one direction each), and
//! their replay; used by the in-memory solver (`jacobi`) and the data and hybrid modes in
//! memory (`distribute::data`).
//!
//! **Blocks.** A direction's links (`links::DirectionLinks`) are in the order its lines were
//! gathered, so replaying one direction reads and writes the light of the surfels it names all
//! over their arrays: for each link a receiver's sums (48 bytes) and a partner's radiosity (24
//! bytes), both at random. Once every direction of a run of [`BLOCK_STEPS`] consecutive steps
//! has its links kept, they are moved into one [`LinkBlock`] that lists them by receiving
//! surfel side: a replay of the block then walks the sums once, in order, each side's in a
//! register, and only the partners' radiosity is read at random. Each side's links stay in step
//! order, and within a step in the order the first gather applied them, so every side adds the
//! same terms in the same order as step after step: the same bits (see
//! `a_block_replays_to_the_bits_of_its_directions`). A block's links take 4 bytes each where
//! its sides and factors fit 32 bits, else 8 (`Entries`).
//! A block is replayed whole at its first step and the steps after it inside the block do
//! nothing, so the light can be saved inside a block only at its bounds
//! ([`KeptLinks::can_save_within`]). Where the ranks must agree on that, blocks are used only in
//! iterations in which every rank kept every step's links ([`Blocks::Uniform`]): then the bounds
//! are the same steps on every rank. One process makes a block of every run whose steps' links
//! are all kept ([`Blocks::WhereWhole`]), even where the budget held only some runs.
//!
//! **The first iteration.** Blocks need not wait for the second iteration: in the first, the
//! steps of a run only write their links down ([`KeptLinks::defers`]), and at the run's last
//! step the sweep makes the block and replays it ([`KeptLinks::finish_run`]). The gather of a
//! search waits on the same random reads a replay of single directions does, so this saves most
//! of the first iteration's gather, with the same bits. On several ranks a run is made a block
//! only where every rank agrees ([`KeptLinks::run_waits_whole`]), so that the steps where the
//! light can be saved stay the same on every rank ([`Blocks::Off`]). Where the budget refuses a
//! step's links, or a checkpoint or a stop falls inside the run ([`KeptLinks::settle`]), the
//! steps waiting are gathered apart at once, in order, and the run's remaining steps gather as
//! they search. A run's steps are written down into the memory of the last block's steps
//! ([`KeptLinks::spare_words`]), not into fresh pages (see `Spare`).

use super::links::{DirectionLinks, LinkBudget};
use super::propagate::prefetch;
use super::update::{Gathered, Radiosity};
use crate::comm::Comm;
use rayon::prelude::*;

/// Steps whose links make one block. Larger blocks read the receivers' sums fewer times; one
/// block of 32 already reads them a thirty-second as often as its steps would apart.
pub const BLOCK_STEPS: usize = 32;

/// How many entries ahead a block's replay asks for the partner a link names.
const PREFETCH_AHEAD: usize = 16;

/// Entries of one piece of a block's replay (pieces are dealt to the threads).
const PIECE_ENTRIES: u64 = 1 << 15;

/// Sides a block can name: its entries hold a side number in 28 bits.
const BLOCK_SIDES: u64 = 1 << 28;

/// Where an entry's factor index begins.
const FACTOR_SHIFT: u32 = 28;

/// Distinct factors a block can hold: far more than its steps have (a few dozen each), and
/// its table of them stays small beside its links.
const BLOCK_FACTORS: u64 = 1 << 23;

/// The links of a run of steps, by receiving surfel side (side `t` is surfel `t / 2`'s side
/// `t % 2`).
///
/// Keyed by side rather than by surfel so that a replay adds each side's terms in a register:
/// with both sides' links of a surfel mixed, each link chose its side's sums by an index, and
/// the sums went through memory from one link to the next (a store then a load of the same
/// place, in a chain: a third of the replay's time in `perf`). A side's links are in the same
/// order either way, so its sum is the same.
#[derive(Debug, Default)]
pub struct LinkBlock {
    /// Side `t`'s links are `entries[starts[t]..starts[t + 1]]`.
    starts: Vec<u32>,
    entries: Entries,
    /// Where an entry's factor index begins: the bits below name the sending side.
    factor_shift: u32,
    /// The steps' distinct factors, one table after the other.
    factors: Vec<f64>,
    /// Replay pieces, as surfel bounds: piece `p` is surfels `pieces[p]..pieces[p + 1]`.
    pieces: Vec<usize>,
}

/// A block's links: each its sending side in the bits below [`LinkBlock::factor_shift`], the
/// index of its factor in [`LinkBlock::factors`] above.
///
/// **Narrow** where the sides and factors fit 32 bits (a scene of 2^20 surfels leaves 11 bits,
/// 2,048 factors for a block's 32 steps, which have a few dozen each): a replay streams the
/// entries (2.1 GB an iteration for the Cornell box at resolution 256 with 589 directions, in
/// 8-byte entries) and they are most of a solve's memory. Else **wide**, 64 bits (the factor
/// index from bit [`FACTOR_SHIFT`]).
#[derive(Debug, PartialEq)]
enum Entries {
    Narrow(Vec<u32>),
    Wide(Vec<u64>),
}

impl Default for Entries {
    fn default() -> Self {
        Entries::Narrow(Vec::new())
    }
}

impl Entries {
    fn bytes(&self) -> usize {
        match self {
            Entries::Narrow(v) => v.len() * 4,
            Entries::Wide(v) => v.len() * 8,
        }
    }
}

/// The bits that name a sending side of a block over `surfels` surfels.
fn side_bits(surfels: usize) -> u32 {
    (2 * surfels as u64).next_power_of_two().trailing_zeros()
}

/// Whether a block over `surfels` surfels with `factors` distinct factors has narrow entries.
fn narrow(surfels: usize, factors: usize) -> bool {
    let bits = side_bits(surfels);
    bits < 32 && factors as u64 <= 1 << (32 - bits)
}

impl LinkBlock {
    /// The bytes a block of the links of `steps` over `surfels` surfels would hold, or `None`
    /// where a block cannot hold them (too many surfels, links or factors).
    pub fn bytes_for(steps: &[&DirectionLinks], surfels: usize) -> Option<u64> {
        let total: usize = steps.iter().map(|d| d.len()).sum();
        let factors: usize = steps.iter().map(|d| d.factors().len()).sum();
        let fits = 2 * surfels as u64 <= BLOCK_SIDES
            && (total as u64) < u32::MAX as u64
            && (factors as u64) < BLOCK_FACTORS;
        let entry = if narrow(surfels, factors) { 4 } else { 8 };
        fits.then(|| (2 * surfels as u64 + 1) * 4 + total as u64 * entry + factors as u64 * 8)
    }

    /// The links of `steps` (in step order) moved into one block over the `surfels` first
    /// surfels, which [`Self::bytes_for`] found it can hold. Each step's links are dropped as
    /// soon as they are placed, so that the memory held while a block is made stays close to
    /// the links' own (the block's pages are written, and taken from the system, as the steps'
    /// are given back).
    pub fn fuse(steps: Vec<DirectionLinks>, surfels: usize) -> LinkBlock {
        Self::fuse_recycling(steps, surfels, None)
    }

    /// [`Self::fuse`], handing the steps' emptied memory to `spare` where given.
    fn fuse_recycling(
        steps: Vec<DirectionLinks>,
        surfels: usize,
        spare: Option<&mut Spare>,
    ) -> LinkBlock {
        let factors = steps.iter().map(|d| d.factors().len()).sum();
        Self::fuse_as(steps, surfels, narrow(surfels, factors), spare)
    }

    /// [`Self::fuse_recycling`], with narrow entries or not as `narrow` says (where they fit).
    fn fuse_as(
        steps: Vec<DirectionLinks>,
        surfels: usize,
        narrow: bool,
        mut spare: Option<&mut Spare>,
    ) -> LinkBlock {
        let total: usize = steps.iter().map(|d| d.len()).sum();
        debug_assert!(Self::bytes_for(&steps.iter().collect::<Vec<_>>(), surfels).is_some());
        // Links per bucket of receiving sides, step by step, then where each bucket's links
        // begin (those of each side are counted inside its bucket, by `place`). By step, so
        // that `place` can give each thread a range of steps and where its links go in every
        // bucket: 4 bytes a bucket and step, 8 MiB for 2^27 surfels in a run of 32 steps.
        // (Counted by side, each thread held an array of every side: 8 bytes a surfel a
        // thread, 32 GB for 2^27 surfels on a node of 32 threads.)
        let sides = 2 * surfels;
        let buckets = sides.div_ceil(BUCKET_SIDES);
        let step_counts: Vec<Vec<u32>> = steps
            .par_iter()
            .map(|d| {
                let mut counts = vec![0u32; buckets];
                d.for_each_link(|to, from, _| {
                    // A narrow entry holds the sending side in `side_bits(surfels)` bits.
                    assert!(
                        (from as usize) < sides,
                        "a link names a surfel of the block"
                    );
                    counts[to as usize / BUCKET_SIDES] += 1
                });
                counts
            })
            .collect();
        let mut counts = vec![0u32; buckets];
        for step in &step_counts {
            counts.iter_mut().zip(step).for_each(|(x, y)| *x += y);
        }
        let mut bucket_starts = Vec::with_capacity(buckets + 1);
        let mut at = 0u32;
        bucket_starts.push(0);
        for c in &counts {
            at += c;
            bucket_starts.push(at);
        }
        let mut offsets = Vec::with_capacity(steps.len());
        let mut factors = Vec::new();
        for d in &steps {
            offsets.push(factors.len() as u64);
            factors.extend_from_slice(d.factors());
        }
        debug_assert!(!narrow || self::narrow(surfels, factors.len()));
        let mut starts = vec![0u32; sides + 1];
        let (entries, factor_shift) = if narrow {
            let bits = side_bits(surfels);
            let entries = place(
                steps,
                &step_counts,
                sides,
                &bucket_starts,
                &mut starts,
                |from, factor, step| (from as u64 | (factor as u64 + offsets[step]) << bits) as u32,
                spare.as_deref_mut(),
            );
            (Entries::Narrow(entries), bits)
        } else {
            let entries = place(
                steps,
                &step_counts,
                sides,
                &bucket_starts,
                &mut starts,
                |from, factor, step| from as u64 | (factor as u64 + offsets[step]) << FACTOR_SHIFT,
                spare,
            );
            (Entries::Wide(entries), FACTOR_SHIFT)
        };
        let pieces = split_by_entries(&starts, (total as u64).div_ceil(PIECE_ENTRIES).max(1));
        LinkBlock {
            starts,
            entries,
            factor_shift,
            factors,
            pieces,
        }
    }

    /// Bytes held (the replay's piece bounds, a few per 32,768 links, left out).
    pub fn bytes(&self) -> u64 {
        (self.starts.len() * 4 + self.entries.bytes() + self.factors.len() * 8) as u64
    }

    /// Adds to `acc` what the block's links bring from `radiosity` (the first `channels`
    /// channels).
    pub fn replay(&self, radiosity: &[Radiosity], channels: usize, acc: &mut [Gathered]) {
        let surfels = (self.starts.len() - 1) / 2;
        assert!(
            acc.len() >= surfels && radiosity.len() >= surfels,
            "the light holds every surfel the block names"
        );
        let mut parts = Vec::with_capacity(self.pieces.len());
        let mut rest = &mut acc[..surfels];
        for w in self.pieces.windows(2) {
            let (part, tail) = rest.split_at_mut(w[1] - w[0]);
            parts.push((w[0], part));
            rest = tail;
        }
        parts
            .into_par_iter()
            .for_each(|(first, part)| match (&self.entries, channels) {
                (Entries::Narrow(e), 1) => self.replay_piece::<1, u32>(e, first, part, radiosity),
                (Entries::Narrow(e), _) => self.replay_piece::<3, u32>(e, first, part, radiosity),
                (Entries::Wide(e), 1) => self.replay_piece::<1, u64>(e, first, part, radiosity),
                (Entries::Wide(e), _) => self.replay_piece::<3, u64>(e, first, part, radiosity),
            });
    }

    /// Replays the links received by surfels `first..first + acc.len()` into `acc`, from the
    /// block's `entries`.
    #[inline(never)]
    fn replay_piece<const CHANNELS: usize, E: Copy + Into<u64>>(
        &self,
        entries: &[E],
        first: usize,
        acc: &mut [Gathered],
        radiosity: &[Radiosity],
    ) {
        let shift = self.factor_shift;
        let side_mask = (1u64 << shift) - 1;
        let starts = &self.starts[2 * first..=2 * (first + acc.len())];
        let entries = &entries[..starts[starts.len() - 1] as usize];
        // Side `t` of the light is surfel `t / 2`'s side `t % 2`, as the entries name it.
        let sides = radiosity.as_flattened();
        let mut k = starts[0] as usize;
        for (s, sums) in acc.iter_mut().enumerate() {
            for (side, to) in sums.iter_mut().enumerate() {
                let last = starts[2 * s + side + 1] as usize;
                let mut light = *to;
                for (at, &entry) in (k..).zip(&entries[k..last]) {
                    if let Some(&ahead) = entries.get(at + PREFETCH_AHEAD) {
                        prefetch(sides.as_ptr(), (ahead.into() & side_mask) as usize);
                    }
                    let entry: u64 = entry.into();
                    let sent = &sides[(entry & side_mask) as usize];
                    let factor = self.factors[(entry >> shift) as usize];
                    for c in 0..CHANNELS {
                        light[c] += sent[c] as f64 * factor;
                    }
                }
                k = last;
                *to = light;
            }
        }
    }
}

/// Receiving sides of one bucket of [`place`]: their entries (about 16 a side in a block of 32
/// steps) fit the caches of one core.
const BUCKET_SIDES: usize = 1 << 12;

/// The entries of the links of `steps`, each made by `entry(from, factor, step)`, by receiving
/// side (of `sides`); each side's in step order, and in each step in link order. Bucket `b` of
/// [`BUCKET_SIDES`] sides holds the links `bucket_starts[b]..bucket_starts[b + 1]`, of which
/// step `s` has `step_counts[s][b]`; where each side's links begin is written to `starts`
/// (`sides + 1` of them).
///
/// Placing each link straight at its side's place writes all over the block's entries (far
/// larger than the caches, every write a miss): instead the links are first appended, step
/// after step, to their buckets, each at its own final range, with the receiver's place in its
/// bucket beside (two bytes a link); then each bucket's sides are counted and its links put in
/// order inside its range, which the caches hold. The first pass runs on the threads by ranges
/// of steps, each range's links placed in every bucket after the earlier ranges' (from the
/// counts by step), so that each link is read once; the second by ranges of buckets. (The
/// first pass by ranges of buckets had every thread read every link and keep those of its
/// buckets: on two threads it read the steps twice, on a node of 32 threads 32 times.) A
/// step's links are dropped once appended. The entries are made at their final width at once:
/// an array of wide entries narrowed afterwards was 12 more bytes a link of fresh pages, which
/// the first iteration of the Cornell setting faulted in for every block. With `spare`, the
/// steps' memory and the receivers' places are handed to it for the next block instead of
/// being freed ([`Spare`]).
fn place<E, F>(
    steps: Vec<DirectionLinks>,
    step_counts: &[Vec<u32>],
    sides: usize,
    bucket_starts: &[u32],
    starts: &mut [u32],
    entry: F,
    mut spare: Option<&mut Spare>,
) -> Vec<E>
where
    E: Copy + Default + Send + Sync,
    F: Fn(u32, u32, usize) -> E + Sync,
{
    const _: () = assert!(BUCKET_SIDES <= 1 << 16);
    let buckets = bucket_starts.len() - 1;
    debug_assert_eq!(buckets, sides.div_ceil(BUCKET_SIDES));
    debug_assert_eq!(starts.len(), sides + 1);
    debug_assert_eq!(step_counts.len(), steps.len());
    let total = bucket_starts[buckets] as usize;
    let bucket_start = |b: usize| bucket_starts[b] as usize;
    let mut entries = vec![E::default(); total];
    let mut places = spare
        .as_deref_mut()
        .map(|spare| std::mem::take(&mut spare.places))
        .unwrap_or_default();
    places.clear();
    places.resize(total, 0);
    let threads = rayon::current_num_threads().max(1);

    // Pass 1: ranges of steps of about equal links, one a thread, each with where its links
    // begin and end in every bucket; each step's links appended to their buckets, then the
    // step dropped (or its memory kept).
    let mut step_ranges = Vec::with_capacity(threads);
    let mut cursor: Vec<u32> = bucket_starts[..buckets].to_vec();
    let mut rest = steps.into_iter();
    let mut links_before = 0usize;
    let mut first = 0;
    while first < step_counts.len() {
        let target = total * (step_ranges.len() + 1) / threads;
        let mut end = first;
        let mut links = links_before;
        while end < step_counts.len() && (end == first || links < target) {
            links += step_counts[end].iter().map(|&c| c as usize).sum::<usize>();
            end += 1;
        }
        let begin = cursor.clone();
        for counts in &step_counts[first..end] {
            cursor.iter_mut().zip(counts).for_each(|(c, n)| *c += n);
        }
        let range: Vec<DirectionLinks> = rest.by_ref().take(end - first).collect();
        step_ranges.push((first, range, begin, cursor.clone()));
        links_before = links;
        first = end;
    }
    debug_assert!(cursor
        .iter()
        .enumerate()
        .all(|(b, &c)| c == bucket_starts[b + 1]));
    let keep_words = spare.is_some();
    let out = Placed {
        entries: entries.as_mut_ptr(),
        places: places.as_mut_ptr(),
    };
    let words: Vec<Vec<Vec<u64>>> = step_ranges
        .into_par_iter()
        .map(|(first, range, mut cursors, ends)| {
            let mut words = Vec::new();
            for (i, d) in range.into_iter().enumerate() {
                let step = first + i;
                d.for_each_link(|to, from, factor| {
                    let s = to as usize;
                    let b = s / BUCKET_SIDES;
                    let at = cursors[b];
                    // The counts by step were made from these very links; this keeps a
                    // miscount from writing into another range's entries.
                    assert!(at < ends[b], "a link beyond its step's count");
                    // SAFETY: `at` lies in this range's own part of bucket `b`
                    // (`cursors[b]..ends[b]`, disjoint from every other range's and inside
                    // `total`), so no other thread writes it.
                    unsafe { out.write(at as usize, entry(from, factor, step), s) };
                    cursors[b] = at + 1;
                });
                if keep_words {
                    words.extend(d.into_words());
                }
            }
            words
        })
        .collect();
    if let Some(spare) = spare.as_deref_mut() {
        spare.words.extend(words.into_iter().flatten());
    }

    // Pass 2: ranges of buckets of about equal entries, one a thread; each bucket's sides
    // counted, then its links in side order, inside its range.
    let mut cuts = vec![0usize];
    for t in 1..threads {
        let target = total * t / threads;
        let b = bucket_starts
            .partition_point(|&s| (s as usize) < target)
            .min(buckets);
        if b > *cuts.last().expect("a first cut") {
            cuts.push(b);
        }
    }
    if *cuts.last().expect("a first cut") < buckets || buckets == 0 {
        cuts.push(buckets);
    }
    cuts.dedup();
    starts[sides] = total as u32;
    let mut parts = Vec::with_capacity(cuts.len());
    let (mut rest, mut rest_places) = (entries.as_mut_slice(), places.as_mut_slice());
    let mut rest_starts = &mut starts[..sides];
    for w in cuts.windows(2) {
        let len = bucket_start(w[1]) - bucket_start(w[0]);
        let (part, tail) = rest.split_at_mut(len);
        let (part_places, tail_places) = rest_places.split_at_mut(len);
        let side_len = (w[1] * BUCKET_SIDES).min(sides) - w[0] * BUCKET_SIDES;
        let (part_starts, tail_starts) = rest_starts.split_at_mut(side_len);
        parts.push((w[0]..w[1], part, part_places, part_starts));
        rest = tail;
        rest_places = tail_places;
        rest_starts = tail_starts;
    }
    parts
        .into_par_iter()
        .for_each(|(range, part, part_places, part_starts)| {
            let base = bucket_start(range.start);
            let first_side = range.start * BUCKET_SIDES;
            let mut buffer = Vec::new();
            let mut place = vec![0u32; BUCKET_SIDES];
            for b in range {
                let (from, to) = (bucket_start(b) - base, bucket_start(b + 1) - base);
                let s0 = b * BUCKET_SIDES;
                let bucket_len = BUCKET_SIDES.min(sides - s0);
                let place = &mut place[..bucket_len];
                place.fill(0);
                for &at in &part_places[from..to] {
                    place[at as usize] += 1;
                }
                // Counts to where each side's links begin, in the bucket and in the block.
                let mut at = 0u32;
                for (k, p) in place.iter_mut().enumerate() {
                    let count = *p;
                    *p = at;
                    part_starts[s0 - first_side + k] = bucket_starts[b] + at;
                    at += count;
                }
                buffer.clear();
                buffer.extend_from_slice(&part[from..to]);
                let out = &mut part[from..to];
                for (&e, &at) in buffer.iter().zip(&part_places[from..to]) {
                    let p = &mut place[at as usize];
                    out[*p as usize] = e;
                    *p += 1;
                }
            }
        });
    if let Some(spare) = spare {
        spare.places = places;
    }
    entries
}

/// The arrays pass 1 of [`place`] writes from several threads, each at places no other thread
/// writes.
struct Placed<E> {
    entries: *mut E,
    places: *mut u16,
}

// SAFETY: the pointers are only written through `Placed::write`, whose callers write disjoint
// places, while the arrays outlive the threads (they are owned by `place`, which joins them).
unsafe impl<E: Send> Send for Placed<E> {}
unsafe impl<E: Send> Sync for Placed<E> {}

impl<E> Placed<E> {
    /// Writes link entry `e` for receiving side `side` at place `at`.
    ///
    /// # Safety
    /// `at` lies inside both arrays, and no other thread reads or writes it meanwhile.
    #[inline(always)]
    unsafe fn write(&self, at: usize, e: E, side: usize) {
        unsafe {
            self.entries.add(at).write(e);
            self.places.add(at).write((side % BUCKET_SIDES) as u16);
        }
    }
}

/// Memory of the links of a run just made a block, kept for the next run's: each step's links
/// (8 bytes a link) and the receivers' places of [`place`] (2 bytes a link). Freed, and given
/// back to the system after each block ([`give_back_freed_memory`]), they were taken again
/// from the system for the next block, a page fault each 4 KiB: the first iteration of the
/// Cornell setting (resolution 256, 589 directions) took about a million page faults, 2.2 to
/// 2.6 s of system time on two threads. Kept, the next run's steps take them over one by one;
/// none are kept from the last run of an iteration ([`KeptLinks::fuse_if_whole`]), when the
/// most blocks are held, nor past an iteration. There the faults halved, the setting took
/// about 0.6 s less (17.6 s against 18.3) and its peak resident memory grew by 1 to 3 %: a
/// block is now made beside its steps' memory kept, not as it is given back
/// (`docs/throughput.md`). What is spare (at most one run's steps, whose links the budget
/// counted while they were kept) is not counted again by the links' budget.
#[derive(Debug, Default)]
struct Spare {
    words: Vec<Vec<u64>>,
    places: Vec<u16>,
}

/// Returns to the system the memory of the links just moved into a block. A step's links are
/// a few MiB, which glibc's malloc serves from its heap and keeps there when freed, while a
/// block's entries (larger) are mapped apart: without this, the process held both, and the
/// Cornell box at resolution 256 with 589 directions peaked at 4.3 GB instead of 2.3 GB.
fn give_back_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `malloc_trim` only returns free pages of malloc's heap to the system.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Surfel bounds cutting `starts` (a prefix sum of entries by side, two sides a surfel) into
/// about `pieces` runs of equal entries, first 0 and last the surfel count: a surfel's two
/// sides stay in one run, so that each run's sums are its own.
fn split_by_entries(starts: &[u32], pieces: u64) -> Vec<usize> {
    let surfels = (starts.len() - 1) / 2;
    let total = starts[2 * surfels] as u64;
    let mut bounds = vec![0usize];
    for p in 1..pieces {
        let target = (total * p / pieces) as u32;
        // The first surfel whose links begin at or after `target`.
        let (mut lo, mut hi) = (0, surfels);
        while lo < hi {
            let mid = (lo + hi) / 2;
            if starts[2 * mid] < target {
                lo = mid + 1;
            } else {
                hi = mid;
            }
        }
        let at = lo;
        if at > *bounds.last().expect("a first bound") {
            bounds.push(at);
        }
    }
    if *bounds.last().expect("a first bound") < surfels || surfels == 0 {
        bounds.push(surfels);
    }
    bounds.dedup();
    bounds
}

/// What one run of [`BLOCK_STEPS`] steps holds.
#[derive(Debug, Default)]
enum Block {
    /// Its steps' links apart (those kept so far).
    #[default]
    Apart,
    /// Its steps' links in one block.
    Fused(LinkBlock),
    /// Some step's links were not kept, or a block cannot hold them: they stay apart.
    Refused,
}

/// Where an iteration replays blocks (see the module header).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Blocks {
    /// Several ranks, not every one of which kept every step's links: no block is made at the
    /// start of a run; the runs written down whole in a first iteration are made blocks at
    /// their ends where every rank agrees ([`KeptLinks::finish_run`]), so that the light can
    /// be saved at the same steps on every rank.
    Off,
    /// Everywhere, on every rank: every rank kept every step's links. The light can be saved
    /// at multiples of [`BLOCK_STEPS`] only, the same steps on every rank.
    Uniform,
    /// One process: every run whose steps' links are all kept. The light can be saved anywhere
    /// but inside a block it has replayed.
    WhereWhole,
}

/// The links of one rank's steps, kept within a budget, apart or in blocks.
pub struct KeptLinks {
    /// By step: the links kept apart.
    apart: Vec<Option<DirectionLinks>>,
    /// By step: whether its links were written down once (kept or not).
    tried: Vec<bool>,
    blocks: Vec<Block>,
    budget: LinkBudget,
    /// Where this iteration replays blocks.
    mode: Blocks,
    /// The steps of this iteration up to which a replayed block has gathered.
    gathered_until: usize,
    /// Steps of this iteration whose links were written down without gathering, to be
    /// gathered together at the end of their run ([`Self::defers`]): consecutive, from the
    /// first step of a run.
    pending: Vec<usize>,
    /// The last block's steps' memory, for the next run's steps ([`Self::spare_words`]).
    spare: Spare,
}

impl KeptLinks {
    /// Nothing kept yet for `steps` steps, with `budget` bytes to keep links in.
    pub fn new(steps: usize, budget: u64) -> Self {
        KeptLinks {
            apart: (0..steps).map(|_| None).collect(),
            tried: vec![false; steps],
            blocks: (0..steps.div_ceil(BLOCK_STEPS))
                .map(|_| Block::Apart)
                .collect(),
            budget: LinkBudget { left: budget },
            mode: Blocks::Off,
            gathered_until: 0,
            pending: Vec::new(),
            spare: Spare::default(),
        }
    }

    /// Memory for a step's links to be written down into (`links::record_links`): that of a
    /// step of the last block made this iteration, where one is left, else none.
    pub fn spare_words(&mut self) -> Vec<u64> {
        self.spare.words.pop().unwrap_or_default()
    }

    /// Whether step `step`'s links are kept (apart or in a block).
    pub fn kept(&self, step: usize) -> bool {
        self.apart[step].is_some() || matches!(self.blocks[step / BLOCK_STEPS], Block::Fused(_))
    }

    /// Whether the first gather of step `step` should write its links down: not yet tried, and
    /// some budget left.
    pub fn should_record(&self, step: usize) -> bool {
        !self.tried[step] && self.budget.left > 0
    }

    /// Whether step `step`'s links were written down once.
    pub fn tried(&self, step: usize) -> bool {
        self.tried[step]
    }

    /// Keeps `recorded` as step `step`'s links if the budget allows.
    pub fn keep(&mut self, step: usize, recorded: DirectionLinks) {
        let _ = self.keep_or_return(step, recorded);
    }

    /// As [`Self::keep`], giving the links back where the budget refuses them.
    fn keep_or_return(&mut self, step: usize, recorded: DirectionLinks) -> Option<DirectionLinks> {
        self.tried[step] = true;
        if self.budget.take(recorded.bytes()) {
            self.apart[step] = Some(recorded);
            None
        } else {
            self.blocks[step / BLOCK_STEPS] = Block::Refused;
            Some(recorded)
        }
    }

    /// Whether the first gather of step `step` should only write its links down
    /// ([`Self::keep_deferred`]) and leave the light to a replay of its whole run
    /// ([`Self::finish_run`]): for the runs whose steps are all written down for the first
    /// time from their first step on, while the budget holds them (in an iteration that does
    /// not replay blocks on every rank, [`Blocks::Uniform`], where every step is kept already).
    /// A block's replay adds each side's terms in the order the steps' gathers would have (the
    /// same bits) and costs about a third of what those gathers spend on the light, which
    /// waits on the caches (the partners' radiosity and the receivers' sums, read at random).
    pub fn defers(&self, step: usize) -> bool {
        let b = step / BLOCK_STEPS;
        let continues = match self.pending.last() {
            None => step % BLOCK_STEPS == 0,
            Some(&last) => last + 1 == step,
        };
        self.mode != Blocks::Uniform
            && continues
            && self.should_record(step)
            && matches!(self.blocks[b], Block::Apart)
    }

    /// Keeps step `step`'s links, written down without gathering ([`Self::defers`]), until
    /// the end of its run ([`Self::finish_run`]). Where the budget refuses them, the steps
    /// waiting and this one are gathered into `acc` (the first `channels` channels of
    /// `radiosity`) apart at once, in order.
    pub fn keep_deferred(
        &mut self,
        step: usize,
        recorded: DirectionLinks,
        radiosity: &[Radiosity],
        channels: usize,
        acc: &mut [Gathered],
    ) {
        debug_assert!(self.defers(step));
        if let Some(refused) = self.keep_or_return(step, recorded) {
            self.settle(radiosity, channels, acc);
            refused.replay(radiosity, channels, acc);
            return;
        }
        self.pending.push(step);
    }

    /// Whether run `b` (steps `b * BLOCK_STEPS ..`) waits whole for its replay and a block over
    /// `surfels` surfels can hold it within the budget: what [`Self::finish_run`] may fuse. On
    /// several ranks they agree on it, so that every rank has blocks at the same runs (where
    /// the light can be saved depends on them, [`Self::can_save_within`]).
    pub fn run_waits_whole(&self, b: usize, surfels: usize) -> bool {
        let Some(range) = self.run(b) else {
            return false;
        };
        self.pending.len() == range.len()
            && self.pending.first() == Some(&range.start)
            && self.block_bytes(b, surfels).is_some()
    }

    /// The end of run `b` in an iteration: the steps of it waiting are gathered into `acc`
    /// (the first `channels` channels of `radiosity`), as one block where `fuse` says
    /// ([`Self::agree_on_run`]), else apart in order.
    pub fn finish_run(
        &mut self,
        b: usize,
        fuse: bool,
        radiosity: &[Radiosity],
        channels: usize,
        acc: &mut [Gathered],
    ) {
        if self.pending.is_empty() {
            return;
        }
        if fuse {
            debug_assert!(self.run_waits_whole(b, acc.len()));
            self.fuse_if_whole(b, acc.len());
        }
        match &self.blocks[b] {
            Block::Fused(block) if fuse => {
                block.replay(radiosity, channels, acc);
                self.pending.clear();
            }
            _ => self.settle(radiosity, channels, acc),
        }
    }

    /// Whether run `b` is replayed as one block at its end ([`Self::finish_run`]): where every
    /// rank of `comm` waits for it whole and can make the block over `surfels` surfels
    /// (collective on `comm` where it has several ranks); `None` where the iteration replays
    /// blocks on every rank ([`Blocks::Uniform`]), no step waits and no rank asks.
    pub fn agree_on_run(&self, b: usize, surfels: usize, comm: &dyn Comm) -> Option<bool> {
        if self.mode == Blocks::Uniform {
            return None;
        }
        let here = self.run_waits_whole(b, surfels);
        Some(if comm.size() == 1 {
            here
        } else {
            comm.max_u64(u64::from(!here)) == 0
        })
    }

    /// Gathers the steps whose links were written down without gathering, apart and in
    /// order, so that the light holds every step done (before a checkpoint inside their
    /// run, or a step that is not deferred).
    pub fn settle(&mut self, radiosity: &[Radiosity], channels: usize, acc: &mut [Gathered]) {
        for step in std::mem::take(&mut self.pending) {
            self.apart[step]
                .as_ref()
                .expect("a deferred step's links are kept")
                .replay(radiosity, channels, acc);
        }
    }

    /// Whether every step's links are kept (apart or in blocks).
    pub fn all_kept(&self) -> bool {
        (0..self.apart.len()).all(|s| self.kept(s))
    }

    /// An iteration starts, replaying blocks where `mode` says: [`Blocks::Uniform`] needs
    /// [`Self::all_kept`] on every rank whose sweep agrees on where to stop with this one's.
    pub fn begin_iteration(&mut self, mode: Blocks) {
        debug_assert!(mode != Blocks::Uniform || self.all_kept());
        debug_assert!(
            self.pending.is_empty(),
            "the last iteration gathered every step"
        );
        self.mode = mode;
        self.gathered_until = 0;
        self.pending.clear();
        // Runs are made blocks in the iteration that writes their links down, or at their
        // first step after: what is spare now would wait, held, for a block that may not come.
        self.spare = Spare::default();
    }

    /// Gathers step `step` into `acc` from its kept links (the first `channels` channels of
    /// `radiosity`); false (nothing done) where they are not kept. In an iteration that replays
    /// blocks, the first step of a block gathers the whole block (made from its steps' links
    /// the first time); its other steps then do nothing.
    pub fn replay(
        &mut self,
        step: usize,
        radiosity: &[Radiosity],
        channels: usize,
        acc: &mut [Gathered],
    ) -> bool {
        let b = step / BLOCK_STEPS;
        if self.mode != Blocks::Off && step % BLOCK_STEPS == 0 {
            self.fuse_if_whole(b, acc.len());
        }
        if let Block::Fused(block) = &self.blocks[b] {
            if step % BLOCK_STEPS == 0 {
                block.replay(radiosity, channels, acc);
                // Not bounded by this rank's steps: a rank dealt fewer steps answers
                // `can_save_within` as the others do.
                self.gathered_until = step + BLOCK_STEPS;
            }
            return true;
        }
        match &self.apart[step] {
            Some(links) => {
                links.replay(radiosity, channels, acc);
                true
            }
            None => false,
        }
    }

    /// The steps of run `b`, if this rank has any there.
    fn run(&self, b: usize) -> Option<std::ops::Range<usize>> {
        let range = b * BLOCK_STEPS..((b + 1) * BLOCK_STEPS).min(self.apart.len());
        (!range.is_empty()).then_some(range)
    }

    /// The bytes of a block of run `b` over `surfels` surfels, if all its steps' links are kept
    /// apart and the budget holds what the block adds.
    fn block_bytes(&self, b: usize, surfels: usize) -> Option<u64> {
        if !matches!(self.blocks.get(b), Some(Block::Apart)) {
            return None;
        }
        let steps = self.apart[self.run(b)?]
            .iter()
            .map(Option::as_ref)
            .collect::<Option<Vec<_>>>()?;
        let apart_bytes: u64 = steps.iter().map(|d| d.bytes()).sum();
        LinkBlock::bytes_for(&steps, surfels)
            .filter(|&bytes| bytes.saturating_sub(apart_bytes) <= self.budget.left)
    }

    /// Moves block `b`'s links into one [`LinkBlock`] over `surfels` surfels (every link names
    /// one of them) if all its steps' links are kept apart and the budget holds what the block
    /// adds.
    fn fuse_if_whole(&mut self, b: usize, surfels: usize) {
        if !matches!(self.blocks[b], Block::Apart) {
            return;
        }
        let Some(range) = self.run(b) else {
            return;
        };
        if self.apart[range.clone()].iter().any(Option::is_none) {
            return;
        }
        let Some(bytes) = self.block_bytes(b, surfels) else {
            self.blocks[b] = Block::Refused;
            return;
        };
        let apart_bytes: u64 = self.apart[range.clone()]
            .iter()
            .flatten()
            .map(DirectionLinks::bytes)
            .sum();
        let taken = self.budget.take(bytes.saturating_sub(apart_bytes));
        debug_assert!(taken, "block_bytes checked the budget");
        self.budget.left += apart_bytes.saturating_sub(bytes);
        let steps = self.apart[range]
            .iter_mut()
            .map(|d| d.take().expect("every step's links are kept"))
            .collect();
        // The last run keeps nothing spare: its block is made when the most blocks are held.
        let last = b + 1 == self.blocks.len();
        if last {
            self.spare = Spare::default();
        }
        let block = LinkBlock::fuse_recycling(steps, surfels, (!last).then_some(&mut self.spare));
        debug_assert_eq!(block.bytes(), bytes);
        self.blocks[b] = Block::Fused(block);
        give_back_freed_memory();
    }

    /// Whether the light can be saved `done` steps into this iteration (see [`Blocks`]); not
    /// while steps wait to be gathered ([`Self::settle`] gathers them).
    pub fn can_save_within(&self, done: usize) -> bool {
        // Off: blocks are made only at the ends of runs the ranks agreed on (`finish_run`),
        // so every rank has them at the same runs.
        match self.mode {
            Blocks::Uniform => done % BLOCK_STEPS == 0,
            Blocks::Off | Blocks::WhereWhole => {
                done >= self.gathered_until && self.pending.is_empty()
            }
        }
    }

    /// Steps whose links are kept, and the bytes held.
    pub fn held(&self) -> (usize, u64) {
        let steps = (0..self.apart.len()).filter(|&s| self.kept(s)).count();
        let apart: u64 = self.apart.iter().flatten().map(DirectionLinks::bytes).sum();
        let blocks: u64 = self
            .blocks
            .iter()
            .map(|b| match b {
                Block::Fused(block) => block.bytes(),
                _ => 0,
            })
            .sum();
        (steps, apart + blocks)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pieces_cut_by_entries_cover_every_surfel_once() {
        // Six surfels, by side.
        let starts = [0u32, 2, 5, 5, 5, 7, 9, 15, 20, 21, 21, 30, 40];
        for pieces in [1, 2, 3, 7, 50] {
            let b = split_by_entries(&starts, pieces);
            assert_eq!(b[0], 0);
            assert_eq!(*b.last().unwrap(), 6);
            assert!(b.windows(2).all(|w| w[0] < w[1]), "{b:?}");
        }
        assert_eq!(split_by_entries(&starts, 2), vec![0, 4, 6]);
        assert_eq!(split_by_entries(&[0], 4), vec![0]);
    }

    /// Links of `steps` directions over `surfels` surfels: each side of most surfels gathers
    /// from some other side, a few twice (an open edge), a few not at all; factors of the
    /// direction's own table.
    fn some_links(steps: usize, surfels: u32) -> Vec<DirectionLinks> {
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut next = move |below: u32| {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed % below as u64) as u32
        };
        (0..steps)
            .map(|d| {
                let factors: Vec<f64> = (0..3 + d % 4).map(|f| 0.1 + f as f64 / 7.0).collect();
                let mut links = Vec::new();
                // In a shuffled order of receivers, as lines visit them.
                let mut order: Vec<u32> = (0..2 * surfels).collect();
                for k in (1..order.len()).rev() {
                    order.swap(k, next(k as u32 + 1) as usize);
                }
                for to in order {
                    for _ in 0..[0, 1, 1, 1, 1, 2][next(6) as usize] {
                        let from = next(2 * surfels);
                        links.push((to, from, next(factors.len() as u32)));
                    }
                }
                DirectionLinks::from_triples(&links, factors)
            })
            .collect()
    }

    /// `steps` steps' links over `surfels` surfels, radiosity that differs from surfel to
    /// surfel, side to side and channel to channel, and the light the steps gather from it
    /// step after step (three channels, from 0.5 everywhere).
    fn steps_apart(
        surfels: u32,
        steps: usize,
    ) -> (Vec<DirectionLinks>, Vec<Radiosity>, Vec<Gathered>) {
        let directions = some_links(steps, surfels);
        let radiosity: Vec<Radiosity> = (0..surfels)
            .map(|s| [[s as f32 / 7.0, 1.0, 0.5], [0.25, s as f32 / 3.0, 2.0]])
            .collect();
        let mut light = vec![[[0.5f64; 3]; 2]; surfels as usize];
        for d in &directions {
            d.replay(&radiosity, 3, &mut light);
        }
        (directions, radiosity, light)
    }

    #[test]
    fn a_block_replays_to_the_bits_of_its_directions() {
        let surfels = 5_000u32;
        let steps = BLOCK_STEPS + 5;
        let directions = some_links(steps, surfels);
        let radiosity: Vec<Radiosity> = (0..surfels)
            .map(|s| {
                let v = |c: u32| ((s * 2_654_435_761u32.wrapping_add(c)) % 1000) as f32 / 997.0;
                [[v(1), v(2), v(3)], [v(4), v(5), v(6)]]
            })
            .collect();
        for channels in [1, 3] {
            // Step after step, apart.
            let mut expected = vec![[[0.25f64; 3]; 2]; surfels as usize];
            for d in &directions {
                d.replay(&radiosity, channels, &mut expected);
            }
            let mut kept = KeptLinks::new(steps, u64::MAX);
            for (step, d) in directions.iter().enumerate() {
                assert!(kept.should_record(step));
                kept.keep(step, d.clone());
            }
            for iteration in 0..2 {
                kept.begin_iteration(Blocks::Uniform);
                let mut acc = vec![[[0.25f64; 3]; 2]; surfels as usize];
                for step in 0..steps {
                    assert!(kept.replay(step, &radiosity, channels, &mut acc));
                    // The light holds whole blocks only.
                    let bound = (step + 1) % BLOCK_STEPS == 0;
                    assert_eq!(kept.can_save_within(step + 1), bound, "step {step}");
                }
                assert_eq!(
                    acc, expected,
                    "iteration {iteration}, {channels} channel(s)"
                );
                assert!(matches!(kept.blocks[0], Block::Fused(_)));
                assert!(matches!(kept.blocks[1], Block::Fused(_)));
                assert_eq!(kept.held().0, steps);
            }
        }
    }

    /// A block is placed by ranges of steps, one a thread, then by ranges of buckets: on any
    /// thread count (more threads than steps too) it holds the same entries in the same order.
    #[test]
    fn blocks_are_the_same_on_any_thread_count() {
        let surfels = 20_000u32;
        assert!(2 * surfels as usize > 4 * BUCKET_SIDES, "several buckets");
        let directions = some_links(BLOCK_STEPS, surfels);
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a pool")
                .install(|| LinkBlock::fuse(directions.clone(), surfels as usize))
        };
        let one = on(1);
        for threads in [2, 3, 7, 64] {
            let block = on(threads);
            assert_eq!(block.starts, one.starts, "{threads} threads");
            assert_eq!(block.entries, one.entries, "{threads} threads");
        }
    }

    /// Making a block hands its steps' memory on to the next run's steps, except the last
    /// run's: the blocks replay as the steps apart do, and nothing is left spare at the end.
    #[test]
    fn blocks_made_in_the_memory_of_the_last_one_replay_alike() {
        let (surfels, steps) = (4_000u32, 2 * BLOCK_STEPS + 3);
        let (directions, radiosity, expected) = steps_apart(surfels, steps);
        let mut kept = KeptLinks::new(steps, u64::MAX);
        for (step, d) in directions.iter().enumerate() {
            kept.keep(step, d.clone());
        }
        kept.begin_iteration(Blocks::Uniform);
        let mut acc = vec![[[0.5f64; 3]; 2]; surfels as usize];
        for step in 0..steps {
            assert!(kept.replay(step, &radiosity, 3, &mut acc));
            if step == 0 {
                // The first block's steps' memory waits for the next run's steps.
                assert_eq!(kept.spare.words.len(), BLOCK_STEPS);
                assert!(!kept.spare.places.is_empty());
                let words = kept.spare_words();
                assert!(words.is_empty() && words.capacity() > 0);
            }
        }
        assert_eq!(acc, expected);
        assert!(kept.blocks.iter().all(|b| matches!(b, Block::Fused(_))));
        assert!(kept.spare.words.is_empty() && kept.spare.places.capacity() == 0);
    }

    #[test]
    fn narrow_and_wide_blocks_replay_alike() {
        let surfels = 3_000u32;
        let directions = some_links(BLOCK_STEPS, surfels);
        let radiosity: Vec<Radiosity> = (0..surfels)
            .map(|s| {
                [
                    [s as f32 / 7.0, 1.0 / (s + 1) as f32, 0.5],
                    [0.25, s as f32, 3.0],
                ]
            })
            .collect();
        let mut expected = vec![[[0.125f64; 3]; 2]; surfels as usize];
        for d in &directions {
            d.replay(&radiosity, 3, &mut expected);
        }
        for narrow in [true, false] {
            let block = LinkBlock::fuse_as(directions.clone(), surfels as usize, narrow, None);
            assert_eq!(matches!(block.entries, Entries::Narrow(_)), narrow);
            let links: usize = directions.iter().map(DirectionLinks::len).sum();
            let entry = if narrow { 4 } else { 8 };
            assert_eq!(
                block.bytes() as usize,
                (2 * surfels as usize + 1) * 4 + links * entry + block.factors.len() * 8
            );
            let mut acc = vec![[[0.125f64; 3]; 2]; surfels as usize];
            block.replay(&radiosity, 3, &mut acc);
            assert_eq!(acc, expected, "narrow {narrow}");
        }
        // 2^20 surfels leave 11 bits of a narrow entry to the factors.
        assert!(narrow(1 << 20, 2048) && !narrow(1 << 20, 2049));
        assert!(!narrow(1 << 31, 1));
    }

    #[test]
    fn a_block_with_a_step_not_kept_stays_apart() {
        let surfels = 300u32;
        let directions = some_links(BLOCK_STEPS, surfels);
        let budget: u64 = directions[1..].iter().map(DirectionLinks::bytes).sum();
        let mut kept = KeptLinks::new(BLOCK_STEPS, budget);
        for (step, d) in directions.iter().enumerate().rev() {
            kept.keep(step, d.clone());
        }
        assert!(!kept.kept(0) && kept.kept(1) && kept.tried(0));
        let radiosity = vec![[[1.0f32; 3]; 2]; surfels as usize];
        let mut acc = vec![[[0.0f64; 3]; 2]; surfels as usize];
        assert!(!kept.all_kept());
        kept.begin_iteration(Blocks::Off);
        assert!(!kept.replay(0, &radiosity, 3, &mut acc));
        assert!(kept.replay(1, &radiosity, 3, &mut acc));
        assert!(matches!(kept.blocks[0], Block::Refused));
        assert!(kept.can_save_within(2));
    }

    #[test]
    fn one_process_makes_blocks_of_the_whole_runs_where_the_budget_held_only_some() {
        let surfels = 300u32;
        let steps = 2 * BLOCK_STEPS;
        let directions = some_links(steps, surfels);
        // Every step's links but the first's, and room for a block's starts.
        let budget = directions[1..]
            .iter()
            .map(DirectionLinks::bytes)
            .sum::<u64>()
            + 2_000;
        let mut kept = KeptLinks::new(steps, budget);
        for (step, d) in directions.iter().enumerate().rev() {
            kept.keep(step, d.clone());
        }
        assert!(!kept.kept(0) && !kept.all_kept());
        let radiosity: Vec<Radiosity> = (0..surfels)
            .map(|s| [[s as f32 / 7.0, 1.0, 0.5], [0.25, s as f32 / 3.0, 2.0]])
            .collect();
        let mut expected = vec![[[0.0f64; 3]; 2]; surfels as usize];
        for d in &directions[1..] {
            d.replay(&radiosity, 3, &mut expected);
        }
        kept.begin_iteration(Blocks::WhereWhole);
        let mut acc = vec![[[0.0f64; 3]; 2]; surfels as usize];
        for step in 0..steps {
            // Inside the second run, which is replayed whole at its first step, and only there,
            // the light holds steps beyond `step`.
            let inside = step > BLOCK_STEPS;
            assert_eq!(kept.can_save_within(step), !inside, "step {step}");
            assert_eq!(kept.replay(step, &radiosity, 3, &mut acc), step > 0);
        }
        assert!(matches!(kept.blocks[0], Block::Refused));
        assert!(matches!(kept.blocks[1], Block::Fused(_)));
        assert_eq!(acc, expected);
    }

    /// The one-process solver's first iteration as `jacobi` runs it: each step either writes
    /// its links down for a replay of its run ([`KeptLinks::defers`]) or, after the steps
    /// waiting are settled, gathers at once (here: its links replayed apart, the bits of a
    /// gather) and keeps them if it may; `settle_at` settles before that step, as a checkpoint
    /// inside the iteration does.
    fn an_iteration(
        kept: &mut KeptLinks,
        directions: &[DirectionLinks],
        radiosity: &[Radiosity],
        acc: &mut [Gathered],
        settle_at: Option<usize>,
    ) -> usize {
        kept.begin_iteration(Blocks::WhereWhole);
        let mut deferred = 0;
        for (step, d) in directions.iter().enumerate() {
            if settle_at == Some(step) {
                kept.settle(radiosity, 3, acc);
                assert!(kept.can_save_within(step));
            }
            let defer = kept.defers(step);
            if !defer {
                kept.settle(radiosity, 3, acc);
            }
            if kept.replay(step, radiosity, 3, acc) {
                assert!(!defer);
            } else if defer {
                deferred += 1;
                kept.keep_deferred(step, d.clone(), radiosity, 3, acc);
            } else {
                d.replay(radiosity, 3, acc);
                if kept.should_record(step) {
                    kept.keep(step, d.clone());
                }
            }
            // The light can be saved wherever no step waits: at the end of each run here.
            let run_end = (step + 1) % BLOCK_STEPS == 0 || step + 1 == directions.len();
            if run_end {
                let b = step / BLOCK_STEPS;
                let fuse = kept.run_waits_whole(b, acc.len());
                kept.finish_run(b, fuse, radiosity, 3, acc);
                // (Asked inside an iteration only.)
                if step + 1 < directions.len() {
                    assert!(kept.can_save_within(step + 1), "step {step}");
                }
            }
        }
        assert!(kept.pending.is_empty());
        deferred
    }

    #[test]
    fn a_first_iteration_replays_its_runs_to_the_bits_of_gathering_step_after_step() {
        let (surfels, steps) = (2_000u32, 2 * BLOCK_STEPS + 5);
        let (directions, radiosity, expected) = steps_apart(surfels, steps);
        let all: u64 = directions.iter().map(DirectionLinks::bytes).sum();
        // Every run whole; a checkpoint inside the second run (its steps before it gathered
        // apart, those after it gathered at once); the budget running out inside the second;
        // a solve resumed inside an iteration, which kept the links of the steps after the
        // checkpoint only (the second run's first steps wait, then its kept steps replay).
        let resumed_at = BLOCK_STEPS + 8;
        let cases = [
            (u64::MAX, None, 0, steps),
            (u64::MAX, Some(BLOCK_STEPS + 7), 0, BLOCK_STEPS + 7 + 5),
            (all / 2, None, 0, 0),
            (u64::MAX, None, resumed_at, BLOCK_STEPS + 8),
        ];
        for (budget, settle_at, kept_from, expect_deferred) in cases {
            let mut kept = KeptLinks::new(steps, budget);
            if kept_from > 0 {
                kept.begin_iteration(Blocks::WhereWhole);
                for (step, d) in directions.iter().enumerate().skip(kept_from) {
                    kept.keep(step, d.clone());
                }
            }
            let mut acc = vec![[[0.5f64; 3]; 2]; surfels as usize];
            let deferred = an_iteration(&mut kept, &directions, &radiosity, &mut acc, settle_at);
            let case = format!("budget {budget}, settled at {settle_at:?}, kept from {kept_from}");
            assert!(acc == expected, "{case}");
            if expect_deferred > 0 {
                assert_eq!(deferred, expect_deferred, "{case}");
            } else {
                // The runs before the budget ran out were deferred, the rest not.
                assert!(
                    deferred >= BLOCK_STEPS && deferred < steps,
                    "{case}: {deferred}"
                );
                assert!(matches!(kept.blocks[0], Block::Fused(_)), "{case}");
                assert!(matches!(kept.blocks[2], Block::Refused), "{case}");
            }
            // The next iteration replays what was kept, to the same bits.
            kept.begin_iteration(Blocks::WhereWhole);
            let mut again = vec![[[0.5f64; 3]; 2]; surfels as usize];
            for (step, d) in directions.iter().enumerate() {
                if !kept.replay(step, &radiosity, 3, &mut again) {
                    d.replay(&radiosity, 3, &mut again);
                }
            }
            assert!(again == expected, "{case}: second iteration");
        }
    }

    /// Two ranks whose budgets differ (the second's runs out inside the second run): in the
    /// first iteration a run becomes a block only where both wait for it whole, so both have
    /// blocks at the same runs and, once their steps waiting are settled, answer alike where
    /// the light can be saved, in the first iteration and the next (which makes no blocks at
    /// the start of runs: not every step was kept on every rank).
    #[test]
    fn ranks_make_blocks_at_the_same_runs() {
        let (surfels, steps) = (1_000u32, 3 * BLOCK_STEPS);
        let (directions, radiosity, expected) = steps_apart(surfels, steps);
        let first_runs: u64 = directions[..BLOCK_STEPS + 4]
            .iter()
            .map(DirectionLinks::bytes)
            .sum();
        let mut ranks = [
            KeptLinks::new(steps, u64::MAX),
            KeptLinks::new(steps, first_runs),
        ];
        let mut acc = vec![vec![[[0.5f64; 3]; 2]; surfels as usize]; 2];
        for iteration in 0..2 {
            for (kept, acc) in ranks.iter_mut().zip(&mut acc) {
                kept.begin_iteration(Blocks::Off);
                acc.iter_mut().for_each(|a| *a = [[0.5; 3]; 2]);
            }
            for (step, d) in directions.iter().enumerate() {
                for (kept, acc) in ranks.iter_mut().zip(&mut acc) {
                    let defer = kept.defers(step);
                    if !defer {
                        kept.settle(&radiosity, 3, acc);
                    }
                    if kept.replay(step, &radiosity, 3, acc) {
                        continue;
                    }
                    if defer {
                        kept.keep_deferred(step, d.clone(), &radiosity, 3, acc);
                    } else {
                        d.replay(&radiosity, 3, acc);
                        if kept.should_record(step) {
                            kept.keep(step, d.clone());
                        }
                    }
                }
                if (step + 1) % BLOCK_STEPS == 0 {
                    let b = step / BLOCK_STEPS;
                    let fuse = ranks.iter().all(|k| k.run_waits_whole(b, surfels as usize));
                    for (kept, acc) in ranks.iter_mut().zip(&mut acc) {
                        kept.finish_run(b, fuse, &radiosity, 3, acc);
                    }
                }
                // Where a checkpoint asks (after the steps waiting are settled, as the loop
                // does): inside the third run in the first iteration (the first rank waits for
                // the second whole, the other does not), everywhere in the next.
                let asked = iteration == 1 || step == 2 * BLOCK_STEPS + 6;
                if asked && step + 1 < steps {
                    for (kept, acc) in ranks.iter_mut().zip(&mut acc) {
                        kept.settle(&radiosity, 3, acc);
                    }
                    let answers = ranks.each_ref().map(|k| k.can_save_within(step + 1));
                    assert_eq!(answers[0], answers[1], "iteration {iteration}, step {step}");
                }
            }
            let fused = |k: &KeptLinks| {
                k.blocks
                    .iter()
                    .map(|b| matches!(b, Block::Fused(_)))
                    .collect::<Vec<_>>()
            };
            assert_eq!(fused(&ranks[0]), vec![true, false, false]);
            assert_eq!(fused(&ranks[1]), vec![true, false, false]);
            for a in &acc {
                assert!(*a == expected, "iteration {iteration}");
            }
        }
    }
}

//! Partner links kept between iterations: which surfel side gathers from which, with its
//! factor, for one direction. Which partner a surfel has along a line does not depend on the
//! radiosity, so the dispatch and the partner search of a direction need to run only once; the
//! iterations after the first replay the links, a streaming gather.
//!
//! A link is written down in the order the first gather applies it (`propagate::Record`), with
//! the very factor it used (`cos W / pi` times the open-edge share, in f64), so a replay adds
//! the same terms to each surfel side in the same order: the same bits as a search again. The
//! links of one direction are kept in the pieces the lines were dealt to the threads in (a
//! surfel lies on one line of a direction, so a surfel's links are all in one piece); the pieces
//! replay in parallel, each touching only its own surfels, whatever the thread count.
//!
//! **Compact.** A replay streams the links (0.5 GB per iteration for the Cornell box at
//! resolution 128, far beyond the caches), and they are most of a solve's memory, so a link is
//! one 64-bit word ([`Packed`]): its two sides and the index of its factor in its direction's
//! table of distinct factors. A direction has few of them (the factor is the receiver's `cos W /
//! pi`, the same for every surfel of one normal, times a share that is 1 but at open edges), so
//! the table stays in the cache. Scenes of more than 2^27 surfels, or a direction with more than
//! 256 distinct factors, keep that direction's links in 12 bytes each.
//!
//! What is kept is bounded by a budget ([`LinkBudget`]): a direction whose links do not fit is
//! searched again in every iteration, as before.
//!
//! **As bytes** ([`DirectionLinks::encode_head`], [`DirectionLinks::encode_block`]): a head and
//! blocks of byte planes of differences, which compress well; the out-of-core links files
//! (`outcore::links`) compress them with LZ4. This module writes and reads the planes, not the
//! files.

use super::dispatch::Lines;
use super::jacobi::AccPtr;
use super::light_sum::LightSum;
use super::mix_hash::MixMap;
use super::propagate::{prefetch, DirectionInput, Record};
use super::update::{Gathered, Radiosity};
use rayon::prelude::*;

/// How many links ahead a replay asks for the surfels a link names.
const PREFETCH_AHEAD: usize = 16;

/// One kept link: side `to & 1` of surfel `to >> 1` gathers side `from & 1` of surfel
/// `from >> 1`, times factor `factor` of its table (its piece's while recorded, its
/// direction's once kept).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Link {
    to: u32,
    from: u32,
    factor: u32,
}

/// What the first gather of one piece of lines writes down: its links, and its distinct factors
/// (by their bits, so that a replay multiplies by the very same value).
pub(crate) struct PieceRecorder {
    links: Vec<Link>,
    /// The largest side number its links name (receiving or sending).
    largest_side: u32,
    factors: Vec<f64>,
    index: MixMap<u32>,
    /// A small cache in front of `index`, by a hash of the factor's bits: (bits, index), or
    /// `u64::MAX` bits for an empty entry (not the bits of any factor, which is finite).
    recent: [(u64, u32); RECENT],
}

/// Entries of [`PieceRecorder::recent`]: a direction's distinct factors are few (one per normal
/// met, times the rare open-edge shares), and consecutive links of a line alternate between
/// the surfaces it crosses, so a cache of the last one missed most of the time.
const RECENT: usize = 64;
const _: () = assert!(RECENT.is_power_of_two());

impl Default for PieceRecorder {
    fn default() -> Self {
        PieceRecorder {
            links: Vec::new(),
            largest_side: 0,
            factors: Vec::new(),
            index: MixMap::default(),
            recent: [(u64::MAX, 0); RECENT],
        }
    }
}

impl Record for PieceRecorder {
    fn expect(&mut self, surfels: usize) {
        // About one link per surfel (a side facing nothing has none, open edges add a few).
        self.links.reserve(surfels + surfels / 8);
    }

    #[inline(always)]
    fn link(&mut self, receiver: u32, to_side: usize, partner: u32, from_side: usize, factor: f64) {
        let bits = factor.to_bits();
        let mixed = (bits ^ bits >> 29).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let slot = (mixed >> (64 - RECENT.trailing_zeros())) as usize;
        let index = match self.recent[slot] {
            (cached, index) if cached == bits => index,
            _ => {
                let next = self.factors.len() as u32;
                let index = *self.index.entry(bits).or_insert(next);
                if index == next {
                    self.factors.push(factor);
                }
                self.recent[slot] = (bits, index);
                index
            }
        };
        let link = Link {
            to: receiver << 1 | to_side as u32,
            from: partner << 1 | from_side as u32,
            factor: index,
        };
        self.largest_side = self.largest_side.max(link.to.max(link.from));
        self.links.push(link);
    }
}

/// Side numbers a narrow link holds (surfel `n`'s side `s` is `2 n + s`): 2^27 surfels.
const NARROW_SIDES: u32 = 1 << 28;
/// Distinct factors of a direction that narrow links can name.
const NARROW_FACTORS: usize = 1 << 8;

/// The links of one direction as stored: narrow, 8 bytes a link (its receiving side in bits 0
/// to 27, its sending side in bits 28 to 55, its factor's index in bits 56 to 63), where the
/// side numbers and the factors fit, else wide (12 bytes a link).
#[derive(Clone, Debug)]
enum Packed {
    Narrow(Vec<u64>),
    Wide(Vec<Link>),
}

impl Default for Packed {
    fn default() -> Self {
        Packed::Narrow(Vec::new())
    }
}

impl Packed {
    fn len(&self) -> usize {
        match self {
            Packed::Narrow(v) => v.len(),
            Packed::Wide(v) => v.len(),
        }
    }

    fn link_bytes(&self) -> usize {
        match self {
            Packed::Narrow(_) => 8,
            Packed::Wide(_) => 12,
        }
    }
}

/// The three numbers of a narrow link.
#[inline(always)]
fn unpack(word: u64) -> Link {
    const MASK: u64 = NARROW_SIDES as u64 - 1;
    Link {
        to: (word & MASK) as u32,
        from: (word >> 28 & MASK) as u32,
        factor: (word >> 56) as u32,
    }
}

/// Whether links naming sides up to `largest_side` with `factors` distinct factors fit narrow
/// words.
fn fits_narrow(largest_side: u32, factors: usize) -> bool {
    largest_side < NARROW_SIDES && factors <= NARROW_FACTORS
}

/// `link` with its piece's factor index replaced by the direction's (`table`).
fn renumbered(link: &Link, table: &[u32]) -> Link {
    Link {
        factor: table[link.factor as usize],
        ..*link
    }
}

/// Links a block of byte planes holds ([`DirectionLinks::encode_block`]; the last of a
/// direction's may hold fewer): a reader or writer needs room for one block's planes (72 KB
/// narrow), not a band's. Under LZ4, blocks of 8,192 links took 2.46 bytes a link, 4,096 2.60
/// and 65,536 2.34 (the Cornell box at resolution 256, 49 directions).
pub const PLANE_BLOCK_LINKS: usize = 1 << 13;

/// Bytes of a link's factor index in [`DirectionLinks::encode_block`]'s planes.
fn factor_index_bytes(wide: bool) -> usize {
    if wide {
        4
    } else {
        1
    }
}

/// Where a block's links are put back from its planes ([`DirectionLinks::encode_block`]).
trait PlaneLink: Copy + Send {
    /// Bytes of the factor index in the planes.
    const FACTOR_BYTES: usize;
    fn of(to: u32, from: u32, factor: u32) -> Self;
}

impl PlaneLink for u64 {
    const FACTOR_BYTES: usize = 1;
    #[inline(always)]
    fn of(to: u32, from: u32, factor: u32) -> Self {
        narrow(&Link { to, from, factor })
    }
}

impl PlaneLink for Link {
    const FACTOR_BYTES: usize = 4;
    #[inline(always)]
    fn of(to: u32, from: u32, factor: u32) -> Self {
        Link { to, from, factor }
    }
}

/// Appends `n` links to `links`, block after block on the threads: `unpack(block, planes)`
/// fills a block's planes, which are then put back ([`links_of_planes`]); false where a block
/// cannot be unpacked or its planes are not links.
fn links_of_blocks<L: PlaneLink + Default>(
    links: &mut Vec<L>,
    n: usize,
    factors: usize,
    unpack: &(impl Fn(usize, &mut [u8]) -> bool + Sync),
) -> bool {
    let at = links.len();
    links.resize(at + n, L::default());
    links[at..]
        .par_chunks_mut(PLANE_BLOCK_LINKS)
        .enumerate()
        .map_init(Vec::new, |planes, (block, out)| {
            planes.resize(out.len() * (8 + L::FACTOR_BYTES), 0);
            unpack(block, planes) && links_of_planes(planes, factors, out)
        })
        .all(|ok| ok)
}

/// Puts a block's links back from its planes into `out` (as many links as it holds); false
/// when a factor index is beyond a table of `factors`, or a narrow link names a side beyond
/// narrow words.
fn links_of_planes<L: PlaneLink>(planes: &[u8], factors: usize, out: &mut [L]) -> bool {
    let n = out.len();
    debug_assert_eq!(planes.len(), n * (8 + L::FACTOR_BYTES));
    // The numbers first, plane by plane (loops the compiler vectorises), then the sides, link
    // by link, a part of the block at a time so that the numbers stay in the cache.
    const PART: usize = 2048;
    let mut numbers = [[0u32; PART]; 3];
    let widths = [4, 4, L::FACTOR_BYTES];
    let mut side = 0u32;
    let mut largest_factor = 0u32;
    // Sides of narrow links below NARROW_SIDES, checked once at the end.
    let mut beyond = 0u32;
    for (part, first) in out.chunks_mut(PART).zip((0..n).step_by(PART)) {
        let len = part.len();
        let mut plane = 0;
        for (values, width) in numbers.iter_mut().zip(widths) {
            let values = &mut values[..len];
            values.fill(0);
            for b in 0..width {
                let bytes = &planes[plane * n + first..plane * n + first + len];
                for (v, &byte) in values.iter_mut().zip(bytes) {
                    *v |= (byte as u32) << (8 * b);
                }
                plane += 1;
            }
        }
        let [steps, reaches, indexes] = &numbers;
        let numbers = steps.iter().zip(reaches).zip(indexes);
        for (link, ((&step, &reach), &factor)) in part.iter_mut().zip(numbers) {
            side = side.wrapping_add(step);
            let partner = side.wrapping_add(reach);
            beyond |= side | partner;
            largest_factor = largest_factor.max(factor);
            *link = L::of(side, partner, factor);
        }
    }
    let fits = L::FACTOR_BYTES == 4 || beyond < NARROW_SIDES;
    fits && (n == 0 || (largest_factor as usize) < factors)
}

/// A link as a narrow word (its numbers fit, see [`NARROW_SIDES`] and [`NARROW_FACTORS`]).
fn narrow(link: &Link) -> u64 {
    link.to as u64 | (link.from as u64) << 28 | (link.factor as u64) << 56
}

/// The links of one direction, in the pieces of lines its first gather dealt to the threads.
#[derive(Clone, Debug, Default)]
pub struct DirectionLinks {
    packed: Packed,
    /// The direction's distinct factors (by their bits).
    factors: Vec<f64>,
    /// Piece `p` is links `pieces[p]..pieces[p + 1]`.
    pieces: Vec<usize>,
    /// Links a head read back announced ([`Self::decode_head`]): its blocks add them.
    expected_links: usize,
}

impl DirectionLinks {
    /// Packs `links` (factor indices into `factors`), cut into `pieces`.
    fn pack(
        links: impl Iterator<Item = Link> + Clone,
        factors: Vec<f64>,
        pieces: Vec<usize>,
    ) -> Self {
        let largest_side = links.clone().map(|l| l.to.max(l.from)).max().unwrap_or(0);
        let packed = if fits_narrow(largest_side, factors.len()) {
            Packed::Narrow(links.map(|l| narrow(&l)).collect())
        } else {
            Packed::Wide(links.collect())
        };
        debug_assert_eq!(packed.len(), *pieces.last().unwrap_or(&0));
        DirectionLinks {
            packed,
            factors,
            pieces,
            expected_links: 0,
        }
    }

    /// The memory of the links, emptied, for the links of another direction
    /// ([`record_links`]); `None` where they are wide.
    pub(crate) fn into_words(self) -> Option<Vec<u64>> {
        match self.packed {
            Packed::Narrow(mut words) => {
                words.clear();
                Some(words)
            }
            Packed::Wide(_) => None,
        }
    }

    /// The links, in order.
    #[cfg(test)]
    fn links(&self) -> Box<dyn Iterator<Item = Link> + '_> {
        match &self.packed {
            Packed::Narrow(v) => Box::new(v.iter().map(|&w| unpack(w))),
            Packed::Wide(v) => Box::new(v.iter().copied()),
        }
    }

    /// Links held.
    pub fn len(&self) -> usize {
        self.packed.len()
    }

    /// Whether no link is held.
    pub fn is_empty(&self) -> bool {
        self.packed.len() == 0
    }

    /// The direction's distinct factors, which the links name by index.
    pub(super) fn factors(&self) -> &[f64] {
        &self.factors
    }

    /// Calls `f(to, from, factor)` for every link, in order: its receiving side, its sending
    /// side (surfel `n`'s side `s` is `2 n + s`) and its factor's index in [`Self::factors`].
    #[inline]
    pub(super) fn for_each_link(&self, mut f: impl FnMut(u32, u32, u32)) {
        match &self.packed {
            Packed::Narrow(v) => v.iter().for_each(|&w| {
                let l = unpack(w);
                f(l.to, l.from, l.factor)
            }),
            Packed::Wide(v) => v.iter().for_each(|l| f(l.to, l.from, l.factor)),
        }
    }

    /// Links from `(to, from, factor index)` triples, in one piece (for tests elsewhere).
    #[cfg(test)]
    pub(crate) fn from_triples(links: &[(u32, u32, u32)], factors: Vec<f64>) -> Self {
        let links = links
            .iter()
            .map(|&(to, from, factor)| Link { to, from, factor });
        let count = links.len();
        DirectionLinks::pack(links, factors, vec![0, count])
    }

    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        (self.packed.len() * self.packed.link_bytes()) as u64
            + self.factors.len() as u64 * 8
            + self.pieces.len() as u64 * 8
    }

    /// Adds to `acc` what the links bring from `radiosity` (the first `channels` channels).
    pub fn replay<A: LightSum>(&self, radiosity: &[Radiosity], channels: usize, acc: &mut [A]) {
        let acc_ptr = AccPtr(acc.as_mut_ptr());
        let len = acc.len();
        assert!(
            radiosity.len() >= len,
            "the radiosity holds every surfel the links name"
        );
        self.pieces.par_windows(2).for_each(|w| {
            let at = Arrays {
                factors: &self.factors,
                radiosity,
                acc: acc_ptr.get(),
                len,
            };
            // SAFETY: the surfels of one piece's links are no other piece's (see the module
            // header), so the pieces write disjoint parts of `acc`; `AccPtr` is shared for that.
            unsafe {
                match (&self.packed, channels) {
                    (Packed::Narrow(v), 1) => replay_piece::<1, _, _>(&v[w[0]..w[1]], unpack, &at),
                    (Packed::Narrow(v), _) => replay_piece::<3, _, _>(&v[w[0]..w[1]], unpack, &at),
                    (Packed::Wide(v), 1) => replay_piece::<1, _, _>(&v[w[0]..w[1]], |l| l, &at),
                    (Packed::Wide(v), _) => replay_piece::<3, _, _>(&v[w[0]..w[1]], |l| l, &at),
                }
            }
        });
    }

    /// Appends the head of the links' bytes to `out`: little-endian counts (factors, pieces,
    /// links) and whether they are wide, then the factors and the piece bounds. The links
    /// follow in blocks of [`PLANE_BLOCK_LINKS`] ([`Self::encode_block`]); [`Self::decode_head`]
    /// and [`Self::decode_blocks`] read them back.
    pub fn encode_head(&self, out: &mut Vec<u8>) {
        let wide = matches!(self.packed, Packed::Wide(_));
        for count in [
            self.factors.len(),
            self.pieces.len(),
            self.packed.len(),
            wide as usize,
        ] {
            out.extend_from_slice(&(count as u64).to_le_bytes());
        }
        for factor in &self.factors {
            out.extend_from_slice(&factor.to_bits().to_le_bytes());
        }
        for &bound in &self.pieces {
            out.extend_from_slice(&(bound as u64).to_le_bytes());
        }
    }

    /// Blocks of [`Self::encode_block`] the links take.
    pub fn blocks(&self) -> usize {
        self.packed.len().div_ceil(PLANE_BLOCK_LINKS)
    }

    /// Appends block `block` of the links (links `block * PLANE_BLOCK_LINKS` on, at most
    /// [`PLANE_BLOCK_LINKS`] of them) to `out` as byte planes. A link is three numbers: its
    /// receiving side less the one before it (wrapping; the block's first less 0), its sending
    /// side less its receiving side (wrapping) and its factor's index (one byte where narrow,
    /// four where wide). The planes are byte 0 of every link's first number, then byte 1, ...,
    /// then the second number's, then the index's.
    ///
    /// Why planes of differences: a line's surfels follow one another at a few strides, and a
    /// partner is the next surfel of its line, so the differences repeat and their high bytes
    /// are nearly all 0 or 255. Whole words looked random to a compressor (LZ4 took 7.7 of
    /// their 8 bytes); these planes take about 2.5 bytes a link under LZ4 (the Cornell box at
    /// resolution 256, 49 directions), which the out-of-core links files use.
    pub fn encode_block(&self, block: usize, out: &mut Vec<u8>) {
        let wide = matches!(self.packed, Packed::Wide(_));
        let first = block * PLANE_BLOCK_LINKS;
        let n = PLANE_BLOCK_LINKS.min(self.packed.len() - first);
        let mut numbers = [
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
        ];
        let mut before = 0u32;
        let mut add = |l: Link| {
            numbers[0].push(l.to.wrapping_sub(before));
            numbers[1].push(l.from.wrapping_sub(l.to));
            numbers[2].push(l.factor);
            before = l.to;
        };
        match &self.packed {
            Packed::Narrow(v) => v[first..first + n].iter().for_each(|&w| add(unpack(w))),
            Packed::Wide(v) => v[first..first + n].iter().for_each(|&l| add(l)),
        }
        let widths = [4, 4, factor_index_bytes(wide)];
        for (values, width) in numbers.iter().zip(widths) {
            for b in 0..width {
                out.extend(values.iter().map(|&v| (v >> (8 * b)) as u8));
            }
        }
    }

    /// Bytes of block `block`'s planes ([`Self::encode_block`]) of links as held.
    pub fn block_len(&self, block: usize) -> usize {
        let wide = matches!(self.packed, Packed::Wide(_));
        let n = PLANE_BLOCK_LINKS.min(self.packed.len() - block * PLANE_BLOCK_LINKS);
        n * (8 + factor_index_bytes(wide))
    }

    /// Reads back into `self` a head [`Self::encode_head`] wrote (the arrays' memory reused),
    /// with no links yet: [`Self::decode_blocks`] adds them. `None` when `bytes` are not such a
    /// head (a piece bound out of range included).
    pub fn decode_head(&mut self, bytes: &[u8]) -> Option<()> {
        let word = |at: usize| -> Option<u64> {
            Some(u64::from_le_bytes(bytes.get(at..at + 8)?.try_into().ok()?))
        };
        let counts = [word(0)?, word(8)?, word(16)?, word(24)?].map(|c| c as usize);
        let [factors, pieces, links, wide] = counts;
        let expected = 8usize.checked_mul(factors.checked_add(pieces)?.checked_add(4)?)?;
        if wide > 1 || bytes.len() != expected {
            return None;
        }
        let mut at = 32;
        self.factors.clear();
        for _ in 0..factors {
            self.factors.push(f64::from_bits(word(at)?));
            at += 8;
        }
        self.pieces.clear();
        for _ in 0..pieces {
            self.pieces.push(word(at)? as usize);
            at += 8;
        }
        let bounds_ok = self.pieces.first().is_none_or(|&b| b == 0)
            && self.pieces.windows(2).all(|w| w[0] <= w[1])
            && self.pieces.last().is_none_or(|&b| b == links);
        if !bounds_ok {
            return None;
        }
        self.expected_links = links;
        self.packed = match (std::mem::take(&mut self.packed), wide) {
            (Packed::Narrow(mut v), 0) => {
                v.clear();
                Packed::Narrow(v)
            }
            (Packed::Wide(mut v), 1) => {
                v.clear();
                Packed::Wide(v)
            }
            (_, 0) => Packed::Narrow(Vec::new()),
            _ => Packed::Wide(Vec::new()),
        };
        Some(())
    }

    /// Links whose blocks are still to come after [`Self::decode_head`].
    pub fn links_to_come(&self) -> usize {
        self.expected_links - self.packed.len()
    }

    /// Encodes every block ([`Self::encode_block`]) on the threads of the current pool and
    /// hands each block's planes to `pack`; what it made of each block, in block order.
    pub fn encode_blocks<T: Send>(&self, pack: impl Fn(&[u8]) -> T + Sync) -> Vec<T> {
        (0..self.blocks())
            .into_par_iter()
            .map_init(Vec::new, |planes, block| {
                planes.clear();
                self.encode_block(block, planes);
                pack(planes)
            })
            .collect()
    }

    /// Adds every link the head read by [`Self::decode_head`] announced, block by block on the
    /// threads of the current pool: `unpack(block, planes)` fills `planes`, sized to the
    /// block's bytes, with that block's planes ([`Self::encode_block`]), or says it cannot
    /// (false). `None` when a block cannot be unpacked or its planes are not links (a factor
    /// index beyond the table, or a narrow link naming a side beyond narrow words).
    pub fn decode_blocks(
        &mut self,
        unpack: impl Fn(usize, &mut [u8]) -> bool + Sync,
    ) -> Option<()> {
        let n = self.links_to_come();
        let factors = self.factors.len();
        let ok = match &mut self.packed {
            Packed::Narrow(v) => links_of_blocks(v, n, factors, &unpack),
            Packed::Wide(v) => links_of_blocks(v, n, factors, &unpack),
        };
        ok.then_some(())
    }

    /// The largest surfel number the links name, plus one (0 for none).
    pub fn surfels_named(&self) -> usize {
        let mut largest = None;
        self.for_each_link(|to, from, _| largest = largest.max(Some(to.max(from))));
        largest.map_or(0, |side| (side >> 1) as usize + 1)
    }
}

/// What a replay reads and writes besides the links.
struct Arrays<'a, A> {
    factors: &'a [f64],
    radiosity: &'a [Radiosity],
    acc: *mut A,
    /// Surfels of `acc`.
    len: usize,
}

/// Adds to `at.acc` the first `CHANNELS` channels of what the links of `piece` (read by
/// `link`) bring from `at.radiosity`, in their order.
///
/// # Safety
/// `at.acc` points to `at.len` surfels, no other thread touches those the links of `piece`
/// receive on, and `at.radiosity` holds at least `at.len` surfels.
#[inline(never)]
unsafe fn replay_piece<const CHANNELS: usize, T: Copy, A: LightSum>(
    piece: &[T],
    link: impl Fn(T) -> Link,
    at: &Arrays<A>,
) {
    for (k, &item) in piece.iter().enumerate() {
        // The surfels a link names lie scattered over arrays far larger than the caches: ask
        // for those of a link a little ahead.
        if let Some(&ahead) = piece.get(k + PREFETCH_AHEAD) {
            let ahead = link(ahead);
            prefetch(at.radiosity.as_ptr(), (ahead.from >> 1) as usize);
            prefetch(at.acc as *const A, (ahead.to >> 1) as usize);
        }
        let link = link(item);
        let (receiver, partner) = ((link.to >> 1) as usize, (link.from >> 1) as usize);
        assert!(
            receiver < at.len && partner < at.len,
            "a link names a surfel of the scene"
        );
        // SAFETY: both indices are in bounds (checked above); see the function's contract.
        let (from, to) = unsafe {
            (
                &at.radiosity.get_unchecked(partner)[(link.from & 1) as usize],
                &mut *at.acc.add(receiver),
            )
        };
        let factor = at.factors[link.factor as usize];
        to.add((link.to & 1) as usize, from, factor, CHANNELS);
    }
}

/// Gathers direction `input` along `lines` into `acc`, as `jacobi::gather_all_lines` does (its
/// pieces, its order), and returns the links it applied.
pub fn gather_and_record<A: LightSum>(
    lines: &Lines,
    input: &DirectionInput,
    acc: &mut [A],
    threads: usize,
) -> DirectionLinks {
    packed(
        super::jacobi::gather_pieces::<_, A, true>(lines, input, acc, threads),
        Vec::new(),
    )
}

/// The links [`gather_and_record`] would return, found without adding any light: replayed
/// later, they add what that gather would have added, bit for bit. They are packed into `words`
/// where they are narrow (its memory reused: see `KeptLinks::spare_words`).
pub fn record_links(
    lines: &Lines,
    input: &DirectionInput,
    threads: usize,
    words: Vec<u64>,
) -> DirectionLinks {
    packed(
        super::jacobi::gather_pieces::<_, Gathered, false>(lines, input, &mut [], threads),
        words,
    )
}

/// The links the pieces of one direction recorded, packed into one [`DirectionLinks`] (into
/// `words` where they are narrow).
fn packed(pieces: Vec<PieceRecorder>, words: Vec<u64>) -> DirectionLinks {
    // The pieces' factor tables merged into one of distinct factors (by their bits), so that
    // the direction's factor indices take as few bits as they can.
    let mut factors: Vec<f64> = Vec::new();
    let mut index: MixMap<u32> = MixMap::default();
    let tables: Vec<Vec<u32>> = pieces
        .iter()
        .map(|piece| {
            piece
                .factors
                .iter()
                .map(|f| {
                    let next = factors.len() as u32;
                    let at = *index.entry(f.to_bits()).or_insert(next);
                    if at == next {
                        factors.push(*f);
                    }
                    at
                })
                .collect()
        })
        .collect();
    let mut bounds = vec![0];
    for piece in &pieces {
        bounds.push(bounds.last().expect("a first bound") + piece.links.len());
    }
    let largest_side = pieces.iter().map(|p| p.largest_side).max().unwrap_or(0);
    if fits_narrow(largest_side, factors.len()) {
        // Each piece packs its own links into its part of the direction's array, on the worker
        // threads (done in one thread after the gather, this was about a seventh of the first
        // pass on two threads). The array is not zeroed first: its memory, often reused from
        // the heap, was zeroed by one thread for every direction, 8 bytes a link.
        let total = bounds[bounds.len() - 1];
        let mut packed = words;
        packed.clear();
        packed.reserve(total);
        let mut parts = Vec::with_capacity(pieces.len());
        let mut rest = &mut packed.spare_capacity_mut()[..total];
        for piece in &pieces {
            let (part, tail) = rest.split_at_mut(piece.links.len());
            parts.push(part);
            rest = tail;
        }
        parts
            .into_par_iter()
            .zip(pieces.par_iter().zip(&tables))
            .for_each(|(part, (piece, table))| {
                for (word, link) in part.iter_mut().zip(&piece.links) {
                    word.write(narrow(&renumbered(link, table)));
                }
            });
        // SAFETY: the pieces' parts cover the first `total` words, and each part holds as many
        // words as its piece has links, every one written above.
        unsafe { packed.set_len(total) };
        return DirectionLinks {
            packed: Packed::Narrow(packed),
            factors,
            pieces: bounds,
            expected_links: 0,
        };
    }
    let links = pieces
        .iter()
        .zip(&tables)
        .flat_map(|(piece, table)| piece.links.iter().map(|link| renumbered(link, table)));
    DirectionLinks::pack(links, factors, bounds)
}

/// The default budget of the links: 4 GiB, at most a quarter of the memory available now (read
/// when the solver's arrays are made): the node's `MemAvailable`, or less where a control group
/// (a batch job's limit) leaves less; all of 4 GiB where neither can be read.
pub fn default_budget() -> u64 {
    let read = |path: &str| std::fs::read_to_string(path).ok();
    let number = |text: Option<String>| text.and_then(|t| t.trim().parse::<u64>().ok());
    let node = read("/proc/meminfo").and_then(|text| {
        let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
        let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
        Some(kib * 1024)
    });
    // cgroup v2, then v1 ("max" or an absent file: no limit).
    let group = [
        ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
        (
            "/sys/fs/cgroup/memory/memory.limit_in_bytes",
            "/sys/fs/cgroup/memory/memory.usage_in_bytes",
        ),
    ]
    .iter()
    .find_map(|(limit, used)| {
        let limit = number(read(limit))?;
        Some(limit.saturating_sub(number(read(used)).unwrap_or(0)))
    });
    let available = [node, group]
        .into_iter()
        .flatten()
        .min()
        .unwrap_or(u64::MAX);
    super::jacobi::DEFAULT_LINKS_MEMORY.min(available / 4)
}

/// The links budget of this rank of `comm` for a scene of `surfels`: `asked` if given, else
/// [`default_budget`] shared by the ranks of `comm` on this node (each would see the same
/// available memory and take its quarter); nothing where a surfel number would not leave a bit
/// for the side. Collective on `comm`.
pub fn rank_budget(asked: Option<u64>, surfels: usize, comm: &dyn crate::comm::Comm) -> u64 {
    if surfels >= 1 << 31 {
        return 0;
    }
    match asked {
        Some(bytes) => bytes,
        None => default_budget() / ranks_on_this_node(comm) as u64,
    }
}

/// How many ranks of `comm` run on this rank's node, by host name (every rank counts as one
/// node's where the name cannot be read: the smaller share). Collective on `comm`.
pub(crate) fn ranks_on_this_node(comm: &dyn crate::comm::Comm) -> usize {
    node_mates(comm).count
}

/// The ranks of `comm` that share this rank's node (by host name).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct NodeMates {
    /// How many, this one included (all where the name cannot be read: the smaller share).
    pub count: usize,
    /// Whether rank 0 is one of them (so it is where the name cannot be read: the room it
    /// needs is then set aside).
    pub with_rank_0: bool,
}

/// Which ranks of `comm` share this rank's node, by host name. Collective on `comm`.
pub(crate) fn node_mates(comm: &dyn crate::comm::Comm) -> NodeMates {
    if comm.size() == 1 {
        return NodeMates {
            count: 1,
            with_rank_0: true,
        };
    }
    let name = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|n| n.trim().as_bytes().to_vec())
        .unwrap_or_default();
    let received = comm.exchange(vec![name.clone(); comm.size()]);
    let mate = |other: &Vec<u8>| name.is_empty() || *other == name;
    NodeMates {
        count: received.iter().filter(|o| mate(o)).count().max(1),
        with_rank_0: comm.rank() == 0 || mate(&received[0]),
    }
}

/// How many bytes of links may still be kept.
#[derive(Clone, Copy, Debug)]
pub struct LinkBudget {
    pub left: u64,
}

impl LinkBudget {
    /// Takes `bytes` from the budget if they fit.
    pub fn take(&mut self, bytes: u64) -> bool {
        let fits = bytes <= self.left;
        if fits {
            self.left -= bytes;
        }
        fits
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_budget_is_at_most_four_gibibytes_and_not_nothing() {
        let budget = default_budget();
        assert!(budget > 0 && budget <= 4 << 30, "{budget}");
    }

    /// The links' head and each block's planes.
    fn encoded(links: &DirectionLinks) -> (Vec<u8>, Vec<Vec<u8>>) {
        let mut head = Vec::new();
        links.encode_head(&mut head);
        let blocks = (0..links.blocks())
            .map(|b| {
                let mut planes = Vec::new();
                links.encode_block(b, &mut planes);
                planes
            })
            .collect();
        (head, blocks)
    }

    /// Links read back from a head and blocks, `None` where any part is refused.
    fn decoded(head: &[u8], blocks: &[Vec<u8>]) -> Option<DirectionLinks> {
        let mut back = DirectionLinks::default();
        back.decode_head(head)?;
        back.decode_blocks(|b, planes| {
            let same = blocks.get(b).is_some_and(|p| p.len() == planes.len());
            if same {
                planes.copy_from_slice(&blocks[b]);
            }
            same
        })?;
        (back.links_to_come() == 0).then_some(back)
    }

    #[test]
    fn links_of_several_blocks_read_back_the_same() {
        // Steps both ways across a block's edge, sides wrapping, many factors.
        let count = 2 * PLANE_BLOCK_LINKS as u32 + 77;
        let links: Vec<Link> = (0..count)
            .map(|k| Link {
                to: (k * 2654435761) >> 5,
                from: (k * 40503) % 1000 + (k / 3),
                factor: k % 200,
            })
            .collect();
        let factors = (0..200).map(|k| k as f64 / 256.0).collect();
        let packed =
            DirectionLinks::pack(links.iter().copied(), factors, vec![0, 100, links.len()]);
        assert!(matches!(packed.packed, Packed::Narrow(_)));
        let (head, blocks) = encoded(&packed);
        assert_eq!(blocks.len(), 3);
        let back = decoded(&head, &blocks).expect("links read back");
        assert_eq!(back.links().collect::<Vec<_>>(), links);
        assert_eq!(back.pieces, packed.pieces);
    }

    #[test]
    fn links_read_back_from_their_bytes_are_the_same_links() {
        let mut recorder = PieceRecorder::default();
        recorder.link(3, 1, 7, 0, 0.25);
        recorder.link(7, 0, 3, 1, 0.125);
        recorder.link(4, 0, 9, 1, 0.25);
        let links = DirectionLinks::pack(
            recorder.links.iter().copied(),
            recorder.factors.clone(),
            vec![0, 2, 3],
        );
        assert!(matches!(links.packed, Packed::Narrow(_)));
        assert_eq!(links.links().collect::<Vec<_>>(), recorder.links);
        let (head, blocks) = encoded(&links);
        assert_eq!(blocks.len(), 1);
        assert_eq!(blocks[0].len(), links.block_len(0));
        let back = decoded(&head, &blocks).expect("links read back");
        assert_eq!(back.links().collect::<Vec<_>>(), recorder.links);
        assert_eq!(back.factors, links.factors);
        assert_eq!(back.pieces, links.pieces);
        assert_eq!(back.surfels_named(), 10);
        // Cut short, or a factor index beyond the table: refused.
        assert!(decoded(&head[..head.len() - 1], &blocks).is_none());
        let short = vec![blocks[0][..blocks[0].len() - 1].to_vec()];
        assert!(decoded(&head, &short).is_none());
        let mut wrong = blocks.clone();
        let last = wrong[0].len() - 1;
        wrong[0][last] = 2;
        assert!(decoded(&head, &wrong).is_none());
        // A receiving side beyond narrow words (the high byte of the first link's difference).
        let mut wide = blocks.clone();
        wide[0][3 * links.len()] = 0x40;
        assert!(decoded(&head, &wide).is_none());
    }

    #[test]
    fn links_too_large_for_narrow_words_are_kept_wide_and_read_back() {
        for (largest, factors) in [
            (NARROW_SIDES - 1, NARROW_FACTORS),
            (NARROW_SIDES, 1),
            (u32::MAX, 3),
            (5, NARROW_FACTORS + 1),
        ] {
            let factor_values: Vec<f64> = (0..factors).map(|k| 1.0 / (k + 2) as f64).collect();
            let links: Vec<Link> = (0..50u32)
                .map(|k| Link {
                    to: largest - k.min(largest),
                    from: k.wrapping_mul(7919) % largest.max(1),
                    factor: (k as usize * 31 % factors) as u32,
                })
                .collect();
            let packed =
                DirectionLinks::pack(links.iter().copied(), factor_values.clone(), vec![0, 50]);
            let narrow = largest < NARROW_SIDES && factors <= NARROW_FACTORS;
            assert_eq!(matches!(packed.packed, Packed::Narrow(_)), narrow);
            assert_eq!(
                packed.links().collect::<Vec<_>>(),
                links,
                "{largest} {factors}"
            );
            let (head, blocks) = encoded(&packed);
            let back = decoded(&head, &blocks).expect("links read back");
            assert_eq!(back.links().collect::<Vec<_>>(), links);
        }
    }

    #[test]
    fn a_replay_adds_each_link_s_light_times_its_factor() {
        let radiosity: Vec<Radiosity> = (0..4)
            .map(|k| [[k as f32, 2.0 * k as f32, 3.0], [10.0 + k as f32, 0.0, 1.0]])
            .collect();
        let links = [
            Link {
                to: 0 << 1,
                from: 3 << 1 | 1,
                factor: 0,
            },
            Link {
                to: 2 << 1 | 1,
                from: 1 << 1,
                factor: 1,
            },
            Link {
                to: 0 << 1,
                from: 2 << 1,
                factor: 1,
            },
        ];
        let kept = DirectionLinks::pack(links.iter().copied(), vec![0.5, 0.25], vec![0, 3]);
        let mut acc = vec![[[0.0f64; 3]; 2]; 4];
        kept.replay(&radiosity, 3, &mut acc);
        assert_eq!(
            acc[0][0],
            [13.0 * 0.5 + 2.0 * 0.25, 0.0 + 4.0 * 0.25, 0.5 + 0.75]
        );
        assert_eq!(acc[2][1], [0.25, 0.5, 0.75]);
        assert_eq!(acc[1], [[0.0; 3]; 2]);
        let mut grey = vec![[[0.0f64; 3]; 2]; 4];
        kept.replay(&radiosity, 1, &mut grey);
        assert_eq!(grey[0][0], [13.0 * 0.5 + 2.0 * 0.25, 0.0, 0.0]);
        // The same links kept wide (a table of more factors than a narrow word can name)
        // bring the same light.
        let mut many = vec![0.5, 0.25];
        many.extend((0..NARROW_FACTORS).map(|k| k as f64));
        let wide = DirectionLinks::pack(links.iter().copied(), many, vec![0, 3]);
        assert!(matches!(wide.packed, Packed::Wide(_)));
        let mut again = vec![[[0.0f64; 3]; 2]; 4];
        wide.replay(&radiosity, 3, &mut again);
        assert_eq!(again, acc);
    }

    #[test]
    fn a_budget_takes_what_fits_and_nothing_more() {
        let mut budget = LinkBudget { left: 100 };
        assert!(budget.take(60));
        assert!(!budget.take(41));
        assert!(budget.take(40));
        assert_eq!(budget.left, 0);
    }
}

//! Propagation: each surfel gathers light from its partner ahead and its partner behind on its
//! discrete line.
//!
//! **Which surfel is the partner is the crux.** The naive rule (the immediate neighbour on the
//! list) loses most of the light: a tunnel-free surface is more than one voxel thick along oblique
//! lines, so a surfel's neighbour is often a surfel of its own sheet, which would shadow it. The
//! rule here: the partner of `r` along `s` is the first surfel `c` ahead on the line such that
//!
//! - `c` is not of `r`'s plane group (coplanar surfels never light each other), and
//! - the two really face each other along the line: `c`'s surface point lies in front of `r`'s
//!   side that faces `s`, and `r`'s point lies in front of `c`'s side that faces back along `s`
//!   (equivalently: the ray from `r`'s point along `s` crosses `c`'s plane ahead, and the ray from
//!   `c`'s point along `-s` crosses `r`'s plane ahead). Both tests use the surfels' actual surface
//!   points, with a margin of [`EPS`] voxel.
//!
//! Surfels of one voxel are at the same place on the line, so among the candidates of one voxel
//! the one whose plane the ray crosses first wins, and surfels of the receiver's own voxel (the
//! other wall at an edge or corner) are candidates in both directions. Surfels that fail the tests
//! are skipped, not treated as blockers: a sheet of surfels stops the search as soon as one of its
//! surfels faces the receiver, which the tunnel-free voxelization guarantees for any line that
//! crosses it. Surfels are two-sided, so there are no back faces to block; the side of the partner
//! that faces the receiver is the one that sends light.
//!
//! **Open edges.** A line is a tube of unit section across its main axis, and a sheet crossed by
//! it blocks the part of that section its pieces cover once projected along the line. Inside a
//! surface that is all of it. Where the tube meets a plane that has an open edge on this line (a
//! lamp's rim, a table top's outline: a piece with coverage below 1, `solve::coverage`), the
//! plane blocks the sum of the projected areas of its pieces on the line (on the search's side of
//! the receiver), `sum(area |n.s|) / |s_main|`, at most 1: the nearest piece sends that share and
//! the rest of the ray goes on past the plane. Counting a whole hit, or the piece's coverage of
//! its own voxel, made an open sheet look up to a voxel wider at grazing angles, where the tube
//! runs along it for many voxels: a closed room lit by floating lamps absorbed 8 % more than the
//! lamps emitted at resolution 64. Summed over the lines, the shares add up to the sheet's
//! projected area along the direction, which is what energy conservation asks of it.
//!
//! **Rims at the ends of a plane's run.** A grazing line can run through a row of a plane's
//! voxels that hold nothing else (the middle of a lamp under its housing) before it reaches the
//! voxel where the plane ends at another surface (the housing's end face). A ray caught in the
//! middle would take the plane although it crosses the plane's level past that edge; so the ray
//! is also judged against the voxel-mates at both ends of the plane's run on the line, as it is
//! against its candidate's own voxel-mates. Without it, each edge of an object smaller than a
//! few voxels counted up to a voxel too wide at grazing directions: the office's 6 cm lamp
//! housings absorbed 25 % more than their lamps emitted at resolution 64 (10.5 % with it), and a
//! glowing cube nine voxels wide over-counted its power by 1 to 3 % at every placement (now
//! scattered around zero with the placement).
//!
//! **Where along a run.** Once a plane is hit, its partner piece is the one in the voxel of the
//! plane's run whose layer along the line's main axis holds the ray's crossing point, not the
//! run's first voxel (`LineView::where_crossed`): a lamp that fills an opening of a ceiling is
//! the ceiling's plane, and was unseen at grazing elevations while the first voxel took every
//! ray.
//!
//! **Boxes.** A piece is known here by its point, normal and bounding box in its voxel. A box
//! that runs through a voxel-mate's plane means a piece that does (a T-junction), unless it pokes
//! through by no more than a box can reach past its own piece (`box_overshoot`): the end face of
//! a tilted slab, sheared in its own plane, only touches the slab's top and bottom planes that
//! its box crosses (`side_of`).
//!
//! **Sides inside solids.** The back side of a closed solid's face (`voxel::enclosed`, flagged
//! in [`PropSurfel::inside_back`]) sees nothing: no search runs from it, and it gathers nothing.
//! A ray from outside can only reach it through the solid's surface, so a search that ends on one
//! is given the face turned to the receiver that it crossed just before (a slab thinner than a
//! voxel), or goes on past the plane when it crossed it beside the piece (a box's corner grazed),
//! and only otherwise stays on the dark side (`LineView::entry_face`).
//!
//! Every surfel side receives exactly one gather per line direction, so accumulating in direction
//! order makes the result independent of how lines are spread over threads.
//!
//! Cost: a line is first copied into a small local buffer (so the search touches contiguous
//! memory and the cosine with `s` is computed once per surfel), and runs of consecutive voxels that
//! hold only the receiver's own plane (a sheet seen at a grazing angle, possibly hundreds of voxels
//! long) are skipped in one step, so finding all partners of a line costs about its length. Most
//! lines (four in five surfels of the Cornell box) hold one surfel per voxel and meet no open
//! edge; they are searched without the line's voxel groups and open crossings and with none of
//! the bookkeeping for voxel-mates and open edges (`plain_partners`, for every search or only
//! those a caller wants; a line whose search meets a side inside a solid from behind goes to
//! `LineView::nearest_plain`), which gives the same partners. The surfels, radiosity and
//! sums of the lines a little ahead are prefetched ([`gather_lines`]): they lie scattered over
//! arrays far larger than the caches (about a sixth of the kernel's time went to waiting).
//! Which side of each other's planes two pieces of one voxel lie on depends on them alone: it is
//! computed once per solve and kept with each piece ([`PropSurfel::mate_sides`]). A caller that
//! needs only some searches of a line (the direct-light pass) says which ([`Toward`]).

use super::light_sum::LightSum;
use crate::voxel::{BACK, FRONT};
use glam::{DVec3, Vec3A};

/// Margin (voxel units) below which a point counts as lying on a plane rather than in front of it.
pub const EPS: f32 = 1e-4;

/// What propagation needs of a surfel, packed for the hot loop. In C layout: [`local_of`] reads
/// its vectors as 16-byte lanes from known offsets.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub struct PropSurfel {
    pub voxel: [i32; 3],
    pub group: u32,
    pub point: [f32; 3],
    pub normal: [f32; 3],
    /// Bounding box of the surfel's piece in its voxel (see `Surfel::extent`).
    pub extent: [[f32; 3]; 2],
    /// Fraction of the voxel's slice of the surfel's plane that its piece covers, for a piece at
    /// the open edge of a surface (alone in its voxel, not filling it); 1 everywhere else.
    pub coverage: f32,
    /// The back side lies inside a closed solid (its material is
    /// `scene::Material::inside_of_solids`): no search runs from it.
    pub inside_back: bool,
    /// The surfel keeps no area (a face wholly pressed against another solid, or a voxel the
    /// plane only touches): its point may lie inside a solid (see `LineView::entry_face`).
    pub no_area: bool,
    /// Its place among the surfels of its voxel, in the order of the surfel set (at most 255).
    pub rank: u8,
    /// Which side of the planes of the first [`RANKED_MATES`] surfels of its voxel (by
    /// [`PropSurfel::rank`]) this piece lies on, as [`side_of`] tells: two bits each,
    /// [`SIDE_UNKNOWN`] (not kept: computed when a search asks), [`SIDE_FRONT`],
    /// [`SIDE_BEHIND`] or [`SIDE_THROUGH`]. It depends on the two pieces alone, and the
    /// searches of every direction ask it again ([`with_mate_sides`]).
    pub mate_sides: u16,
}

/// Voxel-mates whose sides a [`PropSurfel`] keeps.
pub const RANKED_MATES: usize = 8;

/// Fills [`PropSurfel::mate_sides`] of the surfels of one voxel, listed in the order of their
/// surfel set.
pub fn with_mate_sides(voxel: &mut [PropSurfel]) {
    let unit = Vec3A::X;
    let locals: Vec<Local> = voxel.iter().map(|p| local_of(p, unit)).collect();
    for (piece, p) in voxel.iter_mut().enumerate() {
        p.rank = piece.min(u8::MAX as usize) as u8;
        p.mate_sides = 0;
        for (rank, mate) in locals.iter().enumerate().take(RANKED_MATES) {
            if rank != piece {
                p.mate_sides |= (side_code(side_of(mate, &locals[piece])) as u16) << (2 * rank);
            }
        }
    }
}

/// [`side_of`]'s answer as kept in [`PropSurfel::mate_sides`].
fn side_code(side: Option<f32>) -> u8 {
    match side {
        Some(v) if v > 0.0 => SIDE_FRONT,
        Some(_) => SIDE_BEHIND,
        None => SIDE_THROUGH,
    }
}

impl PropSurfel {
    /// What propagation reads of `surfel`, whose open-edge coverage is `coverage`
    /// (`solve::coverage`), with `materials` the surfel set's.
    pub fn new(
        surfel: &crate::voxel::Surfel,
        coverage: f32,
        materials: &[crate::scene::Material],
    ) -> Self {
        PropSurfel {
            voxel: surfel.voxel,
            group: surfel.group,
            point: surfel.point,
            normal: surfel.normal,
            extent: surfel.extent,
            coverage,
            inside_back: materials
                .get(surfel.material[crate::voxel::BACK] as usize)
                .is_some_and(|m| m.inside),
            no_area: surfel.area <= 0.0,
            rank: 0,
            mate_sides: 0,
        }
    }

    /// What propagation reads of the surfels of one voxel (`voxel`, in surfel-set order), with
    /// their open-edge coverage and the sides of each other's planes.
    pub fn of_voxel(
        voxel: &[crate::voxel::Surfel],
        materials: &[crate::scene::Material],
    ) -> Vec<PropSurfel> {
        let mut props: Vec<PropSurfel> = voxel
            .iter()
            .enumerate()
            .map(|(k, s)| {
                PropSurfel::new(s, super::coverage::coverage_in_voxel(voxel, k), materials)
            })
            .collect();
        with_mate_sides(&mut props);
        props
    }
}

/// What propagation reads of every surfel of `set` (with its open-edge coverage).
pub fn prop_surfels(set: &crate::voxel::SurfelSet) -> Vec<PropSurfel> {
    let coverage = super::coverage::coverages(set);
    let mut props: Vec<PropSurfel> = set
        .surfels
        .iter()
        .zip(&coverage)
        .map(|(s, &coverage)| PropSurfel::new(s, coverage, &set.materials))
        .collect();
    // A voxel's surfels are adjacent in a surfel set.
    let mut first = 0;
    while first < props.len() {
        let voxel = set.surfels[first].voxel;
        let end = first + set.surfels[first..].partition_point(|s| s.voxel == voxel);
        if end - first > 1 {
            with_mate_sides(&mut props[first..end]);
        }
        first = end;
    }
    props
}

/// A surfel as the search of direction `sf` reads it.
#[inline(always)]
fn local_of(p: &PropSurfel, sf: Vec3A) -> Local {
    let normal = lanes(p, std::mem::offset_of!(PropSurfel, normal));
    let ns = normal.dot(sf);
    Local {
        voxel: p.voxel,
        group: p.group,
        point: lanes(p, std::mem::offset_of!(PropSurfel, point)),
        normal,
        ns,
        // +1, -1 or 0 (also for NaN), without branches: the sign of a surfel's cosine is as
        // likely one way as the other.
        sgn: (ns > 0.0) as i32 as f32 - (ns < 0.0) as i32 as f32,
        lo: lanes(p, std::mem::offset_of!(PropSurfel, extent)),
        hi: lanes(p, std::mem::offset_of!(PropSurfel, extent) + 12),
        coverage: p.coverage,
        inside_back: p.inside_back,
        no_area: p.no_area,
        rank: p.rank,
        mate_sides: p.mate_sides,
    }
}

/// The three floats of `p` at byte `offset` as a [`Vec3A`], read as one unaligned 16-byte load:
/// its fourth lane holds the next field's first 4 bytes, which `Vec3A` never reads (its sums,
/// dot products and comparisons take three lanes). Building the vectors float by float took
/// about 12 instructions a surfel-direction more in a first pass (callgrind, docs/throughput.md).
#[inline(always)]
fn lanes(p: &PropSurfel, offset: usize) -> Vec3A {
    const {
        use std::mem::{offset_of, size_of};
        // Every vector read leaves 4 bytes of the record after it.
        assert!(offset_of!(PropSurfel, point) + 16 <= size_of::<PropSurfel>());
        assert!(offset_of!(PropSurfel, normal) + 16 <= size_of::<PropSurfel>());
        assert!(offset_of!(PropSurfel, extent) + 12 + 16 <= size_of::<PropSurfel>());
    }
    debug_assert!(offset + 16 <= std::mem::size_of::<PropSurfel>());
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: the 16 bytes at `offset` lie inside `*p` (the asserts above, for every offset
        // `local_of` passes), and SSE2 is part of x86-64; the load needs no alignment.
        unsafe {
            let at = (p as *const PropSurfel as *const u8).add(offset) as *const f32;
            Vec3A::from(std::arch::x86_64::_mm_loadu_ps(at))
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        // SAFETY: as above, 12 bytes inside `*p`; read unaligned.
        Vec3A::from(unsafe {
            ((p as *const PropSurfel as *const u8).add(offset) as *const [f32; 3]).read_unaligned()
        })
    }
}

/// A surfel of the line being processed, with its cosine to the direction. In C layout:
/// [`voxel_offset`] reads its voxel and group as one 16-byte lane.
#[derive(Clone, Copy, Debug)]
#[repr(C)]
struct Local {
    voxel: [i32; 3],
    group: u32,
    point: Vec3A,
    normal: Vec3A,
    /// `normal . s` for the unit direction `s`, and its sign (+-1; 0 when `ns` is 0).
    ns: f32,
    sgn: f32,
    lo: Vec3A,
    hi: Vec3A,
    coverage: f32,
    inside_back: bool,
    no_area: bool,
    rank: u8,
    mate_sides: u16,
}

/// Whether the side of `x` that its search ahead (`FORWARD`) or behind gathers into (the side
/// facing that way) is a back side inside a closed solid: nothing there is seen, so the search
/// is not run and the side gathers nothing (`voxel::enclosed`).
#[inline(always)]
fn gathers_inside<const FORWARD: bool>(x: &Local) -> bool {
    x.inside_back && if FORWARD { x.ns < 0.0 } else { x.ns > 0.0 }
}

/// Which side of `mate`'s plane `piece` lies on, from the piece's bounding box (+1 in front, -1
/// behind); `None` for a piece running through the plane.
///
/// A box reaches past its piece where the mate's plane is tilted against the grid: the end face
/// of a slab tilted by 0.05 rad is a sheared strip whose box pokes 0.05 voxel through the slab's
/// bottom, which it only touches. Past the plane the box's corner farthest along the normal is
/// at most [`box_overshoot`] beyond the piece, so a box that pokes through on one side by no
/// more than that, and reaches further on the other, is taken to lie on the other side. Without
/// this, floor rays that pass just under a tilted slab's end were caught on the end face's inner
/// side (dark: it faces into the solid) and the floor and the slab's underside came out 11 to
/// 15 % dark.
#[inline(always)]
fn side_of(mate: &Local, piece: &Local) -> Option<f32> {
    let n = mate.normal;
    let base = n.dot(offset(mate, piece) - piece.point);
    let (a, b) = (n * piece.lo, n * piece.hi);
    let low = base + a.min(b).element_sum();
    let high = base + a.max(b).element_sum();
    if low >= -EPS {
        return Some(1.0);
    }
    if high <= EPS {
        return Some(-1.0);
    }
    let slack = box_overshoot(n, piece) + EPS;
    if high <= slack && -low > high {
        Some(-1.0)
    } else if -low <= slack && high > -low {
        Some(1.0)
    } else {
        None
    }
}

/// How far the box of `piece` may reach along `n` beyond the piece itself. The piece touches
/// each face of its box, so along the axis `d` where the box spans most of `n`, some point of the
/// piece reaches the box's extreme; the box's corner goes beyond that point only along the
/// other axes: at most `sum_{i != d} |n_i| (hi_i - lo_i)`. Zero for a plane along the grid.
#[inline(always)]
fn box_overshoot(n: Vec3A, piece: &Local) -> f32 {
    let spans = n.abs() * (piece.hi - piece.lo);
    spans.element_sum() - spans.max_element()
}

/// `p_c - p_r` in voxel units, exact in the integer part.
#[inline(always)]
fn offset(r: &Local, c: &Local) -> Vec3A {
    voxel_offset(r, c) + (c.point - r.point)
}

/// `c.voxel - r.voxel` as floats: the integers subtracted, then converted, lane by lane.
#[inline(always)]
fn voxel_offset(r: &Local, c: &Local) -> Vec3A {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{__m128i, _mm_cvtepi32_ps, _mm_loadu_si128, _mm_sub_epi32};
        const { assert!(std::mem::offset_of!(Local, voxel) == 0) };
        const { assert!(std::mem::offset_of!(Local, group) == 12) };
        // SAFETY: the first 16 bytes of a `Local` are its voxel and its group (asserted
        // above); SSE2 is part of x86-64. The fourth lane, the groups' difference, is never
        // read by `Vec3A`. Coordinates are below 2^21, so the subtraction does not wrap, and
        // each lane converts exactly as `(a - b) as f32` does.
        unsafe {
            let a = _mm_loadu_si128(c as *const Local as *const __m128i);
            let b = _mm_loadu_si128(r as *const Local as *const __m128i);
            Vec3A::from(_mm_cvtepi32_ps(_mm_sub_epi32(a, b)))
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    Vec3A::new(
        (c.voxel[0] - r.voxel[0]) as f32,
        (c.voxel[1] - r.voxel[1]) as f32,
        (c.voxel[2] - r.voxel[2]) as f32,
    )
}

/// How far the candidate's piece reaches along `v` beyond the receiver's point: the largest
/// `v . (y - p_receiver)` over the corners `y` of the piece's bounding box.
#[inline(always)]
fn reach(v: Vec3A, receiver: &Local, candidate: &Local) -> f32 {
    let (a, b) = (v * candidate.lo, v * candidate.hi);
    v.dot(offset(receiver, candidate) - candidate.point) + a.max(b).element_sum()
}

/// Whether `r` (behind) and `c` (ahead along the direction) light each other; `RECEIVER_BEHIND`
/// tells which of the two is the receiver. The ray from the receiver's point must cross the
/// candidate's plane ahead, and some of the candidate's piece must lie in front of the receiver's
/// side (the piece's bounding box, not just its centroid, so that a piece running past the
/// receiver's plane, as at a T-junction, still counts). Returns the distance from the receiver's
/// point to the candidate's plane along the search direction.
#[inline(always)]
fn facing<const RECEIVER_BEHIND: bool>(r: &Local, c: &Local) -> Option<f32> {
    if r.group == c.group || r.ns == 0.0 || c.ns == 0.0 {
        return None;
    }
    let d = offset(r, c);
    let (rd, cd) = (r.normal.dot(d), c.normal.dot(d));
    // In one voxel the bounding box says too little: the box of a piece tilted in its own plane
    // (a slab's end face under its tilted top) reaches past the receiver's plane even where the
    // piece stops at it, so a voxel-mate must also have its surface point in front.
    let mate = r.voxel == c.voxel;
    if RECEIVER_BEHIND {
        // Crossing ahead: the receiver r lies in front of c's side facing it.
        let front = r.normal * r.sgn;
        if cd * c.sgn <= EPS || reach(front, r, c) <= EPS || mate && front.dot(d) <= EPS {
            return None;
        }
        Some(cd / c.ns)
    } else {
        let front = -c.normal * c.sgn;
        if rd * r.sgn <= EPS || reach(front, c, r) <= EPS || mate && front.dot(-d) <= EPS {
            return None;
        }
        Some(rd / r.ns)
    }
}

/// `x.floor() as i32`, exactly (saturating, 0 for NaN), without the call to `floorf` that
/// `f32::floor` compiles to on x86-64 without SSE 4.1.
#[inline(always)]
fn floor_to_i32(x: f32) -> i32 {
    let t = x as i32;
    // `t as f32` is exact: either |x| < 2^24 (and so is t), or x is an integer or out of range,
    // where `t` is x itself or saturated and `x < t` is false, except below i32::MIN.
    t.saturating_sub((x < t as f32) as i32)
}

/// The side of a surfel that faces along the direction, given `normal . s`.
#[inline(always)]
fn side_along(ns: f32) -> usize {
    if ns > 0.0 {
        FRONT
    } else {
        BACK
    }
}

/// Per-direction inputs of propagation.
pub struct DirectionInput<'a> {
    /// Unit vector of the line direction.
    pub unit: DVec3,
    /// `W(s) / pi`.
    pub weight: f64,
    pub surfels: &'a [PropSurfel],
    /// Radiosity of the previous iteration, by surfel, side and channel.
    pub radiosity: &'a [[[f32; 3]; 2]],
    /// Channels to gather (1 for a grey scene, whose channels are equal; else 3).
    pub channels: usize,
}

/// Reusable per-thread buffers for one line at a time.
#[derive(Default)]
pub struct LineScratch {
    locals: Vec<Local>,
    /// Start position of each voxel group, then the line length.
    groups: Vec<usize>,
    /// For each voxel group: the plane group if the voxel holds a single surfel, else `u32::MAX`.
    single: Vec<u32>,
    /// For each voxel group: the first voxel group after its run of equal `single` values, and
    /// the last one before it.
    run_after: Vec<u32>,
    run_before: Vec<u32>,
    /// For each line position: the positions of the partner ahead and behind (`u32::MAX`: none).
    pub partners: Vec<[(u32, f32); 2]>,
    /// Further partners of chains longer than one (rare: rays past open edges), as
    /// (line position, 0 ahead / 1 behind, partner position, weight).
    pub extra: Vec<(u32, u8, u32, f32)>,
    /// Open crossings of this line: for each plane group with an open-edge piece on the line,
    /// its range in `open_items`.
    open_ranges: Vec<(u32, u32, u32)>,
    /// The surfels of the open crossings, group after group in line order: (voxel group, line
    /// position, sum of the shares of the group's surfels up to and including this one).
    open_items: Vec<(u32, u32, f32)>,
    /// For each line position: the index of its open crossing in `open_ranges`, or `u32::MAX`.
    open_slot: Vec<u32>,
}

/// What [`PropSurfel::mate_sides`] keeps of [`side_of`]: not kept, in front, behind, or
/// running through the mate's plane.
const SIDE_UNKNOWN: u8 = 0;
const SIDE_FRONT: u8 = 1;
const SIDE_BEHIND: u8 = 2;
const SIDE_THROUGH: u8 = 3;

/// Longest chain of partners one search may return.
pub const MAX_CHAIN: usize = 4;

/// The partners one search found: line positions with the share of the light each sends. A ray
/// that meets the open edge of a surface (a piece covering part of its voxel) takes that piece's
/// coverage from it and goes on to what lies behind with the rest; every other hit ends it.
#[derive(Clone, Copy, Debug, Default)]
pub struct Chain {
    pub len: u8,
    pub items: [(u32, f32); MAX_CHAIN],
}

impl Chain {
    fn push(&mut self, position: usize, weight: f32) {
        if (self.len as usize) < MAX_CHAIN {
            self.items[self.len as usize] = (position as u32, weight);
            self.len += 1;
        }
    }

    /// The partners and their weights.
    pub fn iter(&self) -> impl Iterator<Item = (u32, f32)> + '_ {
        self.items[..self.len as usize].iter().copied()
    }
}

/// Finds the partners of every surfel of one line (surfel indices in order along `s`); the result
/// is in `scratch.partners`, by line position.
pub fn find_partners(line: &[u32], surfels: &[PropSurfel], s: DVec3, scratch: &mut LineScratch) {
    find_partners_toward(line, surfels, s, scratch, None);
}

/// Which searches of a line [`find_partners_toward`] runs: those whose partner may be wanted.
/// A search ahead walks only its own voxel and the voxels after it, a search behind its own and
/// those before it, so a partner at some line position can only be found by the searches ahead
/// from its voxel and before, and behind from its voxel and after.
#[derive(Clone, Copy, Debug, Default)]
pub struct Toward<'a> {
    /// Search ahead from the positions up to this position's voxel (none: no such prefix).
    pub ahead_upto: Option<usize>,
    /// Search behind from the positions from this position's voxel on (none: no such suffix).
    pub behind_from: Option<usize>,
    /// Further positions searched ahead, and behind, in ascending order.
    pub also_ahead: &'a [u32],
    pub also_behind: &'a [u32],
    /// By line position: whether links to that surfel are the ones wanted (the direct pass's
    /// emitters). When given, a search from the spans above that cannot reach the plane of any
    /// target is not run ([`crosses_a_target`]); the searches of `also_ahead` and `also_behind`
    /// always run. Empty: every search of the spans runs.
    pub targets: &'a [bool],
}

impl Toward<'_> {
    /// Every search that may find a partner at a position `first..=last` (or in their voxels).
    pub fn span(first: usize, last: usize) -> Self {
        Toward {
            ahead_upto: Some(last),
            behind_from: Some(first),
            ..Toward::default()
        }
    }
}

/// As [`find_partners`], searching only as `toward` asks (every search when `None`); the other
/// searches find nothing. The direct-light pass needs only the links from its emitters' emitting
/// sides, and its emitters' own searches (`solve::direct`).
pub fn find_partners_toward(
    line: &[u32],
    surfels: &[PropSurfel],
    s: DVec3,
    scratch: &mut LineScratch,
    toward: Option<Toward>,
) {
    search_line(line, surfels, s, scratch, toward, true);
}

/// [`find_partners_toward`]; without `plain`, every line takes the general search
/// (`LineView::nearest`), which the tests hold the plain lines' searches to.
#[inline(always)]
fn search_line(
    line: &[u32],
    surfels: &[PropSurfel],
    s: DVec3,
    scratch: &mut LineScratch,
    toward: Option<Toward>,
    plain: bool,
) {
    let sf = Vec3A::from(s.as_vec3());
    // The line's cross-section across the direction, in voxel-size squared: a line is a tube of
    // unit section across its main axis.
    let section = sf.abs().max_element();
    let LineScratch {
        locals,
        groups,
        single,
        run_after,
        run_before,
        partners,
        extra,
        open_ranges,
        open_items,
        open_slot,
    } = scratch;
    locals.clear();
    locals.extend(line.iter().map(|&m| local_of(&surfels[m as usize], sf)));
    let main = {
        let a = sf.abs();
        if a.x >= a.y && a.x >= a.z {
            0
        } else if a.y >= a.z {
            1
        } else {
            2
        }
    };
    if plain && plain_partners(locals, sf, main, toward, run_after, run_before, partners) {
        extra.clear();
        return;
    }
    groups.clear();
    for k in 0..locals.len() {
        if k == 0 || locals[k].voxel != locals[k - 1].voxel {
            groups.push(k);
        }
    }
    groups.push(locals.len());
    let group_count = groups.len() - 1;
    // Most lines hold one surfel per voxel: then no voxel has mates, and no run of a plane ends
    // at a voxel-mate (`LineView::off_the_run`).
    let shared = group_count < locals.len();
    open_crossings(locals, groups, section, open_ranges, open_items, open_slot);
    single.clear();
    single.extend((0..group_count).map(|g| {
        if groups[g + 1] - groups[g] == 1 {
            locals[groups[g]].group
        } else {
            u32::MAX
        }
    }));
    run_after.clear();
    run_after.resize(group_count, 0);
    run_before.clear();
    run_before.resize(group_count, 0);
    for g in 0..group_count {
        let r = group_count - 1 - g;
        run_after[r] = if r + 1 < group_count && single[r] != u32::MAX && single[r + 1] == single[r]
        {
            run_after[r + 1]
        } else {
            r as u32 + 1
        };
        run_before[g] = if g > 0 && single[g] != u32::MAX && single[g - 1] == single[g] {
            run_before[g - 1]
        } else {
            g as u32
        };
    }
    partners.clear();
    extra.clear();
    let view = LineView {
        locals,
        groups,
        single,
        run_after,
        run_before,
        open_ranges,
        open_items,
        open_slot,
        shared,
        main,
    };
    // The voxel groups whose searches ahead and behind may be needed.
    let group_of = |k: usize| groups.partition_point(|&start| start <= k) - 1;
    let (ahead_to, behind_from, also_ahead, also_behind) = match toward {
        None => (group_count, 0, &[][..], &[][..]),
        Some(t) => (
            t.ahead_upto.map_or(0, |last| group_of(last) + 1),
            t.behind_from.map_or(group_count, group_of),
            t.also_ahead,
            t.also_behind,
        ),
    };
    let also = |list: &[u32], k: usize| !list.is_empty() && list.binary_search(&(k as u32)).is_ok();
    let targets = toward.map_or(&[][..], |t| t.targets);
    // Whether the search of position `k` (voxel group `g`) ahead, or behind, is wanted.
    let wanted_ahead = |g: usize, k: usize| {
        also(also_ahead, k)
            || g < ahead_to
                && (targets.is_empty()
                    || crosses_a_target::<true>(locals, targets, groups[g]..locals.len(), k))
    };
    let wanted_behind = |g: usize, k: usize| {
        also(also_behind, k)
            || g >= behind_from
                && (targets.is_empty()
                    || crosses_a_target::<false>(locals, targets, 0..groups[g + 1], k))
    };
    if plain && !shared && open_ranges.is_empty() {
        // The common line: one surfel per voxel and no open edge (see `LineView::nearest_plain`).
        let none = (u32::MAX, 0.0);
        partners.extend((0..locals.len()).map(|k| {
            [
                if wanted_ahead(k, k) {
                    view.nearest_plain::<true>(k, sf)
                } else {
                    none
                },
                if wanted_behind(k, k) {
                    view.nearest_plain::<false>(k, -sf)
                } else {
                    none
                },
            ]
        }));
        return;
    }
    let (mut ahead, mut behind) = (Chain::default(), Chain::default());
    let every = toward.is_none();
    for g in 0..group_count {
        for k in groups[g]..groups[g + 1] {
            // The chains are filled in place: returned by value, each was copied through the
            // stack with wide loads of narrower stores just written (a store-forwarding stall
            // that cost a tenth of the search).
            // Every search is wanted without `toward` (the closures' tests were 1.5 % of the
            // instructions of a first pass).
            if every || wanted_ahead(g, k) {
                view.nearest::<true>(g, k, sf, &mut ahead);
            } else {
                ahead.len = 0;
            }
            if every || wanted_behind(g, k) {
                view.nearest::<false>(g, k, -sf, &mut behind);
            } else {
                behind.len = 0;
            }
            let first = |c: &Chain| {
                if c.len > 0 {
                    c.items[0]
                } else {
                    (u32::MAX, 0.0)
                }
            };
            partners.push([first(&ahead), first(&behind)]);
            for (which, chain) in [&ahead, &behind].into_iter().enumerate() {
                for &(position, weight) in
                    &chain.items[1.min(chain.len as usize)..chain.len as usize]
                {
                    extra.push((k as u32, which as u8, position, weight));
                }
            }
        }
    }
}

/// The partners of every surfel of a plain line, one surfel per voxel and no open edge (the
/// common line: four in five surfels of the Cornell box lie on one), into `partners`; false,
/// with `partners` to be filled by the general search, when the line is not plain or a search
/// meets the side of a solid's face turned inside, which [`LineView::entry_face`] judges.
///
/// It finds what [`LineView::nearest_plain`] finds, without the line's voxel groups, the
/// planes they hold and its open crossings, which such a line does not need: the set-up of
/// those, for every line, took a fifth of the instructions of a first pass (counted with
/// callgrind on the Cornell box), about as many as this line's searches.
fn plain_partners(
    locals: &[Local],
    sf: Vec3A,
    main: usize,
    toward: Option<Toward>,
    run_after: &mut Vec<u32>,
    run_before: &mut Vec<u32>,
    partners: &mut Vec<[(u32, f32); 2]>,
) -> bool {
    let n = locals.len();
    // A voxel's surfels are adjacent on a line; `u32::MAX` is no plane (see `LineScratch::single`).
    let plain = (0..n).all(|k| {
        let l = &locals[k];
        l.coverage >= 1.0 && l.group != u32::MAX && (k == 0 || l.voxel != locals[k - 1].voxel)
    });
    if !plain {
        return false;
    }
    // Runs of one plane, as `LineScratch::run_after` and `run_before` (voxel groups are
    // positions here).
    run_before.clear();
    run_before.resize(n, 0);
    for g in 0..n {
        run_before[g] = if g > 0 && locals[g].group == locals[g - 1].group {
            run_before[g - 1]
        } else {
            g as u32
        };
    }
    run_after.clear();
    run_after.resize(n, 0);
    for r in (0..n).rev() {
        run_after[r] = if r + 1 < n && locals[r].group == locals[r + 1].group {
            run_after[r + 1]
        } else {
            r as u32 + 1
        };
    }
    partners.clear();
    let line = PlainLine {
        locals,
        run_after,
        run_before,
        main,
    };
    let none = Some((u32::MAX, 0.0));
    let Some(toward) = toward else {
        for k in 0..n {
            let (Some(ahead), Some(behind)) =
                (line.nearest::<true>(k, sf), line.nearest::<false>(k, -sf))
            else {
                return false;
            };
            partners.push([ahead, behind]);
        }
        return true;
    };
    // The searches `toward` asks for, as `find_partners_toward` picks them (voxel groups are
    // positions here).
    let ahead_to = toward.ahead_upto.map_or(0, |last| last + 1);
    let behind_from = toward.behind_from.unwrap_or(n);
    let also = |list: &[u32], k: usize| !list.is_empty() && list.binary_search(&(k as u32)).is_ok();
    let targets = toward.targets;
    for k in 0..n {
        let wanted_ahead = also(toward.also_ahead, k)
            || k < ahead_to
                && (targets.is_empty() || crosses_a_target::<true>(locals, targets, k..n, k));
        let wanted_behind = also(toward.also_behind, k)
            || k >= behind_from
                && (targets.is_empty() || crosses_a_target::<false>(locals, targets, 0..k + 1, k));
        let ahead = if wanted_ahead {
            line.nearest::<true>(k, sf)
        } else {
            none
        };
        let behind = if wanted_behind {
            line.nearest::<false>(k, -sf)
        } else {
            none
        };
        let (Some(ahead), Some(behind)) = (ahead, behind) else {
            return false;
        };
        partners.push([ahead, behind]);
    }
    true
}

/// The next candidate that a search on a plain line (one surfel per voxel, no open edge) from
/// receiver `x` accepts past line position `from`, ahead (`FORWARD`) or behind, with the
/// acceptance test's distance; runs of the receiver's own plane are jumped over. `None`: the
/// line ends first.
#[inline(always)]
fn next_accepted<const FORWARD: bool>(
    locals: &[Local],
    run_after: &[u32],
    run_before: &[u32],
    x: &Local,
    from: usize,
) -> Option<(usize, f32)> {
    let mut g2 = from;
    loop {
        if FORWARD {
            g2 += 1;
            if g2 >= locals.len() {
                return None;
            }
        } else {
            if g2 == 0 {
                return None;
            }
            g2 -= 1;
        }
        let candidate = &locals[g2];
        if candidate.group == x.group {
            g2 = if FORWARD {
                run_after[g2] as usize - 1
            } else {
                run_before[g2] as usize
            };
            continue;
        }
        if let Some(t) = LineView::test::<FORWARD>(x, candidate) {
            return Some((g2, t));
        }
    }
}

/// A plain line as [`plain_partners`] searches it.
struct PlainLine<'a> {
    locals: &'a [Local],
    run_after: &'a [u32],
    run_before: &'a [u32],
    main: usize,
}

impl PlainLine<'_> {
    /// [`LineView::nearest_plain`] on this line: the partner's position and share,
    /// `(u32::MAX, 0.0)` for none; `None` when the hit is a side inside a solid met from
    /// behind (left to [`LineView::entry_face`]).
    #[inline(always)]
    fn nearest<const FORWARD: bool>(&self, k: usize, dir: Vec3A) -> Option<(u32, f32)> {
        let locals = self.locals;
        let x = &locals[k];
        let none = Some((u32::MAX, 0.0));
        if x.ns == 0.0 || gathers_inside::<FORWARD>(x) {
            return none;
        }
        let Some((g2, t)) = next_accepted::<FORWARD>(locals, self.run_after, self.run_before, x, k)
        else {
            return none;
        };
        let hit = self.where_crossed::<FORWARD>(x, g2, t, dir);
        let h = &locals[hit];
        let from_back = if FORWARD { h.ns > 0.0 } else { h.ns < 0.0 };
        // Met from behind, a side inside a solid is `entry_face`'s to judge.
        (!(h.inside_back && from_back)).then_some((hit as u32, 1.0))
    }

    /// [`LineView::where_crossed`] on this line, where each voxel holds one piece.
    #[inline(always)]
    fn where_crossed<const FORWARD: bool>(&self, x: &Local, c: usize, t: f32, dir: Vec3A) -> usize {
        let locals = self.locals;
        if locals[c].voxel == x.voxel {
            return c;
        }
        let plane = locals[c].group;
        let main = self.main;
        let at = crossing_group::<FORWARD>(
            (x, t, dir, main),
            c,
            locals.len(),
            |g| locals[g].group == plane,
            |g| locals[g].voxel[main],
        );
        if at == c || LineView::test::<FORWARD>(x, &locals[at]).is_none() {
            c
        } else {
            at
        }
    }
}

/// Whether the ray of line position `k`, searching ahead (`FORWARD`) or behind, crosses the
/// plane of some target at the line positions `walked`, those of the voxels that search walks
/// (from its own voxel's first surfel to the line's end, or from the start to its own voxel's
/// last). Every partner a search returns (the piece it accepts, the piece of the same plane
/// where the ray crosses it, an open sheet's piece before it) lies on a plane one of whose pieces
/// passed the acceptance test ([`facing`]), whose first condition is that the ray crosses that plane ahead of the
/// receiver; the pieces of a plane group share its plane (to rounding, hence the margin). So a
/// search whose ray crosses no target's plane cannot return a target.
///
/// In the direct pass most searches of a line are from surfels the lamp cannot light along the
/// line (the housing's top and sides beside a lamp, the surfaces above a lamp that emits
/// downwards): this leaves them out, the same links from emitters being found.
#[inline]
fn crosses_a_target<const FORWARD: bool>(
    locals: &[Local],
    targets: &[bool],
    walked: std::ops::Range<usize>,
    k: usize,
) -> bool {
    const MARGIN: f32 = 1e-3;
    let x = &locals[k];
    if x.ns == 0.0 {
        // No search from a surfel along its own plane finds anything.
        return false;
    }
    walked.into_iter().any(|t| {
        let c = &locals[t];
        if !targets[t] || c.group == x.group || c.ns == 0.0 {
            return false;
        }
        let d = if FORWARD { offset(x, c) } else { offset(c, x) };
        c.normal.dot(d) * c.sgn > EPS - MARGIN
    })
}

/// Area (voxel-size squared) of a surfel's piece of an open sheet, from its coverage of its
/// voxel's slice of its plane (`solve::coverage`; 1 for a piece that fills the slice). The
/// slice is 1 for a plane along the grid axes; others are clipped to the voxel here, on the few
/// lines that meet an open edge.
fn piece_area(l: &Local) -> f32 {
    let n = l.normal;
    let axis_aligned = n.abs().max_element() > 1.0 - 1e-6;
    let slice = if axis_aligned {
        1.0
    } else {
        crate::solve::coverage::slice_area(n.as_dvec3(), l.point.as_dvec3()) as f32
    };
    l.coverage.clamp(0.0, 1.0) * slice
}

/// Finds the line's open crossings: the plane groups that have an open-edge piece (coverage
/// below 1) on this line, with the running sums of their surfels' shares (see [`LineView::nearest`]).
/// Most lines have none, and then this only scans the coverages.
fn open_crossings(
    locals: &[Local],
    groups: &[usize],
    section: f32,
    open_ranges: &mut Vec<(u32, u32, u32)>,
    open_items: &mut Vec<(u32, u32, f32)>,
    open_slot: &mut Vec<u32>,
) {
    open_ranges.clear();
    open_items.clear();
    open_slot.clear();
    if locals.iter().all(|l| l.coverage >= 1.0) {
        return;
    }
    for l in locals {
        if l.coverage < 1.0 && !open_ranges.iter().any(|r| r.0 == l.group) {
            open_ranges.push((l.group, 0, 0));
        }
    }
    open_slot.resize(locals.len(), u32::MAX);
    for (slot, range) in open_ranges.iter_mut().enumerate() {
        range.1 = open_items.len() as u32;
        let mut sum = 0.0f32;
        for g in 0..groups.len() - 1 {
            // A plane held twice in one voxel (a sheet modelled back to back) blocks the line
            // once: its copies cover the same part of it.
            let (mut here, mut at) = (0.0f32, 0);
            for k in groups[g]..groups[g + 1] {
                if locals[k].group == range.0 {
                    let share = piece_area(&locals[k]) * locals[k].ns.abs() / section;
                    if share > here {
                        (here, at) = (share, k);
                    }
                    open_slot[k] = slot as u32;
                }
            }
            if here > 0.0 {
                sum += here;
                open_items.push((g as u32, at as u32, sum));
            }
        }
        range.2 = open_items.len() as u32;
    }
}

/// What a search that met a plane ends with ([`LineView::entry_face`]).
enum Entry {
    /// This line position is the partner.
    Hit(usize),
    /// The ray passed by a closed solid, beside the face whose plane it crossed: go on.
    PassedBy,
}

/// Distance (voxel units) along the ray within which a side inside a solid is taken as met
/// from within the solid ([`LineView::entry_face`]).
const NEAR_START: f32 = 1.0;

/// How far (voxel units) outside a piece's bounding box a crossing of its plane must lie for a
/// ray that met the piece's side inside a solid to count as having passed by the solid.
const PASSED_BY: f32 = 1e-3;

/// The plane of the last open edge a search took a share from. Open pieces of parallel planes
/// in one layer of voxels usually do not overlap (a lamp set in an opening of the ceiling, its
/// rim beside the opening's): their shares add up, where pieces of planes at an angle are
/// crossed one after the other and each takes its share of what the ones before let through.
#[derive(Default)]
struct OpenLayer {
    normal: Option<Vec3A>,
}

impl OpenLayer {
    /// Pushes the partner at line position `at` with `share` of the section, and updates `left`.
    #[inline(always)]
    fn take(&mut self, chain: &mut Chain, left: &mut f32, at: usize, share: f32, normal: Vec3A) {
        let parallel = self
            .normal
            .is_some_and(|n| n.dot(normal).abs() > 1.0 - 1e-4);
        if parallel {
            let part = share.min(*left);
            chain.push(at, part);
            *left -= part;
        } else {
            chain.push(at, *left * share);
            *left *= 1.0 - share;
        }
        self.normal = Some(normal);
    }
}

/// Plane groups a search has found to be crossed off their pieces (a few at most; more are
/// dropped, which only costs exactness in pathological clutter).
#[derive(Default)]
struct Missed {
    groups: [u32; 4],
    len: usize,
}

impl Missed {
    #[inline(always)]
    fn contains(&self, group: u32) -> bool {
        self.groups[..self.len].contains(&group)
    }

    /// Whether one more plane can be remembered.
    #[inline(always)]
    fn has_room(&self) -> bool {
        self.len < self.groups.len()
    }

    #[inline(always)]
    fn insert(&mut self, group: u32) {
        if self.len < self.groups.len() && !self.contains(group) {
            self.groups[self.len] = group;
            self.len += 1;
        }
    }
}

/// Where along a plane's run [`LineView::where_crossed`] takes the crossing of the ray from
/// receiver `x` that meets the plane at distance `t` along `dir` (`main` the line's main axis):
/// walking from the candidate's voxel group `g_c` along the search (the search met nothing of
/// the plane before it), one layer at a time towards the crossing's, while the next voxel group
/// holds the plane alone (`alone`; a voxel holding another surface too, a wall standing on the
/// floor, may block the ray before the plane beyond: only the search's own tests there can
/// tell) and lies in the next layer (`coordinate`: a group's main-axis coordinate; a gap ends
/// the walk too). The walk is the same whichever way the line is listed, so the out-of-core
/// solver, which lists some lines the other way, finds the same partner.
#[inline(always)]
fn crossing_group<const FORWARD: bool>(
    (x, t, dir, main): (&Local, f32, Vec3A, usize),
    g_c: usize,
    group_count: usize,
    alone: impl Fn(usize) -> bool,
    coordinate: impl Fn(usize) -> i32,
) -> usize {
    // Most hits are on a plane whose run ends at the candidate's voxel: the walk would stop
    // there whatever the crossing's layer, so that layer is not computed.
    let next = if FORWARD {
        g_c + 1
    } else {
        g_c.wrapping_sub(1)
    };
    if next >= group_count || !alone(next) {
        return g_c;
    }
    let layer = floor_to_i32(x.voxel[main] as f32 + x.point[main] + dir[main] * t);
    let mut at = g_c;
    loop {
        let here = coordinate(at);
        if here == layer {
            break;
        }
        let next = if FORWARD {
            at + 1
        } else if at == 0 {
            break;
        } else {
            at - 1
        };
        if next >= group_count || !alone(next) {
            break;
        }
        let there = coordinate(next);
        // Towards the crossing's layer, by one layer.
        if (there - here).abs() != 1 || (layer - there).abs() >= (layer - here).abs() {
            break;
        }
        at = next;
    }
    at
}

/// One line of one direction, with its voxel groups and same-plane runs.
#[derive(Clone, Copy)]
struct LineView<'a> {
    locals: &'a [Local],
    groups: &'a [usize],
    single: &'a [u32],
    run_after: &'a [u32],
    run_before: &'a [u32],
    open_ranges: &'a [(u32, u32, u32)],
    open_items: &'a [(u32, u32, f32)],
    open_slot: &'a [u32],
    /// Whether some voxel of the line holds more than one surfel (else `runs` is empty).
    shared: bool,
    /// The line's main axis (the largest component of the direction).
    main: usize,
}

impl LineView<'_> {
    /// [`side_of`] for two surfels of one voxel at line positions `mate` and `piece`: kept
    /// with the piece where the mate is among the first [`RANKED_MATES`] of the voxel, else
    /// computed. Every receiver whose search reaches the voxel asks it again, along every
    /// direction (a voxel of a building's thin walls and floors holds two to a dozen surfels;
    /// computing it was a sixth of the search there, and caching it per line still a tenth).
    #[inline(always)]
    fn mate_side(&self, mate: usize, piece: usize) -> Option<f32> {
        let rank = self.locals[mate].rank as usize;
        let code = if rank < RANKED_MATES {
            (self.locals[piece].mate_sides >> (2 * rank) & 3) as u8
        } else {
            SIDE_UNKNOWN
        };
        match code {
            SIDE_FRONT => Some(1.0),
            SIDE_BEHIND => Some(-1.0),
            SIDE_THROUGH => None,
            _ => side_of(&self.locals[mate], &self.locals[piece]),
        }
    }

    /// The surfel of candidate `c`'s plane where the ray from receiver `x`, which meets the
    /// plane at distance `t`, crosses it: the piece in the voxel of the plane's run on this line
    /// whose layer along the main axis holds the crossing point (the nearest end of the run if
    /// none does). Along a grazing line a plane's run is many voxels long, and its surfels
    /// differ: a lamp that fills an opening of the ceiling is the ceiling's plane, and the
    /// run's first voxel, which the search meets first, took every ray that crosses the plane
    /// in the lamp (in a box lit so, no wall's ray met the lamp within 6 degrees of the
    /// ceiling's plane, and a third of what it sent at 10 to 17 degrees).
    #[inline(always)]
    fn where_crossed<const FORWARD: bool>(
        &self,
        x: &Local,
        c: usize,
        g_c: usize,
        t: f32,
        dir: Vec3A,
    ) -> usize {
        // A voxel-mate of the receiver (the other wall at a corner) is met where the two meet.
        if self.locals[c].voxel == x.voxel {
            return c;
        }
        let plane = self.locals[c].group;
        let main = self.main;
        let at = crossing_group::<FORWARD>(
            (x, t, dir, main),
            g_c,
            self.groups.len() - 1,
            |g| self.single[g] == plane,
            |g| self.locals[self.groups[g]].voxel[main],
        );
        if at == g_c {
            return c;
        }
        // A plane held twice there (two coincident pieces facing opposite ways): the piece
        // whose front faces the receiver, as in `best_in`.
        let mut chosen: Option<usize> = None;
        for k in self.groups[at]..self.groups[at + 1] {
            let piece = &self.locals[k];
            if piece.group != plane || Self::test::<FORWARD>(x, piece).is_none() {
                continue;
            }
            if chosen.is_none() || piece.normal.dot(dir) < 0.0 {
                chosen = Some(k);
            }
        }
        chosen.unwrap_or(c)
    }

    /// The run of line position `c`'s plane on the line (`g` its voxel group): the first and
    /// last of the consecutive voxel groups around `g` that hold a piece of the plane. Found
    /// when a search asks (a few times a line) rather than for every position of every line:
    /// the direct-light pass runs only some searches of its long lines, and this was 6 % of it.
    #[inline(always)]
    fn run_of(&self, c: usize, g: usize) -> [u32; 2] {
        let plane = self.locals[c].group;
        let holds =
            |g: usize| (self.groups[g]..self.groups[g + 1]).any(|k| self.locals[k].group == plane);
        let (mut lo, mut hi) = (g, g);
        while lo > 0 && holds(lo - 1) {
            lo -= 1;
        }
        while hi + 2 < self.groups.len() && holds(hi + 1) {
            hi += 1;
        }
        [lo as u32, hi as u32]
    }

    /// Whether the ray from receiver `x`, which meets the plane of candidate `c` at distance `t`,
    /// crosses that plane off its pieces on this line: beyond the edge where the plane's run of
    /// voxels ends at a voxel-mate bounding it (a lamp's end under its housing's end face). The
    /// run's voxels away from its ends hold the plane alone, so a grazing ray that reaches one of
    /// them would otherwise be caught there though it crosses the plane past the edge; each end
    /// is judged like a voxel-mate in [`LineView::best_in`], and the candidate's own voxel is
    /// judged there already.
    #[inline(always)]
    fn off_the_run(&self, x: &Local, c: usize, g_c: usize, t: f32, dir: Vec3A) -> bool {
        if !self.shared {
            // No run end holds mates.
            return false;
        }
        let plane = self.locals[c].group;
        // Most hits are on a plane the line crosses in one voxel (a wall seen across a room):
        // then both ends are the candidate's own voxel, judged in `best_in` already.
        let holds =
            |g: usize| (self.groups[g]..self.groups[g + 1]).any(|k| self.locals[k].group == plane);
        if !(g_c > 0 && holds(g_c - 1) || g_c + 2 < self.groups.len() && holds(g_c + 1)) {
            return false;
        }
        let own = self.run_of(c, g_c);
        let here = self.locals[c].voxel;
        for end in [own[0], own[1]] {
            let range = self.groups[end as usize]..self.groups[end as usize + 1];
            if range.len() < 2 || self.locals[range.start].voxel == here {
                continue;
            }
            // The plane may hold several pieces here (a ceiling and the top of a wall pressed
            // against it): the ray is off the run's end only if it is off every one of them.
            let mut pieces = range
                .clone()
                .filter(|&k| self.locals[k].group == plane)
                .peekable();
            if pieces.peek().is_none() {
                continue;
            }
            let candidate = &self.locals[c];
            let on_some = pieces.any(|at| {
                let piece = &self.locals[at];
                range.clone().all(|k| {
                    let mate = &self.locals[k];
                    if mate.group == plane || mate.group == x.group {
                        return true;
                    }
                    let n = mate.normal;
                    if n.dot(piece.normal).abs() > 1.0 - 1e-4 {
                        return true;
                    }
                    // A mate bounds the run only if the run's pieces lie on one side of it: the
                    // candidate's piece, where the ray was caught, on the same side as the end's
                    // (a wall pressed up against a ceiling, its face on the voxel boundary, does
                    // not end the ceiling that goes on over it).
                    let Some(piece_side) = self.mate_side(k, at) else {
                        return true;
                    };
                    if side_of(mate, candidate) != Some(piece_side) {
                        return true;
                    }
                    let q = dir * t - offset(x, mate);
                    n.dot(q) * piece_side >= -EPS
                })
            });
            if !on_some {
                return true;
            }
        }
        false
    }

    /// For a candidate at line position `c` whose plane has an open edge on this line: the share
    /// of the line's cross-section its plane's pieces block on the search's side of voxel group
    /// `g` (capped at 1), else `None` (the candidate blocks the whole line).
    #[inline(always)]
    fn open_share<const FORWARD: bool>(&self, g: usize, c: usize) -> Option<f32> {
        let slot = *self.open_slot.get(c)?;
        if slot == u32::MAX {
            return None;
        }
        self.open_crossing_share::<FORWARD>(g, slot as usize)
            .map(|(share, _)| share)
    }

    /// The share of open crossing `slot` on the search's side of voxel group `g`, if below 1,
    /// with the line position of its piece nearest to `g` on that side.
    #[inline(always)]
    fn open_crossing_share<const FORWARD: bool>(
        &self,
        g: usize,
        slot: usize,
    ) -> Option<(f32, usize)> {
        let (_, start, end) = self.open_ranges[slot];
        let items = &self.open_items[start as usize..end as usize];
        let total = items.last().map_or(0.0, |i| i.2);
        // Items before the first one in voxel group `g` or later.
        let split = items.partition_point(|i| (i.0 as usize) < g);
        let before = if split == 0 { 0.0 } else { items[split - 1].2 };
        // Items up to the last one in voxel group `g` or earlier.
        let upto = items.partition_point(|i| (i.0 as usize) <= g);
        let through = if upto == 0 { 0.0 } else { items[upto - 1].2 };
        let (share, nearest) = if FORWARD {
            (total - before, items.get(split))
        } else {
            (through, upto.checked_sub(1).map(|u| &items[u]))
        };
        let nearest = nearest?.1 as usize;
        (share < 1.0 - 1e-4).then_some((share.max(0.0), nearest))
    }

    /// Before a full hit on the piece at line position `hit` (voxel group `g_hit`, distance
    /// `t_hit`): an open sheet hung less than a voxel in front of the hit surface and parallel
    /// to it (a lamp just under a ceiling), whose pieces lie in the hit surface's run of voxels
    /// on this line, is crossed first by the receiver's ray, though a grazing line meets the
    /// surface's first voxel before the sheet's. Such sheets send their shares first, nearest
    /// first, and `left` shrinks.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn open_before_hit<const FORWARD: bool>(
        &self,
        g: usize,
        x: &Local,
        hit: usize,
        g_hit: usize,
        t_hit: f32,
        missed: &mut Missed,
        layer: &mut OpenLayer,
        chain: &mut Chain,
        left: &mut f32,
    ) {
        if self.open_ranges.is_empty() {
            return;
        }
        let surface = &self.locals[hit];
        // The hit surface's run on this line: voxel groups from `g_hit` on (along the search)
        // that hold a piece of its plane.
        let holds = |v: usize| {
            (self.groups[v]..self.groups[v + 1]).any(|c| self.locals[c].group == surface.group)
        };
        let group_count = self.groups.len() - 1;
        let mut run_end = g_hit;
        loop {
            let next = if FORWARD {
                run_end + 1
            } else {
                run_end.wrapping_sub(1)
            };
            if next >= group_count || !holds(next) {
                break;
            }
            run_end = next;
        }
        let (run_lo, run_hi) = if FORWARD {
            (g_hit, run_end)
        } else {
            (run_end, g_hit)
        };
        let mut earlier: [(f32, usize, f32, u32); MAX_CHAIN] = [(0.0, 0, 0.0, 0); MAX_CHAIN];
        let mut count = 0;
        for (slot, &(group, start, end)) in self.open_ranges.iter().enumerate() {
            if group == x.group || group == surface.group || missed.contains(group) {
                continue;
            }
            let items = &self.open_items[start as usize..end as usize];
            let Some(inside) = items
                .iter()
                .find(|i| (run_lo..=run_hi).contains(&(i.0 as usize)))
            else {
                continue;
            };
            let sheet = &self.locals[inside.1 as usize];
            let parallel = sheet.normal.dot(surface.normal).abs() > 1.0 - 1e-4;
            let gap = surface.normal.dot(offset(surface, sheet)).abs();
            if !parallel || gap >= 1.0 {
                continue;
            }
            let Some((share, at)) = self.open_crossing_share::<FORWARD>(g, slot) else {
                continue;
            };
            let Some(t) = Self::test::<FORWARD>(x, sheet) else {
                continue;
            };
            if t < t_hit - EPS && count + 1 < MAX_CHAIN - chain.len as usize && share > 0.0 {
                earlier[count] = (t, at, share, group);
                count += 1;
            }
        }
        let earlier = &mut earlier[..count];
        earlier.sort_by(|a, b| a.0.total_cmp(&b.0));
        for &(_, at, share, group) in earlier.iter() {
            layer.take(chain, left, at, share, self.locals[at].normal);
            missed.insert(group);
        }
    }

    /// The partner of a search from receiver `x` (voxel group `g`) whose ray met a plane at line
    /// position `hit`. A ray can reach a side inside a closed solid (`Local::inside_back`) only
    /// through the solid's surface, yet at the scale of the voxels a search may end on one:
    /// - it *entered through a face the search passed by*: a slab thinner than a voxel holds
    ///   both faces in one voxel, and a ray crossing the near face just off its piece is caught
    ///   on the far face's inner side. Its partner is that face: of the surfels from the
    ///   receiver's voxel group to the hit's that turn their front to the receiver and pass its
    ///   acceptance test no farther than the hit, the one crossed last;
    /// - it *passed by the solid*: a ray grazing a box's corner crosses a face's plane beyond the
    ///   face, where a voxel of the face's run catches it. Its crossing then lies outside the
    ///   hit piece's bounding box, and the search goes on past that plane ([`Entry::PassedBy`]);
    /// - otherwise, or within a voxel of the receiver, or from a receiver without area (either
    ///   may lie inside the solid itself: a face pressed against it), it stays on the hit, whose
    ///   side sends nothing.
    ///
    /// Before those sides went dark, they carried whatever such rays brought into them, which
    /// hid these rays in a furnace; dark, each would be light lost (0.6 % of the power of the
    /// thin-slab twin of `tests/hard_case_twins.rs`).
    #[inline(always)]
    fn entry_face<const FORWARD: bool>(
        &self,
        x: &Local,
        g: usize,
        hit: usize,
        dir: Vec3A,
    ) -> Entry {
        let h = &self.locals[hit];
        // The side of the hit facing back toward the receiver is its back side.
        let from_back = if FORWARD { h.ns > 0.0 } else { h.ns < 0.0 };
        if !(h.inside_back && from_back) {
            return Entry::Hit(hit);
        }
        self.entry_face_of::<FORWARD>(x, [g, hit], dir)
    }

    /// [`LineView::entry_face`] past its first test, for `[g, hit]` (kept out of line: rare).
    #[inline(never)]
    fn entry_face_of<const FORWARD: bool>(&self, x: &Local, at: [usize; 2], dir: Vec3A) -> Entry {
        let [g, hit] = at;
        let h = &self.locals[hit];
        let Some(t_hit) = Self::test::<FORWARD>(x, h) else {
            return Entry::Hit(hit);
        };
        // A ray that meets an inner side within a voxel of its start, or from a surfel without
        // area (a face wholly pressed against another solid), may have started inside the solid:
        // it stays.
        if t_hit <= NEAR_START || x.no_area {
            return Entry::Hit(hit);
        }
        let g_hit = self.groups.partition_point(|&start| start <= hit) - 1;
        let (lo, hi) = if FORWARD { (g, g_hit) } else { (g_hit, g) };
        let mut best: Option<(f32, usize)> = None;
        for q in self.groups[lo]..self.groups[hi + 1] {
            let c = &self.locals[q];
            if q == hit || c.group == x.group || c.group == h.group {
                continue;
            }
            // Its front turned to the receiver (a face of the solid seen from outside).
            let front_to_receiver = if FORWARD { c.ns < 0.0 } else { c.ns > 0.0 };
            if !front_to_receiver {
                continue;
            }
            let Some(t) = Self::test::<FORWARD>(x, c) else {
                continue;
            };
            if t > t_hit + EPS {
                continue;
            }
            // The last crossed; equal distances by plane group, then voxel: the same choice
            // whichever way the line is listed.
            let better = match best {
                None => true,
                Some((bt, bq)) => {
                    let b = &self.locals[bq];
                    t > bt || t == bt && (c.group, c.voxel) < (b.group, b.voxel)
                }
            };
            if better {
                best = Some((t, q));
            }
        }
        if let Some((_, q)) = best {
            return Entry::Hit(q);
        }
        // Where the ray crosses the hit's plane, in the hit's voxel units.
        let crossing = dir * t_hit - offset(x, h) + h.point;
        let margin = Vec3A::splat(PASSED_BY);
        if crossing.cmplt(h.lo - margin).any() || crossing.cmpgt(h.hi + margin).any() {
            Entry::PassedBy
        } else {
            Entry::Hit(hit)
        }
    }

    /// The acceptance test of candidate `c` for receiver `x`, looking ahead or behind: the distance
    /// from `x`'s point to `c`'s plane along the search direction.
    #[inline(always)]
    fn test<const FORWARD: bool>(x: &Local, c: &Local) -> Option<f32> {
        if FORWARD {
            facing::<true>(x, c)
        } else {
            facing::<false>(c, x)
        }
    }

    /// The accepted candidate of voxel group `g2` nearest to receiver `k`, if any (see `nearest`),
    /// with its distance (what the acceptance test returned for it). Planes whose crossing falls
    /// off their piece are added to `missed`.
    #[inline(always)]
    fn best_in<const FORWARD: bool>(
        &self,
        g2: usize,
        k: usize,
        dir: Vec3A,
        missed: &mut Missed,
    ) -> Option<(usize, f32)> {
        let locals = self.locals;
        let x = &locals[k];
        let range = self.groups[g2]..self.groups[g2 + 1];
        let mut best: Option<(f32, usize)> = None;
        // Planes crossed off / on their pieces in this voxel: a plane with two pieces here (two
        // facings) counts as missed only if neither piece was hit.
        let (mut off, mut on) = (Missed::default(), Missed::default());
        for k2 in range.clone() {
            if k2 == k {
                continue;
            }
            let c = &locals[k2];
            if missed.contains(c.group) {
                continue;
            }
            let Some(t) = Self::test::<FORWARD>(x, c) else {
                continue;
            };
            if let Some((bt, bk)) = best {
                // Two coincident surfels of one plane facing opposite ways: the one whose front
                // (the side its triangles face) faces the receiver wins.
                let tie = (t - bt).abs() <= EPS && locals[bk].group == c.group;
                let c_faces = c.normal.dot(dir) < 0.0;
                if !(t < bt - EPS || tie && c_faces && locals[bk].normal.dot(dir) >= 0.0) {
                    continue;
                }
            }
            let on_piece = range.clone().all(|k3| {
                let mate = &locals[k3];
                if k3 == k2 || k3 == k || mate.group == c.group {
                    return true;
                }
                // Which side of the mate's plane the candidate's piece lies on; a piece running
                // through the plane (a T-junction) is not bounded by it.
                let Some(piece_side) = self.mate_side(k3, k2) else {
                    return true;
                };
                let n = mate.normal;
                // Crossing point relative to the mate's point.
                let q = dir * t - offset(x, mate);
                n.dot(q) * piece_side >= -EPS
            });
            if on_piece {
                best = Some((t, k2));
                on.insert(c.group);
            } else {
                off.insert(c.group);
            }
        }
        for &group in &off.groups[..off.len] {
            if !on.contains(group) {
                missed.insert(group);
            }
        }
        best.map(|(t, k2)| (k2, t))
    }

    /// [`LineView::nearest`] on a line whose voxels hold one surfel each and that meets no open
    /// edge, where it reduces to this: no voxel has mates to search or to judge a run's end by
    /// (`off_the_run` is false), no plane is ever missed, and every hit ends the search with the
    /// whole ray. Returns the partner's line position and share, `(u32::MAX, 0.0)` for none, as
    /// the first item of `nearest`'s chain.
    #[inline(always)]
    fn nearest_plain<const FORWARD: bool>(&self, k: usize, dir: Vec3A) -> (u32, f32) {
        let x = &self.locals[k];
        if x.ns == 0.0 || gathers_inside::<FORWARD>(x) {
            return (u32::MAX, 0.0);
        }
        // Voxel groups are line positions here.
        let mut from = k;
        while let Some((g2, t)) =
            next_accepted::<FORWARD>(self.locals, self.run_after, self.run_before, x, from)
        {
            let hit = self.where_crossed::<FORWARD>(x, g2, g2, t, dir);
            match self.entry_face::<FORWARD>(x, k, hit, dir) {
                Entry::Hit(partner) => return (partner as u32, 1.0),
                // The ray passed by the solid: the next voxels of the plane's run are judged
                // alike, and the search goes on past them.
                Entry::PassedBy => from = g2,
            }
        }
        (u32::MAX, 0.0)
    }

    /// Searches the receiver's own voxel group, then the voxel groups ahead (or behind) in order;
    /// within a voxel group the accepted candidate with the smallest distance wins. Runs of voxels
    /// holding only the receiver's plane are jumped over (none of them can be its partner).
    ///
    /// A candidate sharing its voxel with other surfels (an edge or corner of an object) must also
    /// be crossed *on its own piece*: the crossing point of the ray from the receiver must lie on the
    /// same side of each voxel-mate's plane as the candidate's surface point. Without this, the
    /// plane of a floor would catch rays that pass outside the room's corner, beyond the wall that
    /// bounds the floor, and light would leak out of closed rooms.
    ///
    /// A ray crosses a plane once: when that crossing falls off the plane's piece (past the edge
    /// where the plane meets its voxel-mate), no later surfel of the same plane can catch the ray,
    /// so the plane is remembered as missed for the rest of the search. This is what keeps a ray
    /// that grazes past the outside corner of a room from meeting the inside of the wall beyond it.
    #[inline(always)]
    fn nearest<const FORWARD: bool>(&self, g: usize, k: usize, dir: Vec3A, chain: &mut Chain) {
        chain.len = 0;
        let x = &self.locals[k];
        if x.ns == 0.0 || gathers_inside::<FORWARD>(x) {
            // The direction lies in the receiver's plane (it gathers nothing along it, and no
            // candidate could pass the test anyway), or the side gathering is inside a solid:
            // do not walk the line.
            return;
        }
        let mut missed = Missed::default();
        let mut layer = OpenLayer::default();
        let mut left = 1.0f32;
        let group_count = self.groups.len() - 1;
        let mut g2 = g;
        // The receiver's own voxel is searched first when it holds other surfels; a voxel is
        // searched again after an open edge in it let part of the ray through (a lamp piece
        // hanging above a floor piece in the same voxel).
        let mut search_here = self.single[g] == u32::MAX;
        loop {
            if search_here {
                search_here = false;
                let Some((found, t)) = self.best_in::<FORWARD>(g2, k, dir, &mut missed) else {
                    continue;
                };
                let candidate = &self.locals[found];
                let open = self.open_share::<FORWARD>(g, found);
                if let Some(share) = open.filter(|_| (chain.len as usize) < MAX_CHAIN - 1) {
                    // An open edge sharing its voxel: it sends its share, its plane is now
                    // crossed, and the rest of the ray may still meet another plane here.
                    layer.take(chain, &mut left, found, share, candidate.normal);
                    missed.insert(candidate.group);
                    if left <= 1e-3 {
                        return;
                    }
                    search_here = true;
                    continue;
                }
                // `t`: the distance the acceptance test gave for the candidate.
                if missed.has_room() && self.off_the_run(x, found, g2, t, dir) {
                    missed.insert(candidate.group);
                    search_here = true;
                    continue;
                }
                let hit = self.where_crossed::<FORWARD>(x, found, g2, t, dir);
                let partner = match self.entry_face::<FORWARD>(x, g, hit, dir) {
                    Entry::Hit(partner) => partner,
                    Entry::PassedBy if missed.has_room() => {
                        missed.insert(candidate.group);
                        search_here = true;
                        continue;
                    }
                    Entry::PassedBy => hit,
                };
                self.open_before_hit::<FORWARD>(
                    g,
                    x,
                    found,
                    g2,
                    t,
                    &mut missed,
                    &mut layer,
                    chain,
                    &mut left,
                );
                chain.push(partner, left);
                return;
            }
            if FORWARD {
                g2 += 1;
                if g2 >= group_count {
                    return;
                }
            } else {
                if g2 == 0 {
                    return;
                }
                g2 -= 1;
            }
            let single = self.single[g2];
            if single == x.group {
                // A run of the receiver's own plane: jump to its far end.
                g2 = if FORWARD {
                    self.run_after[g2] as usize - 1
                } else {
                    self.run_before[g2] as usize
                };
                continue;
            }
            if single != u32::MAX {
                let c = self.groups[g2];
                let candidate = &self.locals[c];
                let hit = if missed.contains(single) {
                    None
                } else {
                    Self::test::<FORWARD>(x, candidate)
                };
                if let Some(t) = hit {
                    let open = self.open_share::<FORWARD>(g, c);
                    if let Some(share) = open.filter(|_| (chain.len as usize) < MAX_CHAIN - 1) {
                        // An open edge: it sends its share, and the ray goes on past its plane
                        // (now crossed, so no other piece of that plane can catch it).
                        layer.take(chain, &mut left, c, share, candidate.normal);
                        missed.insert(single);
                        if left <= 1e-3 {
                            return;
                        }
                        continue;
                    }
                    if missed.has_room() && self.off_the_run(x, c, g2, t, dir) {
                        missed.insert(single);
                        continue;
                    }
                    let hit = self.where_crossed::<FORWARD>(x, c, g2, t, dir);
                    let partner = match self.entry_face::<FORWARD>(x, g, hit, dir) {
                        Entry::Hit(partner) => partner,
                        Entry::PassedBy if missed.has_room() => {
                            missed.insert(single);
                            continue;
                        }
                        Entry::PassedBy => hit,
                    };
                    self.open_before_hit::<FORWARD>(
                        g,
                        x,
                        c,
                        g2,
                        t,
                        &mut missed,
                        &mut layer,
                        chain,
                        &mut left,
                    );
                    chain.push(partner, left);
                    return;
                }
            } else {
                search_here = true;
            }
        }
    }
}

/// How many surfels ahead of the line being gathered [`gather_lines`] asks the memory for. A
/// line's surfels, their radiosity and their sums sit at scattered places of arrays far larger
/// than the caches, and most lines hold only a few surfels, so without this each line waits for
/// its own misses one after the other (the Cornell box at resolution 128 ran about a sixth
/// faster with this). About 40 surfels cover the latency of a miss with the work of the lines in
/// between; 20 did as well, 200 worse.
const PREFETCH_SURFELS: usize = 40;

/// Asks the memory for the cache lines of `base[index]` without waiting for them: its first
/// and its last byte's, or only its first's for a value of at most 16 bytes, which seldom
/// straddles two lines (a side's 12 bytes of light at 2 of its 16 places in a line), where a
/// second instruction for every value cost more than the rare line asked for late.
#[inline(always)]
pub(crate) fn prefetch<T>(base: *const T, index: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let first = base.wrapping_add(index) as *const i8;
        let last = first.wrapping_add(std::mem::size_of::<T>() - 1);
        // SAFETY: a prefetch is only a hint: it never faults and reads nothing into the program,
        // whatever the address.
        unsafe {
            _mm_prefetch::<_MM_HINT_T0>(first);
            if std::mem::size_of::<T>() > 16 {
                _mm_prefetch::<_MM_HINT_T0>(last);
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (base, index);
}

/// Gathers light along the lines `range` of `lines` into `acc`, as [`gather_line`] on each line
/// of two surfels or more, in order; the data of the lines a little ahead is prefetched.
/// Without `ADD` the links are only written down (`acc` is not touched, and may be null): the
/// one-process solver's first iteration records a run of directions and then replays them
/// together (`kept_links`).
///
/// # Safety
/// As for [`gather_line`], for every line of `range`.
pub unsafe fn gather_lines<R: Record, A: LightSum, const ADD: bool>(
    lines: &crate::solve::dispatch::Lines,
    range: std::ops::Range<usize>,
    input: &DirectionInput,
    scratch: &mut LineScratch,
    acc: *mut A,
    record: &mut R,
) {
    let mut ahead = range.start;
    for l in range.clone() {
        let horizon = lines.starts[l] as usize + PREFETCH_SURFELS;
        while ahead < range.end && (lines.starts[ahead] as usize) < horizon {
            let line = lines.line(ahead);
            if line.len() >= 2 {
                for &m in line {
                    prefetch(input.surfels.as_ptr(), m as usize);
                    if ADD {
                        prefetch(input.radiosity.as_ptr(), m as usize);
                        prefetch(acc as *const A, m as usize);
                    }
                }
            }
            ahead += 1;
        }
        let line = lines.line(l);
        if line.len() < 2 {
            continue;
        }
        // SAFETY: see the function's contract.
        unsafe { gather_line::<R, A, ADD>(line, input, scratch, acc, record) };
    }
}

/// Where the links a gather applies are written down, in the order it applies them (see
/// `solve::links`); `()` writes nothing.
pub trait Record {
    /// Side `to_side` of surfel `receiver` gathered `factor` times side `from_side` of surfel
    /// `partner` (surfel indices).
    fn link(&mut self, receiver: u32, to_side: usize, partner: u32, from_side: usize, factor: f64);

    /// The lines about to be gathered hold `surfels` surfels (a recorder can make room for
    /// their links at once instead of growing by steps, each a copy).
    fn expect(&mut self, _surfels: usize) {}
}

impl Record for () {
    #[inline(always)]
    fn link(&mut self, _: u32, _: usize, _: u32, _: usize, _: f64) {}
}

/// Gathers light along one line into `acc` (indexed by surfel); without `ADD`, only writes its
/// links down.
///
/// # Safety
/// With `ADD`, `acc` must point to an array with one entry per surfel of `input.surfels`, and no
/// other thread may access the entries of this line's surfels while this runs (each surfel lies
/// on exactly one line of a direction).
pub unsafe fn gather_line<R: Record, A: LightSum, const ADD: bool>(
    line: &[u32],
    input: &DirectionInput,
    scratch: &mut LineScratch,
    acc: *mut A,
    record: &mut R,
) {
    let s = input.unit;
    find_partners(line, input.surfels, s, scratch);
    // The links in `for_each_link`'s order, written out here so that the gather inlines (through
    // the closure it was a call per link).
    for (k, &[ahead, behind]) in scratch.partners.iter().enumerate() {
        // SAFETY (all three): see the function's contract.
        unsafe {
            add_link::<R, A, ADD>(
                line,
                input,
                acc,
                scratch.link(s, k, 0, ahead.0, ahead.1),
                record,
            );
            add_link::<R, A, ADD>(
                line,
                input,
                acc,
                scratch.link(s, k, 1, behind.0, behind.1),
                record,
            );
        }
    }
    for &(k, which, position, share) in &scratch.extra {
        let link = scratch.link(s, k as usize, which, position, share);
        unsafe { add_link::<R, A, ADD>(line, input, acc, link, record) };
    }
}

/// Adds the light `link` brings (if any) to its receiver's sum in `acc`.
///
/// # Safety
/// As for [`gather_line`].
#[inline(always)]
unsafe fn add_link<R: Record, A: LightSum, const ADD: bool>(
    line: &[u32],
    input: &DirectionInput,
    acc: *mut A,
    link: Option<Link>,
    record: &mut R,
) {
    let Some(link) = link else {
        return;
    };
    if link.cosine == 0.0 {
        return;
    }
    let (receiver, partner) = (line[link.receiver], line[link.partner]);
    let f = link.cosine * input.weight * link.share as f64;
    if ADD {
        let from = &input.radiosity[partner as usize][link.from_side];
        // SAFETY: see the function's contract.
        let to = unsafe { &mut *acc.add(receiver as usize) };
        to.add(link.to_side, from, f, input.channels);
    }
    record.link(receiver, link.to_side, partner, link.from_side, f);
}

/// One partner link of a line: receiver `receiver`'s side `to_side` gathers `share` of its ray
/// along the direction from side `from_side` of `partner` (line positions).
#[derive(Clone, Copy, Debug)]
pub struct Link {
    pub receiver: usize,
    pub to_side: usize,
    pub partner: usize,
    pub from_side: usize,
    pub share: f32,
    /// `|n.s|` of the receiver in f64, exactly as `normalize::cosine` computes it for `S(n)`.
    pub cosine: f64,
    /// 0: the partner lies ahead along `s`; 1: behind.
    pub which: u8,
}

/// Calls `f` for every partner link that [`find_partners`] left in `scratch` for direction `s`.
pub fn for_each_link(scratch: &LineScratch, s: DVec3, mut f: impl FnMut(Link)) {
    for (k, [ahead, behind]) in scratch.partners.iter().enumerate() {
        if let Some(link) = scratch.link(s, k, 0, ahead.0, ahead.1) {
            f(link);
        }
        if let Some(link) = scratch.link(s, k, 1, behind.0, behind.1) {
            f(link);
        }
    }
    for &(k, which, position, share) in &scratch.extra {
        if let Some(link) = scratch.link(s, k as usize, which, position, share) {
            f(link);
        }
    }
}

impl LineScratch {
    /// The link from line position `k`'s search ahead (`which` 0) or behind (1) to line position
    /// `position` with `share` of the ray; `None` when the search found nothing.
    #[inline(always)]
    fn link(&self, s: DVec3, k: usize, which: u8, position: u32, share: f32) -> Option<Link> {
        if position == u32::MAX {
            return None;
        }
        let local = &self.locals[k];
        let partner = &self.locals[position as usize];
        // The receiver's side facing the partner gathers from the partner's side facing it.
        let (to_side, from_side) = if which == 0 {
            (side_along(local.ns), side_along(-partner.ns))
        } else {
            (side_along(-local.ns), side_along(partner.ns))
        };
        Some(Link {
            receiver: k,
            to_side,
            partner: position as usize,
            from_side,
            share,
            cosine: crate::solve::normalize::cosine(local.normal.to_array(), s),
            which,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The sides kept with each piece are what `side_of` says, for every pair of every voxel
    /// of a scene of slabs thinner than a voxel, tilted and meeting, and a voxel holding two
    /// small boxes (a dozen surfels), whose pairs past the kept ranks are left to be computed.
    #[test]
    fn kept_mate_sides_are_side_of() {
        use crate::scene::{Material, Scene};
        use crate::voxel::voxelize::{voxelize, GridSpec};
        let mut scene = Scene::default();
        let m = scene.add_material(Material::new("grey", [0.5; 3], [0.0; 3]));
        let p = DVec3::new;
        scene.add_box(p(0.0, 0.0, 0.0), p(1.0, 1.0, 0.02), m, false);
        scene.add_box(p(0.0, 0.0, 0.0), p(0.02, 1.0, 1.0), m, false);
        scene.add_box(p(0.3, 0.0, 0.4), p(0.7, 0.03, 0.45), m, false);
        // Two small boxes in one voxel: a dozen surfels there.
        scene.add_box(p(0.905, 0.905, 0.905), p(0.915, 0.915, 0.915), m, false);
        scene.add_box(p(0.92, 0.905, 0.92), p(0.93, 0.915, 0.93), m, false);
        let first = scene.triangles.len();
        scene.add_box(p(0.2, 0.2, 0.2), p(0.8, 0.8, 0.23), m, false);
        let tilt = glam::DMat3::from_rotation_x(0.3) * glam::DMat3::from_rotation_y(0.2);
        for t in &mut scene.triangles[first..] {
            for v in &mut t.vertices {
                *v = tilt * (*v - p(0.5, 0.5, 0.5)) + p(0.5, 0.5, 0.5);
            }
        }
        let set = voxelize(&scene, GridSpec::Resolution(24)).expect("voxelize");
        let props = prop_surfels(&set);
        let (mut kept, mut beyond, mut most) = (0, 0, 0);
        let mut first = 0;
        while first < props.len() {
            let voxel = set.surfels[first].voxel;
            let end = first + set.surfels[first..].partition_point(|s| s.voxel == voxel);
            most = most.max(end - first);
            // What the out-of-core work files are made with, one voxel at a time.
            assert_eq!(
                PropSurfel::of_voxel(&set.surfels[first..end], &set.materials),
                props[first..end]
            );
            let locals: Vec<Local> = props[first..end]
                .iter()
                .map(|q| local_of(q, Vec3A::Z))
                .collect();
            for (piece, q) in props[first..end].iter().enumerate() {
                assert_eq!(q.rank as usize, piece);
                for (rank, mate) in locals.iter().enumerate() {
                    let code = if rank < RANKED_MATES {
                        (q.mate_sides >> (2 * rank) & 3) as u8
                    } else {
                        SIDE_UNKNOWN
                    };
                    if rank == piece {
                        assert_eq!(code, SIDE_UNKNOWN);
                    } else if rank < RANKED_MATES {
                        assert_eq!(code, side_code(side_of(mate, &locals[piece])));
                        kept += 1;
                    } else {
                        assert_eq!(code, SIDE_UNKNOWN);
                        beyond += 1;
                    }
                }
            }
            first = end;
        }
        assert!(
            kept > 1000 && most > RANKED_MATES && beyond > 0,
            "{kept} pairs kept, {beyond} beyond the kept ranks, {most} surfels at most"
        );
    }

    /// The searches of plain lines (`plain_partners`, `LineView::nearest_plain`) find what the
    /// general search finds on them, every search or some (`Toward`, as the direct pass asks),
    /// on every line of the Cornell box and of a small generated building along 73 directions:
    /// the building's walls and slabs are closed solids, so rays also meet sides inside them.
    #[test]
    fn plain_lines_find_what_the_general_search_finds() {
        use crate::voxel::voxelize::{voxelize, GridSpec};
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/examples/cornell_box.obj");
        let cornell = crate::scene::obj::load_obj(std::path::Path::new(path)).expect("the example");
        let building = crate::gen::procedural::building(2, 2, 1, 7);
        for (scene, resolution) in [(cornell, 40), (building, 60)] {
            let set = voxelize(&scene, GridSpec::Resolution(resolution)).expect("voxelized");
            plain_lines_agree(&set);
        }
    }

    fn plain_lines_agree(set: &crate::voxel::SurfelSet) {
        use crate::geometry::{directions::DirectionSet, lines::LineFrame, order};
        use crate::solve::dispatch::{dispatch, lexicographic_orders, Lines};
        let props = prop_surfels(set);
        let orders = lexicographic_orders(set);
        let (mut plain, mut general) = (LineScratch::default(), LineScratch::default());
        let mut lines = Lines::default();
        let (mut plain_lines, mut partners_found) = (0, 0);
        for d in &DirectionSet::with_count(73).directions {
            let frame = LineFrame::new(d.vector, set.grid.dims);
            dispatch(&orders[order::order_of(d.vector)], &frame, 1, &mut lines);
            for l in 0..lines.line_count() {
                let line = lines.line(l);
                if line.len() < 2 {
                    continue;
                }
                let is_plain = line
                    .windows(2)
                    .all(|w| props[w[0] as usize].voxel != props[w[1] as usize].voxel)
                    && line.iter().all(|&m| props[m as usize].coverage >= 1.0);
                plain_lines += is_plain as usize;
                // Every search, then those of a span and of its targets, as the direct pass.
                let (first, last) = (line.len() / 3, line.len() / 2);
                let targets: Vec<bool> = (0..line.len()).map(|k| k % 3 == 1).collect();
                let towards = [
                    None,
                    Some(Toward::span(first, last)),
                    Some(Toward {
                        also_ahead: &[0],
                        targets: &targets,
                        ..Toward::span(first, last)
                    }),
                ];
                for toward in towards {
                    search_line(line, &props, d.unit, &mut plain, toward, true);
                    search_line(line, &props, d.unit, &mut general, toward, false);
                    assert_eq!(
                        plain.partners, general.partners,
                        "direction {:?}, line {l}",
                        d.vector
                    );
                    assert_eq!(plain.extra, general.extra);
                    partners_found += plain
                        .partners
                        .iter()
                        .flatten()
                        .filter(|p| p.0 != u32::MAX)
                        .count();
                }
            }
        }
        // The comparison saw plain lines, and searches that found partners on them.
        assert!(plain_lines > 50_000, "{plain_lines} plain lines");
        assert!(partners_found > 1_000_000, "{partners_found} partners");
    }

    #[test]
    fn floor_to_i32_is_floor() {
        let mut values = vec![
            0.0f32,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            1.5,
            -1.5,
            2.999_999_8,
            -2.999_999_8,
            16_777_215.5,
            -16_777_215.5,
            16_777_216.0,
            3.0e9,
            -3.0e9,
            2_147_483_648.0,
            -2_147_483_648.0,
            -2_147_483_904.0,
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            1e-30,
            -1e-30,
        ];
        values.extend((-2000..2000).map(|i| i as f32 * 0.0137));
        for x in values {
            assert_eq!(floor_to_i32(x), x.floor() as i32, "{x}");
        }
    }
}

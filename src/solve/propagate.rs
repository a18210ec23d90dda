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
//! Every surfel side receives exactly one gather per line direction, so accumulating in direction
//! order makes the result independent of how lines are spread over threads.

use crate::voxel::{BACK, FRONT};
use glam::DVec3;

/// Margin (voxel units) below which a point counts as lying on a plane rather than in front of it.
pub const EPS: f64 = 1e-4;

/// What propagation needs of a surfel, packed for the hot loop.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PropSurfel {
    pub voxel: [i32; 3],
    pub group: u32,
    pub point: [f32; 3],
    pub normal: [f32; 3],
}

impl PropSurfel {
    #[inline]
    fn normal(&self) -> DVec3 {
        DVec3::new(
            self.normal[0] as f64,
            self.normal[1] as f64,
            self.normal[2] as f64,
        )
    }
}

/// `p_c - p_r` in voxel units, exact in the integer part.
#[inline]
fn offset(r: &PropSurfel, c: &PropSurfel) -> DVec3 {
    DVec3::new(
        (c.voxel[0] - r.voxel[0]) as f64 + (c.point[0] - r.point[0]) as f64,
        (c.voxel[1] - r.voxel[1]) as f64 + (c.point[1] - r.point[1]) as f64,
        (c.voxel[2] - r.voxel[2]) as f64 + (c.point[2] - r.point[2]) as f64,
    )
}

/// Whether `r` (behind) and `c` (ahead along unit direction `s`) light each other. Returns the
/// distance along `s` from `r`'s point to `c`'s plane and the distance along `-s` from `c`'s point
/// to `r`'s plane (both positive), used to pick the nearest candidate within a voxel.
#[inline]
pub fn facing(r: &PropSurfel, c: &PropSurfel, s: DVec3) -> Option<(f64, f64)> {
    if r.group == c.group {
        return None;
    }
    let (nr, nc) = (r.normal(), c.normal());
    let (rs, cs) = (nr.dot(s), nc.dot(s));
    if rs == 0.0 || cs == 0.0 {
        return None;
    }
    let d = offset(r, c);
    let (rd, cd) = (nr.dot(d), nc.dot(d));
    if rd * rs.signum() <= EPS || cd * cs.signum() <= EPS {
        return None;
    }
    Some((cd / cs, rd / rs))
}

/// The side of a surfel (normal `n`) that faces along `s`.
#[inline]
pub fn side_facing(n: DVec3, s: DVec3) -> usize {
    if n.dot(s) > 0.0 {
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
}

/// Partners found on one line: for each position, the line position of the partner ahead and the
/// partner behind (`u32::MAX` for none).
pub fn find_partners(
    line: &[u32],
    surfels: &[PropSurfel],
    s: DVec3,
    groups: &mut Vec<usize>,
    out: &mut Vec<[u32; 2]>,
) {
    groups.clear();
    out.clear();
    for (k, &m) in line.iter().enumerate() {
        if k == 0 || surfels[m as usize].voxel != surfels[line[k - 1] as usize].voxel {
            groups.push(k);
        }
    }
    groups.push(line.len());
    let group_count = groups.len() - 1;
    for g in 0..group_count {
        for k in groups[g]..groups[g + 1] {
            let x = &surfels[line[k] as usize];
            let view = LineView {
                line,
                surfels,
                groups,
            };
            let ahead = view.nearest(g, k, s, true, |other| facing(x, other, s).map(|t| t.0));
            let behind = view.nearest(g, k, -s, false, |other| facing(other, x, s).map(|t| t.1));
            out.push([ahead, behind]);
        }
    }
}

/// Searches the receiver's own voxel group, then the groups ahead along `dir` (or behind, for
/// `dir = -s`) in order; within a group the accepted candidate with the smallest distance wins.
///
/// A candidate sharing its voxel with other surfels (an edge or corner of an object) must also be
/// crossed *on its own piece*: the crossing point of the ray from the receiver must lie on the
/// same side of each voxel-mate's plane as the candidate's surface point. Without this, the plane
/// of a floor would catch rays that pass outside the room's corner, beyond the wall that bounds
/// the floor, and light would leak out of closed rooms.
impl LineView<'_> {
    #[inline]
    fn nearest(
        &self,
        g: usize,
        k: usize,
        dir: DVec3,
        forward: bool,
        test: impl Fn(&PropSurfel) -> Option<f64>,
    ) -> u32 {
        let LineView {
            line,
            surfels,
            groups,
        } = *self;
        let x = &surfels[line[k] as usize];
        let best_in = |range: std::ops::Range<usize>| -> Option<usize> {
            let mut best: Option<(f64, usize)> = None;
            for k2 in range.clone() {
                if k2 == k {
                    continue;
                }
                let c = &surfels[line[k2] as usize];
                let Some(t) = test(c) else { continue };
                if best.is_some_and(|(bt, _)| t >= bt) {
                    continue;
                }
                // Crossing point relative to the receiver's point.
                let q = dir * t;
                let on_piece = range.clone().all(|k3| {
                    let mate = &surfels[line[k3] as usize];
                    if k3 == k2 || k3 == k || mate.group == c.group {
                        return true;
                    }
                    let n = mate.normal();
                    let piece_side = n.dot(offset(mate, c));
                    if piece_side.abs() <= EPS {
                        return true;
                    }
                    n.dot(q - offset(x, mate)) * piece_side.signum() >= -EPS
                });
                if on_piece {
                    best = Some((t, k2));
                }
            }
            best.map(|b| b.1)
        };
        if let Some(found) = best_in(groups[g]..groups[g + 1]) {
            return found as u32;
        }
        if forward {
            for g2 in g + 1..groups.len() - 1 {
                if let Some(found) = best_in(groups[g2]..groups[g2 + 1]) {
                    return found as u32;
                }
            }
        } else {
            for g2 in (0..g).rev() {
                if let Some(found) = best_in(groups[g2]..groups[g2 + 1]) {
                    return found as u32;
                }
            }
        }
        u32::MAX
    }
}

/// One line of one direction, with its voxel groups (start positions, then the end).
#[derive(Clone, Copy)]
struct LineView<'a> {
    line: &'a [u32],
    surfels: &'a [PropSurfel],
    groups: &'a [usize],
}

/// Gathers light along one line into `acc` (indexed by surfel).
///
/// # Safety
/// `acc` must point to an array with one entry per surfel of `input.surfels`, and no other thread
/// may access the entries of this line's surfels while this runs (each surfel lies on exactly one
/// line of a direction).
pub unsafe fn gather_line(
    line: &[u32],
    input: &DirectionInput,
    groups: &mut Vec<usize>,
    partners: &mut Vec<[u32; 2]>,
    acc: *mut [[f64; 3]; 2],
) {
    let s = input.unit;
    find_partners(line, input.surfels, s, groups, partners);
    for (k, &m) in line.iter().enumerate() {
        let x = &input.surfels[m as usize];
        let n = x.normal();
        let cos = n.dot(s).abs();
        if cos == 0.0 {
            continue;
        }
        let factor = cos * input.weight;
        let [ahead, behind] = partners[k];
        // SAFETY: see the function's contract.
        let target = unsafe { &mut *acc.add(m as usize) };
        if ahead != u32::MAX {
            let y = line[ahead as usize] as usize;
            let from = input.radiosity[y][side_facing(input.surfels[y].normal(), -s)];
            let to = &mut target[side_facing(n, s)];
            for ch in 0..3 {
                to[ch] += from[ch] as f64 * factor;
            }
        }
        if behind != u32::MAX {
            let y = line[behind as usize] as usize;
            let from = input.radiosity[y][side_facing(input.surfels[y].normal(), s)];
            let to = &mut target[side_facing(n, -s)];
            for ch in 0..3 {
                to[ch] += from[ch] as f64 * factor;
            }
        }
    }
}

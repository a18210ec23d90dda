//! Whether a scene's light is sealed in: the check behind `closed`'s scales, made in one sweep
//! over the surfels in the shard order, within a bounded memory, the same in every solve path.
//!
//! **What it decides.** A scene is closed when no emitting side faces air that reaches the grid's
//! outside. Air is the empty voxels; the outside air is every empty voxel connected through faces
//! of empty voxels to one on the grid's boundary. An emitting side faces the first empty voxel
//! along its normal (at most three voxels on, past voxels its own solid or a neighbouring surface
//! holds; a voxel past the grid is outside; a side whose three voxels on are all held opens
//! nothing). An opening narrower than a voxel does not open a scene: its voxels hold the wall.
//!
//! **How.** The surfels come sorted by `z` first (the shard order, `geometry::order`; a set in
//! memory is sorted for the check), so the grid is swept one `z` slice at a time: each slice's
//! empty voxels are labelled and joined, in a union-find, with their empty neighbours in the
//! slice and in the slice before; empty voxels on the grid's boundary join the outside. An
//! emitting side notes the label of the voxel it faces once the slices its walk needs are known
//! (three on along its normal). Once the last slice is labelled, a side is open when its label's
//! set holds the outside. A scene held in memory, one out of core and one dealt over ranks go
//! through the same sweep, so they reach the same verdict whatever memory they were given, as
//! long as the check fits in it.
//!
//! **Cost.** Four slices of labels (4 bytes a voxel) and occupancy, 4 bytes per label set
//! (a few per room and slice), 24 bytes per emitting side waiting for the slices ahead of it,
//! and 16 per distinct label faced. A check that would take more than the memory it is given
//! gives up, and the scene is solved as an open one, which the report says.

use crate::voxel::disjoint::DisjointSets;
use crate::voxel::SurfelSet;
use glam::Vec3;
use std::collections::HashMap;

/// What the check found, for the solve and the report.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Verdict {
    /// The scene's light is sealed in: the scales apply.
    pub closed: bool,
    /// The check needed more memory than it was given: the scene is solved as an open one.
    pub unchecked: bool,
    /// Emitting sides, and those among them that face air reaching the grid's outside.
    pub emitting_sides: u64,
    pub open_sides: u64,
}

/// Slices held at once: a walk three voxels along a normal spans four.
const RING: usize = 4;
/// How far a side's walk looks along its normal.
const WALK: i64 = 3;
/// Label of a held voxel.
const HELD: u32 = 0;
/// Label of the air outside the grid.
const OUTSIDE: u32 = 1;
/// Bytes an emitting side takes while it waits for the slices ahead of it.
const BYTES_PER_PENDING: u64 = std::mem::size_of::<([i32; 3], Vec3)>() as u64;
/// Bytes a distinct faced label takes (a hash map entry, with its slack).
const BYTES_PER_FACED: u64 = 32;

/// The sweep: feed every surfel with [`Enclosure::add`] in nondecreasing `z`, then take the
/// [`Enclosure::verdict`].
pub struct Enclosure {
    dims: [i64; 3],
    /// Occupancy bits of the slices `current - 3 ..= current`, slice `z` at `z % RING`.
    held: Vec<Vec<u64>>,
    /// Labels of the same slices' voxels (labelled once a slice is complete).
    labels: Vec<Vec<u32>>,
    /// The sets of labels; [`OUTSIDE`] is the outside's (its smallest label, so its root).
    sets: DisjointSets,
    /// The slice surfels are being added to; those below it are labelled.
    current: i64,
    /// Emitting sides waiting for the slice their walk needs: voxel and emitting normal.
    pending: Vec<([i32; 3], Vec3)>,
    /// Sides that faced each label, and those that faced past the grid.
    faced: HashMap<u32, u64>,
    faced_past_grid: u64,
    emitting_sides: u64,
    /// Bytes the parts that grow may take; `None` once the check gave up.
    allowance: Option<u64>,
}

impl Enclosure {
    /// A sweep over a grid of `dims` that takes at most `max_bytes`, or `None` when its slices
    /// alone take more.
    pub fn new(dims: [u32; 3], max_bytes: u64) -> Option<Self> {
        let slice = dims[0] as u64 * dims[1] as u64;
        let fixed = RING as u64 * (slice * 4 + slice.div_ceil(64) * 8);
        if fixed > max_bytes {
            return None;
        }
        Some(Enclosure {
            dims: dims.map(|d| d as i64),
            held: vec![vec![0; slice.div_ceil(64) as usize]; RING],
            labels: vec![vec![HELD; slice as usize]; RING],
            sets: DisjointSets::new(2),
            current: 0,
            pending: Vec::new(),
            faced: HashMap::new(),
            faced_past_grid: 0,
            emitting_sides: 0,
            allowance: Some(max_bytes - fixed),
        })
    }

    /// The verdict on a set held in memory (sorted here into the sweep's order).
    pub fn verdict_of_set(set: &SurfelSet) -> Verdict {
        let Some(mut e) = Enclosure::new(set.grid.dims, u64::MAX) else {
            return Verdict::too_large();
        };
        let mut order: Vec<u32> = (0..set.surfels.len() as u32).collect();
        order.sort_unstable_by_key(|&i| set.surfels[i as usize].voxel[2]);
        for i in order {
            let s = &set.surfels[i as usize];
            let emits = s
                .material
                .map(|m| set.materials[m as usize].emission.iter().any(|&v| v > 0.0));
            e.add(s.voxel, s.normal, emits);
        }
        e.verdict()
    }

    /// Notes a surfel in `voxel` whose front has `normal`; `emits` tells which of its sides
    /// (front, back) emit. Surfels come in nondecreasing `z`; one out of order ends the check.
    pub fn add(&mut self, voxel: [i32; 3], normal: [f32; 3], emits: [bool; 2]) {
        if self.allowance.is_none() {
            return;
        }
        let z = voxel[2] as i64;
        if z < self.current {
            self.allowance = None;
            return;
        }
        while self.current < z.min(self.dims[2]) {
            self.close_slice();
        }
        if let Some(i) = self.cell(voxel.map(|v| v as i64)) {
            self.held[z as usize % RING][i / 64] |= 1 << (i % 64);
        }
        let n = Vec3::from(normal);
        for (side, sign) in [(0, 1.0f32), (1, -1.0)] {
            if emits[side] {
                self.emitting_sides += 1;
                self.pending.push((voxel, n * sign));
                self.spend(BYTES_PER_PENDING);
            }
        }
    }

    /// Labels the remaining slices and judges the scene.
    pub fn verdict(mut self) -> Verdict {
        while self.allowance.is_some() && self.current < self.dims[2] {
            self.close_slice();
        }
        if self.allowance.is_none() {
            return Verdict::too_large();
        }
        // Sides facing past the last slice.
        self.resolve(i64::MAX);
        let outside = self.sets.find(OUTSIDE);
        let mut open_sides = self.faced_past_grid;
        let faced: Vec<(u32, u64)> = self.faced.iter().map(|(&l, &c)| (l, c)).collect();
        for (label, count) in faced {
            if self.sets.find(label) == outside {
                open_sides += count;
            }
        }
        Verdict {
            closed: self.emitting_sides > 0 && open_sides == 0,
            unchecked: false,
            emitting_sides: self.emitting_sides,
            open_sides,
        }
    }

    /// Takes `bytes` from the allowance, giving up when it runs out.
    fn spend(&mut self, bytes: u64) {
        self.allowance = self.allowance.and_then(|a| a.checked_sub(bytes));
        if self.allowance.is_none() {
            self.pending = Vec::new();
            self.faced = HashMap::new();
            self.sets = DisjointSets::default();
        }
    }

    /// Index of `c` within its slice, if `c` is in the grid.
    fn cell(&self, c: [i64; 3]) -> Option<usize> {
        let [nx, ny, nz] = self.dims;
        let inside = (0..nx).contains(&c[0]) && (0..ny).contains(&c[1]) && (0..nz).contains(&c[2]);
        inside.then(|| (c[1] * nx + c[0]) as usize)
    }

    fn is_held(&self, z: i64, i: usize) -> bool {
        self.held[z as usize % RING][i / 64] >> (i % 64) & 1 == 1
    }

    /// Labels slice `current`, whose surfels are all in, then resolves the sides that can be
    /// and makes room for the next slice.
    fn close_slice(&mut self) {
        let [nx, ny, nz] = self.dims;
        let z = self.current;
        let slot = z as usize % RING;
        let before = (z + RING as i64 - 1) as usize % RING;
        let mut labels = std::mem::take(&mut self.labels[slot]);
        let previous = std::mem::take(&mut self.labels[before]);
        for y in 0..ny {
            for x in 0..nx {
                let i = (y * nx + x) as usize;
                if self.is_held(z, i) {
                    labels[i] = HELD;
                    continue;
                }
                let left = if x > 0 { labels[i - 1] } else { HELD };
                let up = if y > 0 { labels[i - nx as usize] } else { HELD };
                let back = if z > 0 { previous[i] } else { HELD };
                let mut label = [left, up, back]
                    .into_iter()
                    .find(|&l| l != HELD)
                    .unwrap_or(HELD);
                if label == HELD {
                    label = self.sets.push();
                    self.spend(4);
                    if self.allowance.is_none() {
                        return;
                    }
                }
                for other in [left, up, back] {
                    if other != HELD && other != label {
                        self.sets.union(label, other);
                    }
                }
                let boundary = x == 0 || y == 0 || z == 0 || x == nx - 1 || y == ny - 1;
                if boundary || z == nz - 1 {
                    self.sets.union(label, OUTSIDE);
                }
                labels[i] = label;
            }
        }
        self.labels[slot] = labels;
        self.labels[before] = previous;
        self.resolve(z);
        // The slice that leaves the ring makes room for slice z + 1.
        self.current += 1;
        let next = self.current as usize % RING;
        self.held[next].fill(0);
    }

    /// The last slice a side's walk reads: three on along its normal where that goes up in `z`,
    /// else its own.
    fn last_slice(voxel: [i32; 3], n: Vec3) -> i64 {
        let ahead = (1..=WALK)
            .map(|t| (n.z * t as f32).round() as i64)
            .max()
            .unwrap_or(0);
        voxel[2] as i64 + ahead.max(0)
    }

    /// Notes the faced voxel of every waiting side whose walk needs no slice past `labelled`.
    fn resolve(&mut self, labelled: i64) {
        let mut waiting = std::mem::take(&mut self.pending);
        waiting.retain(|&(voxel, n)| {
            if Self::last_slice(voxel, n) > labelled {
                return true;
            }
            self.face(voxel, n);
            false
        });
        self.pending = waiting;
    }

    /// Walks from the side in `voxel` along `n` to the first empty voxel and notes its label.
    fn face(&mut self, voxel: [i32; 3], n: Vec3) {
        let start = voxel.map(|v| v as i64);
        for t in 1..=WALK {
            let step = (n * t as f32).round();
            let c = [
                start[0] + step.x as i64,
                start[1] + step.y as i64,
                start[2] + step.z as i64,
            ];
            if c == start {
                continue;
            }
            let Some(i) = self.cell(c) else {
                self.faced_past_grid += 1;
                return;
            };
            if !self.is_held(c[2], i) {
                let label = self.labels[c[2] as usize % RING][i];
                let known = self.faced.len();
                *self.faced.entry(label).or_insert(0) += 1;
                if self.faced.len() > known {
                    self.spend(BYTES_PER_FACED);
                }
                return;
            }
        }
    }
}

impl Verdict {
    /// The verdict of a check that needed more memory than it was given, or met surfels out of
    /// order: an open scene.
    pub fn too_large() -> Self {
        Verdict {
            unchecked: true,
            ..Default::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An independent answer: the whole grid in memory, the outside air flooded from the
    /// boundary voxel by voxel, each side's walk looked up afterwards.
    fn flooded(dims: [i64; 3], held: &[[i64; 3]], emitters: &[([i64; 3], Vec3)]) -> (u64, u64) {
        let [nx, ny, nz] = dims;
        let at = |c: [i64; 3]| ((c[2] * ny + c[1]) * nx + c[0]) as usize;
        let inside = |c: [i64; 3]| (0..3).all(|k| (0..dims[k]).contains(&c[k]));
        let mut full = vec![false; (nx * ny * nz) as usize];
        for c in held.iter().chain(emitters.iter().map(|(c, _)| c)) {
            full[at(*c)] = true;
        }
        let mut outside = vec![false; full.len()];
        let mut stack = Vec::new();
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    let edge = [x, y, z]
                        .iter()
                        .zip(dims)
                        .any(|(&c, d)| c == 0 || c == d - 1);
                    if edge && !full[at([x, y, z])] {
                        stack.push([x, y, z]);
                    }
                }
            }
        }
        while let Some(c) = stack.pop() {
            if !inside(c) || full[at(c)] || outside[at(c)] {
                continue;
            }
            outside[at(c)] = true;
            for k in 0..3 {
                for d in [-1, 1] {
                    let mut n = c;
                    n[k] += d;
                    stack.push(n);
                }
            }
        }
        let mut open = 0;
        for &(v, n) in emitters {
            for t in 1..=WALK {
                let s = (n * t as f32).round();
                let c = [v[0] + s.x as i64, v[1] + s.y as i64, v[2] + s.z as i64];
                if c == v {
                    continue;
                }
                if !inside(c) {
                    open += 1;
                    break;
                }
                if !full[at(c)] {
                    open += outside[at(c)] as u64;
                    break;
                }
            }
        }
        (emitters.len() as u64, open)
    }

    /// The sweep's verdict on the same voxels, fed in z order.
    fn swept(dims: [i64; 3], held: &[[i64; 3]], emitters: &[([i64; 3], Vec3)]) -> Verdict {
        let mut e = Enclosure::new(dims.map(|d| d as u32), u64::MAX).unwrap();
        let mut items: Vec<([i64; 3], Option<Vec3>)> = held.iter().map(|&c| (c, None)).collect();
        items.extend(emitters.iter().map(|&(c, n)| (c, Some(n))));
        items.sort_by_key(|(c, _)| c[2]);
        for (c, n) in items {
            let v = c.map(|x| x as i32);
            match n {
                Some(n) => e.add(v, n.into(), [true, false]),
                None => e.add(v, [0.0, 0.0, 1.0], [false, false]),
            }
        }
        e.verdict()
    }

    /// A hollow box of side `n` with a lamp on its floor facing up; `hole`: one voxel of the
    /// ceiling left out.
    fn hollow_box(n: i64, hole: bool) -> Verdict {
        let mut held = Vec::new();
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let shell = [x, y, z].iter().any(|&c| c == 0 || c == n - 1);
                    let opening = hole && y == n - 1 && x == n / 2 && z == n / 2;
                    if shell && !opening {
                        held.push([x, y, z]);
                    }
                }
            }
        }
        swept([n; 3], &held, &[([n / 2, 0, n / 2], Vec3::Y)])
    }

    #[test]
    fn a_sealed_box_is_closed_and_one_hole_opens_it() {
        let sealed = hollow_box(8, false);
        assert!(sealed.closed, "{sealed:?}");
        assert_eq!((sealed.emitting_sides, sealed.open_sides), (1, 0));
        let open = hollow_box(8, true);
        assert!(!open.closed, "{open:?}");
        assert_eq!(open.open_sides, 1);
    }

    #[test]
    fn a_lamp_facing_out_of_the_grid_opens_the_scene() {
        // A lamp on the grid's top layer, emitting upward: out of the grid.
        let v = swept([4; 3], &[], &[([1, 3, 1], Vec3::Y)]);
        assert!(!v.closed);
        // The same lamp emitting down into the grid, whose air reaches the outside.
        let v = swept([4; 3], &[], &[([1, 3, 1], -Vec3::Y)]);
        assert!(!v.closed && v.open_sides == 1);
    }

    #[test]
    fn a_scene_without_emitters_is_not_called_closed() {
        assert!(!swept([3; 3], &[[1, 1, 1]], &[]).closed);
    }

    #[test]
    fn the_sweep_agrees_with_a_flood_of_the_whole_grid() {
        // Random walls with random gaps and random lamps: the sweep, one slice at a time, and
        // the flood, the whole grid at once, must find the same open sides.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = |m: u64| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state % m
        };
        let mut closed = 0;
        for case in 0..300 {
            let dims = [3 + next(9) as i64, 3 + next(9) as i64, 3 + next(9) as i64];
            let mut held = Vec::new();
            // A shell with a few gaps (often none), and inner walls.
            let gaps = if case % 2 == 0 { 0 } else { 1 + next(3) };
            let gap_cells: Vec<[i64; 3]> = (0..gaps)
                .map(|_| [0, 1, 2].map(|k| next(dims[k] as u64) as i64))
                .collect();
            for z in 0..dims[2] {
                for y in 0..dims[1] {
                    for x in 0..dims[0] {
                        let c = [x, y, z];
                        let shell = (0..3).any(|k| c[k] == 0 || c[k] == dims[k] - 1);
                        let wall = next(7) == 0;
                        if (shell && !gap_cells.contains(&c)) || (!shell && wall) {
                            held.push(c);
                        }
                    }
                }
            }
            let lamps: Vec<([i64; 3], Vec3)> = (0..1 + next(4))
                .map(|_| {
                    let c = [0, 1, 2].map(|k| next(dims[k] as u64) as i64);
                    let n = Vec3::new(
                        next(5) as f32 - 2.0,
                        next(5) as f32 - 2.0,
                        next(5) as f32 - 2.0,
                    )
                    .try_normalize()
                    .unwrap_or(Vec3::Z);
                    (c, n)
                })
                .collect();
            let v = swept(dims, &held, &lamps);
            assert_eq!(
                (v.emitting_sides, v.open_sides),
                flooded(dims, &held, &lamps),
                "case {case}: {dims:?}"
            );
            closed += v.closed as u32;
        }
        // Both kinds of scenes were met.
        assert!(closed > 20 && closed < 280, "{closed} closed");
    }

    #[test]
    fn a_check_beyond_its_memory_is_unchecked_not_closed() {
        // A 8 x 8 slice: four slices take 4 * (256 + 8) bytes.
        assert!(Enclosure::new([8, 8, 8], 1055).is_none());
        let mut e = Enclosure::new([8, 8, 8], 1056 + 2 * BYTES_PER_PENDING).unwrap();
        for x in 0..3 {
            e.add([x, 0, 0], [0.0, 1.0, 0.0], [true, false]);
        }
        let v = e.verdict();
        assert!(v.unchecked && !v.closed, "{v:?}");
    }
}

//! Irradiance at sensor points anywhere in the scene (not only on surfaces), from a solve's
//! radiosity: what a lighting engineer's workplane grid reads (`voxrad grid`).
//!
//! A sensor at `p` facing `n` receives `H = (1/pi) * integral of B(w) cos(w, n) dw` over the
//! hemisphere `n` faces, where `B(w)` is the radiosity of the first surface seen along `w`, on
//! the side facing back to `p`. voxrad splits it as its solver does:
//!
//! - **Reflected light** along the integer directions of a [`DirectionSet`] (each `s` and `-s`,
//!   weighted by the solid angle of its cell, normalised by their sum on the hemisphere as the
//!   solver's `S(n)`): a ray from `p` through the voxel grid (Amanatides and Woo's traversal)
//!   meets, in each occupied voxel, the planes of its surfels; the nearest crossing that lies on
//!   a surfel's piece (inside the piece's bounding box in the voxel) is the surface seen. A ray that meets an emitting side counts nothing here.
//! - **Emitters** one surfel side at a time: `B A cos(n, u) cos(m, -u) / (pi r^2)` for the
//!   side's area `A`, normal `m`, at distance `r` along `u`, if a ray from `p` towards it meets
//!   nothing before its voxel. A few hundred bounce directions would miss small lamps, as they
//!   do in the solver without its direct-light pass.
//!
//! Positions are in voxel units inside; the caller gives and gets world units.

use super::results::Results;
use crate::geometry::directions::DirectionSet;
use crate::solve::mix_hash::MixMap;
use crate::voxel::{packed_voxel, BACK, FRONT};
use glam::DVec3;
use std::f64::consts::PI;

/// Rays start this far (voxels) along their direction from the sensor, so that a sensor laid on
/// a surface does not see that surface.
const START: f64 = 1e-6;

/// A surfel side that emits, for the emitter sum.
struct Emitter {
    /// Position (voxel units) and the emitting side's normal.
    point: DVec3,
    normal: DVec3,
    /// Area (voxel units squared) times the side's radiosity.
    power: [f64; 3],
    voxel: [i32; 3],
}

/// The records of a results file, indexed for ray casting, and its emitting sides.
pub struct SensorField<'a> {
    results: &'a Results,
    /// Record indices by voxel (`voxel::packed_voxel`), in the solver's fast hash map: a ray
    /// looks up every voxel it crosses.
    cells: MixMap<Vec<u32>>,
    /// The grid's box in voxels (inclusive low corner, exclusive high).
    low: [i32; 3],
    high: [i32; 3],
    /// One bit per voxel of the box ([`SensorField::bit_of`]): set where some record lies. A
    /// ray crosses mostly empty voxels (the air of a room), which the bitmap answers without a
    /// hash look-up (the look-ups took over half of a grid's time). Only for boxes of at most
    /// [`MAX_BITMAP_VOXELS`] voxels.
    occupied: Option<Vec<u64>>,
    emitters: Vec<Emitter>,
    /// Whether each record's side emits (its rays count in the emitter sum instead).
    emits: Vec<[bool; 2]>,
    directions: Vec<(DVec3, f64)>,
}

/// Line directions a sensor gathers along by default at resolution 64 ([`directions_for`]).
pub const DIRECTIONS_AT_64: usize = 2000;

/// The most line directions [`directions_for`] asks for.
pub const MOST_DIRECTIONS: usize = 32_000;

/// Line directions a probe's sensor (`voxrad probe --gather`, the study) gathers along by
/// default for a grid of `dims` voxels: 2,000 at a longest side of 64 voxels, growing with its
/// square up to 32,000 at 256. A ray's neighbours then lie about as many voxels apart at the far
/// wall whatever the resolution: at resolution 192, 2,000 directions left the gathered answer
/// 0.56 % off the path-traced reference on the office scene, 20,000 took it to 0.35 %
/// (docs/accuracy.md, "The sensors' directions and the `high` preset"). `voxrad grid`, whose
/// many sensors would take six times longer at 256, keeps 2,000 unless told.
pub fn directions_for(dims: [u32; 3]) -> usize {
    let longest = dims.iter().copied().max().unwrap_or(0) as f64;
    let scaled = DIRECTIONS_AT_64 as f64 * (longest / 64.0).powi(2);
    (scaled.round() as usize).clamp(DIRECTIONS_AT_64, MOST_DIRECTIONS)
}

/// The largest box (in voxels) that gets an occupancy bitmap: 32 MiB of bits.
const MAX_BITMAP_VOXELS: u64 = 1 << 28;

/// The bit of voxel `v` (inside the box `low..high`) in [`SensorField::occupied`].
fn bit_of(low: [i32; 3], high: [i32; 3], v: [i32; 3]) -> usize {
    let size = |a: usize| (high[a] - low[a]) as usize;
    let at = |a: usize| (v[a] - low[a]) as usize;
    (at(0) * size(1) + at(1)) * size(2) + at(2)
}

/// What a ray met first.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub record: usize,
    pub side: usize,
    /// Distance along the ray, voxels.
    pub t: f64,
}

impl<'a> SensorField<'a> {
    /// Indexes `results` (whose sides' emission comes from its material table) for sensors that
    /// gather along about `directions` line directions.
    pub fn new(results: &'a Results, directions: usize) -> Self {
        let mut cells: MixMap<Vec<u32>> = MixMap::default();
        let (mut low, mut high) = ([i32::MAX; 3], [i32::MIN; 3]);
        let mut emitters = Vec::new();
        let mut emits = Vec::with_capacity(results.records.len());
        for (k, r) in results.records.iter().enumerate() {
            if let Some(key) = packed_voxel(r.voxel) {
                cells.entry(key).or_default().push(k as u32);
            }
            for a in 0..3 {
                low[a] = low[a].min(r.voxel[a]);
                high[a] = high[a].max(r.voxel[a] + 1);
            }
            let mut side_emits = [false; 2];
            for side in [FRONT, BACK] {
                let e = results
                    .materials
                    .get(r.material[side] as usize)
                    .map_or([0.0; 3], |m| m.emission);
                if e.iter().any(|&c| c > 0.0) && r.area > 0.0 {
                    side_emits[side] = true;
                    emitters.push(Emitter {
                        point: r.position(),
                        normal: r.side_normal(side),
                        power: r.radiosity[side].map(|b| b as f64 * r.area as f64),
                        voxel: r.voxel,
                    });
                }
            }
            emits.push(side_emits);
        }
        let set = DirectionSet::with_count(directions);
        let directions = set
            .directions
            .iter()
            .flat_map(|d| [(d.unit, d.solid_angle), (-d.unit, d.solid_angle)])
            .collect();
        let voxels: u64 = (0..3)
            .map(|a| (high[a] as i64 - low[a] as i64).max(0) as u64)
            .product();
        let occupied = (voxels <= MAX_BITMAP_VOXELS).then(|| {
            let mut bits = vec![0u64; voxels.div_ceil(64) as usize];
            for r in &results.records {
                let bit = bit_of(low, high, r.voxel);
                bits[bit / 64] |= 1 << (bit % 64);
            }
            bits
        });
        SensorField {
            results,
            cells,
            low,
            high,
            occupied,
            emitters,
            emits,
            directions,
        }
    }

    /// `row` (a probe looked up in the same results) answered by gathering instead: the
    /// irradiance a sensor a thousandth of a voxel off the surface receives, and the radiosity
    /// `E + rho H` of the surface's side there (its material is the probe's). A row that found
    /// no surface is returned as it is.
    pub fn gather_row(&self, row: &super::ProbeRow) -> super::ProbeRow {
        let Some(m) = row
            .material
            .and_then(|m| self.results.materials.get(m as usize))
        else {
            return *row;
        };
        let n = row.normal.normalize_or_zero();
        let lift = 1e-3 * self.results.grid.voxel_size;
        let h = self.irradiance(row.point + n * lift, n);
        super::ProbeRow {
            radiosity: std::array::from_fn(|c| m.emission[c] + m.reflectance[c] * h[c]),
            irradiance: h,
            ..*row
        }
    }

    /// Number of emitting surfel sides summed one by one.
    pub fn emitter_count(&self) -> usize {
        self.emitters.len()
    }

    /// Number of bounce directions (both senses).
    pub fn direction_count(&self) -> usize {
        self.directions.len()
    }

    /// The irradiance (RGB, units of `Ke`) on a sensor at `point` (world units) facing `normal`.
    pub fn irradiance(&self, point: DVec3, normal: DVec3) -> [f64; 3] {
        let p = self.results.grid.to_voxel_units(point);
        let n = normal.normalize_or_zero();
        let mut h = [0.0; 3];
        if n == DVec3::ZERO || !p.is_finite() {
            return h;
        }
        let mut norm = 0.0;
        for &(d, w) in &self.directions {
            let c = n.dot(d);
            if c <= 0.0 {
                continue;
            }
            norm += w * c;
            if let Some(hit) = self.cast(p, d, f64::INFINITY) {
                if self.emits[hit.record][hit.side] {
                    continue;
                }
                let b = self.results.records[hit.record].radiosity[hit.side];
                for ch in 0..3 {
                    h[ch] += w * c * b[ch] as f64;
                }
            }
        }
        if norm > 0.0 {
            for v in &mut h {
                *v /= norm;
            }
        }
        for e in &self.emitters {
            let to = e.point - p;
            let r2 = to.length_squared();
            if r2 == 0.0 {
                continue;
            }
            let u = to / r2.sqrt();
            let (cos_sensor, cos_emitter) = (n.dot(u), -e.normal.dot(u));
            if cos_sensor <= 0.0 || cos_emitter <= 0.0 {
                continue;
            }
            if !self.sees(p, u, r2.sqrt(), e.voxel) {
                continue;
            }
            let g = cos_sensor * cos_emitter / (PI * r2);
            for (v, power) in h.iter_mut().zip(e.power) {
                *v += power * g;
            }
        }
        h
    }

    /// Whether the ray from `p` along `u` reaches the voxel `target` (at distance about `r`)
    /// before meeting a surface elsewhere.
    fn sees(&self, p: DVec3, u: DVec3, r: f64, target: [i32; 3]) -> bool {
        match self.cast(p, u, r + 2.0) {
            None => true,
            Some(hit) => self.results.records[hit.record].voxel == target || hit.t >= r - 1e-9,
        }
    }

    /// The first surfel side the ray from `p` (voxel units) along unit `d` meets within
    /// `max_t`, if any.
    pub fn cast(&self, p: DVec3, d: DVec3, max_t: f64) -> Option<Hit> {
        // Clip the ray to the grid's box.
        let (mut t0, mut t1) = (START, max_t);
        for a in 0..3 {
            let (lo, hi) = (self.low[a] as f64, self.high[a] as f64);
            if d[a] == 0.0 {
                if p[a] < lo || p[a] > hi {
                    return None;
                }
            } else {
                let (ta, tb) = ((lo - p[a]) / d[a], (hi - p[a]) / d[a]);
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
        }
        if t0 > t1 {
            return None;
        }
        let start = p + d * t0;
        let mut cell =
            [0usize, 1, 2].map(|a| (start[a].floor() as i32).clamp(self.low[a], self.high[a] - 1));
        let step = [0usize, 1, 2].map(|a| if d[a] > 0.0 { 1 } else { -1 });
        // Distance along the ray to the next cell boundary on each axis, and between two.
        let mut next = [0.0f64; 3];
        let mut delta = [f64::INFINITY; 3];
        for a in 0..3 {
            if d[a] != 0.0 {
                let boundary = if d[a] > 0.0 {
                    cell[a] as f64 + 1.0
                } else {
                    cell[a] as f64
                };
                next[a] = (boundary - p[a]) / d[a];
                delta[a] = 1.0 / d[a].abs();
            } else {
                next[a] = f64::INFINITY;
            }
        }
        loop {
            // The planes of the box's outer voxels lie on its faces: a crossing there may come
            // out a rounding past `t1`, so the cell's test takes the caller's limit.
            let empty = self.occupied.as_ref().is_some_and(|bits| {
                let bit = bit_of(self.low, self.high, cell);
                bits[bit / 64] >> (bit % 64) & 1 == 0
            });
            if !empty {
                if let Some(hit) = self.hit_in(cell, p, d, max_t) {
                    return Some(hit);
                }
            }
            let a = if next[0] <= next[1] && next[0] <= next[2] {
                0
            } else if next[1] <= next[2] {
                1
            } else {
                2
            };
            if next[a] > t1 {
                return None;
            }
            cell[a] += step[a];
            if cell[a] < self.low[a] || cell[a] >= self.high[a] {
                return None;
            }
            next[a] += delta[a];
        }
    }

    /// The nearest crossing of the ray with a plane of a surfel of `cell` that lies inside the
    /// cell, at a distance between [`START`] and `max_t`.
    fn hit_in(&self, cell: [i32; 3], p: DVec3, d: DVec3, max_t: f64) -> Option<Hit> {
        let records = self.cells.get(&packed_voxel(cell)?)?;
        let mut best: Option<Hit> = None;
        let slack = 1e-6;
        for &k in records {
            let r = &self.results.records[k as usize];
            let m = r.side_normal(FRONT);
            let along = m.dot(d);
            if along == 0.0 {
                continue;
            }
            let t = m.dot(r.position() - p) / along;
            if !(START..=max_t).contains(&t) || best.is_some_and(|b| b.t <= t) {
                continue;
            }
            // On the piece: inside its bounding box in the voxel (a piece a few centimetres tall,
            // a desk's edge, does not stop rays that pass over it through its voxel).
            let x = p + d * t;
            let inside = (0..3).all(|a| {
                let lo = cell[a] as f64;
                x[a] >= lo + r.extent[0][a] as f64 - slack
                    && x[a] <= lo + r.extent[1][a] as f64 + slack
            });
            if inside {
                // The side whose normal faces back along the ray sends light to `p`.
                let side = if along < 0.0 { FRONT } else { BACK };
                best = Some(Hit {
                    record: k as usize,
                    side,
                    t,
                });
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::results::SideMaterial;
    use crate::output::testutil;
    use crate::solve::Solution;

    #[test]
    fn default_directions_grow_with_the_square_of_the_resolution_between_bounds() {
        assert_eq!(directions_for([32, 10, 20]), DIRECTIONS_AT_64);
        assert_eq!(directions_for([30, 64, 12]), 2000);
        assert_eq!(directions_for([128, 40, 90]), 8000);
        assert_eq!(directions_for([100, 192, 60]), 18_000);
        assert_eq!(directions_for([256, 256, 256]), MOST_DIRECTIONS);
        assert_eq!(directions_for([1024, 5, 5]), MOST_DIRECTIONS);
    }

    /// A closed box of uniform radiosity `b` (a furnace seen from inside): any sensor inside
    /// receives `b`, whatever it faces.
    #[test]
    fn a_sensor_inside_a_uniform_box_receives_its_radiosity() {
        let n = 8;
        let mut surfels = Vec::new();
        for i in 0..n {
            for j in 0..n {
                // The six walls, facing in.
                let c = [i, j];
                surfels.push(testutil::surfel(
                    [c[0], c[1], 0],
                    [0.5, 0.5, 0.0],
                    [0.0, 0.0, 1.0],
                    1.0,
                ));
                surfels.push(testutil::surfel(
                    [c[0], c[1], n - 1],
                    [0.5, 0.5, 1.0],
                    [0.0, 0.0, -1.0],
                    1.0,
                ));
                surfels.push(testutil::surfel(
                    [c[0], 0, c[1]],
                    [0.5, 0.0, 0.5],
                    [0.0, 1.0, 0.0],
                    1.0,
                ));
                surfels.push(testutil::surfel(
                    [c[0], n - 1, c[1]],
                    [0.5, 1.0, 0.5],
                    [0.0, -1.0, 0.0],
                    1.0,
                ));
                surfels.push(testutil::surfel(
                    [0, c[0], c[1]],
                    [0.0, 0.5, 0.5],
                    [1.0, 0.0, 0.0],
                    1.0,
                ));
                surfels.push(testutil::surfel(
                    [n - 1, c[0], c[1]],
                    [1.0, 0.5, 0.5],
                    [-1.0, 0.0, 0.0],
                    1.0,
                ));
            }
        }
        let radiosity = vec![[[2.0, 3.0, 4.0], [0.0; 3]]; surfels.len()];
        let set = testutil::set_of(surfels, 0.5);
        let solution = Solution {
            radiosity,
            stats: Default::default(),
        };
        let results = Results::from_solution(&set, &solution).unwrap();
        let field = SensorField::new(&results, 200);
        for (p, normal) in [
            (DVec3::new(4.0, 4.0, 4.0), DVec3::Y),
            (DVec3::new(1.3, 6.2, 2.7), DVec3::new(1.0, -2.0, 0.5)),
            (DVec3::new(0.01, 4.0, 4.0), DVec3::X),
        ] {
            let h = field.irradiance(results.grid.to_world(p), normal);
            for (got, want) in h.iter().zip([2.0, 3.0, 4.0]) {
                assert!((got - want).abs() < 1e-9 * want, "{p} {normal}: {h:?}");
            }
        }
    }

    /// One emitting square seen from a point on its axis: the emitter sum is the exact form
    /// factor of a square to a parallel point, `B F`.
    #[test]
    fn an_emitter_is_summed_as_its_form_factor() {
        let n = 40;
        let mut surfels = Vec::new();
        for i in 0..n {
            for j in 0..n {
                let mut s = testutil::surfel([i, j, 0], [0.5, 0.5, 0.5], [0.0, 0.0, -1.0], 1.0);
                s.material = [1, 0];
                surfels.push(s);
            }
        }
        let radiosity = vec![[[1.0; 3], [0.0; 3]]; surfels.len()];
        let mut set = testutil::set_of(surfels, 1.0);
        set.materials
            .push(crate::scene::Material::new("lamp", [0.0; 3], [1.0; 3]));
        let solution = Solution {
            radiosity,
            stats: Default::default(),
        };
        let results = Results::from_solution(&set, &solution).unwrap();
        assert_eq!(
            results.materials[1],
            SideMaterial {
                reflectance: [0.0; 3],
                emission: [1.0; 3]
            }
        );
        let field = SensorField::new(&results, 50);
        // 10 voxels under the square's centre (voxel units 20, 20, 0.5), facing up at it.
        let p = DVec3::new(20.0, 20.0, -9.5);
        let h = field.irradiance(results.grid.to_world(p), DVec3::Z);
        // Form factor of a square of half-side a at distance c, on its axis.
        let (a, c) = (20.0f64, 10.0f64);
        let x = a / c;
        let exact = 2.0 / PI * (2.0 * x / (1.0 + x * x).sqrt() * (x / (1.0 + x * x).sqrt()).atan());
        assert!((h[0] - exact).abs() < 0.01 * exact, "{} vs {exact}", h[0]);
    }
}

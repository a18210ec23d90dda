//! The direction set: integer vectors on the surface of the cube `max(|a|, |b|, |c|) = N`.
//!
//! Every integer point of that surface is a direction; its cell is the unit square around it on
//! the cube face (cut at the face's edges, so an edge point's cell lies on two faces and a corner's
//! on three), and its weight is the exact solid angle of that cell seen from the origin. The cells
//! tile the cube surface, so the weights add up to `4 pi` (to rounding). There are `24 N^2 + 2`
//! directions; `s` and `-s` share one discrete-line partition, so a [`DirectionSet`] stores one
//! *line direction* per pair (`12 N^2 + 1` of them), and its weight is the weight of each of `s` and
//! `-s` (they are equal by symmetry).
//!
//! Line directions are ordered by octant (sign pattern of the vector) and, inside an octant, along a
//! serpentine walk of the cube face, so that consecutive directions are close (paper, section 4.2).

use glam::DVec3;
use std::collections::HashMap;
use std::f64::consts::PI;

/// One line direction: the integer vector `s` (its partner `-s` is implied).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Direction {
    /// Integer vector, normalised so that its last non-zero component is positive.
    pub vector: [i64; 3],
    /// Unit vector along `vector`.
    pub unit: DVec3,
    /// Solid angle (steradians) of the cell of `s`; the cell of `-s` has the same.
    pub solid_angle: f64,
}

/// A set of line directions covering the sphere.
#[derive(Clone, Debug)]
pub struct DirectionSet {
    /// Half-size `N` of the cube whose surface points are the directions.
    pub cube_half_size: u32,
    pub directions: Vec<Direction>,
}

/// Solid angle subtended at the origin by the rectangle `[x1, x2] x [y1, y2]` on the plane at
/// distance `d` (perpendicular to the view axis). Uses the corner function
/// `F(x, y) = atan(x y / (d sqrt(x^2 + y^2 + d^2)))`, exact for axis-aligned rectangles.
fn rectangle_solid_angle(x1: f64, x2: f64, y1: f64, y2: f64, d: f64) -> f64 {
    let f = |x: f64, y: f64| (x * y / (d * (x * x + y * y + d * d).sqrt())).atan();
    f(x2, y2) - f(x1, y2) - f(x2, y1) + f(x1, y1)
}

impl DirectionSet {
    /// Directions on the cube of half-size `n >= 1`: `12 n^2 + 1` line directions.
    pub fn cube(n: u32) -> Self {
        let n = n.max(1) as i64;
        let nf = n as f64;
        let mut weights: HashMap<[i64; 3], f64> = HashMap::new();
        for axis in 0..3 {
            for sign in [-1i64, 1] {
                for u in -n..=n {
                    for v in -n..=n {
                        let (u1, u2) = ((u as f64 - 0.5).max(-nf), (u as f64 + 0.5).min(nf));
                        let (v1, v2) = ((v as f64 - 0.5).max(-nf), (v as f64 + 0.5).min(nf));
                        let w = rectangle_solid_angle(u1, u2, v1, v2, nf);
                        let mut p = [0i64; 3];
                        p[axis] = sign * n;
                        p[(axis + 1) % 3] = u;
                        p[(axis + 2) % 3] = v;
                        *weights.entry(p).or_insert(0.0) += w;
                    }
                }
            }
        }
        let mut directions: Vec<Direction> = weights
            .into_iter()
            .filter(|(p, _)| is_canonical(*p))
            .map(|(p, w)| Direction {
                vector: p,
                unit: DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64).normalize(),
                solid_angle: w,
            })
            .collect();
        directions.sort_by_key(|d| walk_key(d.vector, n));
        DirectionSet {
            cube_half_size: n as u32,
            directions,
        }
    }

    /// The cube direction set whose line-direction count `12 N^2 + 1` is closest to `count`.
    pub fn with_count(count: usize) -> Self {
        let n = (((count.max(13) - 1) as f64) / 12.0)
            .sqrt()
            .round()
            .max(1.0) as u32;
        Self::cube(n)
    }

    pub fn len(&self) -> usize {
        self.directions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.directions.is_empty()
    }

    /// Sum of the solid angles of all `s` and `-s`: `4 pi` up to rounding.
    pub fn total_solid_angle(&self) -> f64 {
        2.0 * self.directions.iter().map(|d| d.solid_angle).sum::<f64>()
    }

    /// `S(n) = sum over s with n.s > 0 of (n.s) W(s) / pi` for a unit normal `n`: the fraction of
    /// the hemisphere's cosine-weighted measure the set reproduces (1 for a perfect set).
    pub fn cosine_sum(&self, normal: DVec3) -> f64 {
        self.directions
            .iter()
            .map(|d| normal.dot(d.unit).abs() * d.solid_angle)
            .sum::<f64>()
            / PI
    }
}

/// One of each pair `p`, `-p`: the last non-zero component is positive.
fn is_canonical(p: [i64; 3]) -> bool {
    if p[2] != 0 {
        p[2] > 0
    } else if p[1] != 0 {
        p[1] > 0
    } else {
        p[0] > 0
    }
}

/// Sort key: octant of the vector first, then a serpentine walk over the cube face so that
/// neighbours in the order are neighbours on the sphere.
fn walk_key(p: [i64; 3], n: i64) -> (u8, u8, i64, i64) {
    let octant = ((p[0] < 0) as u8) | (((p[1] < 0) as u8) << 1) | (((p[2] < 0) as u8) << 2);
    let main = (0..3).max_by_key(|&k| (p[k].abs(), k)).unwrap_or(2);
    let (u, v) = (p[(main + 1) % 3] + n, p[(main + 2) % 3] + n);
    let v_walk = if u % 2 == 0 { v } else { -v };
    (octant, main as u8, u, v_walk)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_and_total_solid_angle() {
        for n in [1u32, 2, 5, 20] {
            let set = DirectionSet::cube(n);
            assert_eq!(set.len(), 12 * (n as usize).pow(2) + 1);
            let total = set.total_solid_angle();
            assert!((total - 4.0 * PI).abs() < 1e-9, "n={n}: {total}");
        }
    }

    #[test]
    fn weights_are_positive_and_near_uniform() {
        let set = DirectionSet::cube(10);
        let mean = 2.0 * PI / set.len() as f64;
        for d in &set.directions {
            assert!(d.solid_angle > 0.0);
            // Cells at the face centre are the largest, corner cells a quarter-ish of that.
            assert!(d.solid_angle < 3.0 * mean && d.solid_angle > 0.05 * mean);
        }
    }

    #[test]
    fn with_count_reaches_twenty_thousand() {
        assert!(DirectionSet::with_count(20_000).len() >= 19_000);
        assert_eq!(DirectionSet::with_count(50).len(), 49);
        assert_eq!(DirectionSet::with_count(0).len(), 13);
    }

    #[test]
    fn cosine_sum_is_close_to_one() {
        let set = DirectionSet::cube(8);
        for n in [
            DVec3::X,
            DVec3::new(1.0, 2.0, 3.0).normalize(),
            DVec3::new(-1.0, 0.5, 0.0).normalize(),
        ] {
            let s = set.cosine_sum(n);
            assert!((s - 1.0).abs() < 0.02, "{s}");
        }
    }
}

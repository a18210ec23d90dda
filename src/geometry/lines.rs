//! Discrete lines: which line `(i, j)` of a direction a voxel belongs to.
//!
//! For a direction `(a, b, c)` whose main axis is the third (`|c|` largest, and made positive by
//! negating the whole vector, which names the same family of lines), voxel `(x, y, z)` lies on line
//! `i = floor((c x - a z) / c)`, `j = floor((c y - b z) / c)` (paper section 2.2). Other main axes
//! permute the coordinates. Each voxel lies on exactly one line, each line holds exactly one voxel
//! per layer of the main axis, and consecutive voxels of a line are 26-neighbours.
//!
//! Because `c x / c` is exact, `i = x + floor(-a z / c)`: [`LineFrame`] tabulates the per-layer
//! offsets once per direction so that the dense line index of a voxel inside the grid costs one
//! table look-up and a multiply-add. All arithmetic is in 64-bit integers.

/// Floor division for a positive divisor.
pub fn floor_div(n: i64, d: i64) -> i64 {
    debug_assert!(d > 0);
    n.div_euclid(d)
}

/// The exact line `(i, j)` of a voxel for direction `vector`, with no grid assumed.
pub fn line_of(vector: [i64; 3], voxel: [i64; 3]) -> (i64, i64) {
    let (main, u, v) = axes(vector);
    let sign = vector[main].signum();
    let (a, b, c) = (sign * vector[u], sign * vector[v], sign * vector[main]);
    (
        floor_div(c * voxel[u] - a * voxel[main], c),
        floor_div(c * voxel[v] - b * voxel[main], c),
    )
}

/// Main axis (largest absolute component; the last one on ties) and the two others.
pub fn axes(vector: [i64; 3]) -> (usize, usize, usize) {
    let mut main = 2;
    for k in [1, 0] {
        if vector[k].abs() > vector[main].abs() {
            main = k;
        }
    }
    (main, (main + 1) % 3, (main + 2) % 3)
}

/// Dense line numbering of one direction over a grid of `dims` voxels.
#[derive(Clone, Debug)]
pub struct LineFrame {
    pub main: usize,
    pub u: usize,
    pub v: usize,
    /// Number of line rows along `i` and columns along `j`.
    pub ni: u64,
    pub nj: u64,
    /// Number of lines: `ni * nj`.
    pub line_count: u64,
    /// Per layer of the main axis: `(off_u - min_u) * nj + (off_v - min_v)`.
    layer_offset: Vec<u64>,
    /// Per layer of the main axis: `(off_u - min_u, off_v - min_v)`, so that a voxel's line is
    /// `i = voxel[u] + shift.0`, `j = voxel[v] + shift.1`.
    layer_shift: Vec<(u64, u64)>,
}

impl LineFrame {
    pub fn new(vector: [i64; 3], dims: [u32; 3]) -> Self {
        let (main, u, v) = axes(vector);
        let sign = vector[main].signum();
        let (a, b, c) = (sign * vector[u], sign * vector[v], sign * vector[main]);
        let layers = dims[main] as i64;
        let off_u: Vec<i64> = (0..layers).map(|z| floor_div(-a * z, c)).collect();
        let off_v: Vec<i64> = (0..layers).map(|z| floor_div(-b * z, c)).collect();
        let (min_u, max_u) = min_max(&off_u);
        let (min_v, max_v) = min_max(&off_v);
        let ni = dims[u] as u64 + (max_u - min_u) as u64;
        let nj = dims[v] as u64 + (max_v - min_v) as u64;
        let layer_shift: Vec<(u64, u64)> = off_u
            .iter()
            .zip(&off_v)
            .map(|(&ou, &ov)| ((ou - min_u) as u64, (ov - min_v) as u64))
            .collect();
        let layer_offset = layer_shift.iter().map(|&(su, sv)| su * nj + sv).collect();
        LineFrame {
            main,
            u,
            v,
            ni,
            nj,
            line_count: ni * nj,
            layer_offset,
            layer_shift,
        }
    }

    /// `(i, j)` shifts of layer `layer` of the main axis: a voxel of that layer lies on line
    /// `(voxel[u] + shift.0, voxel[v] + shift.1)`, numbered `i * nj + j`.
    #[inline]
    pub fn layer_shift(&self, layer: usize) -> (u64, u64) {
        self.layer_shift[layer]
    }

    /// Dense line index of a voxel inside the grid.
    #[inline]
    pub fn line_index(&self, voxel: [i32; 3]) -> u64 {
        voxel[self.u] as u64 * self.nj
            + voxel[self.v] as u64
            + self.layer_offset[voxel[self.main] as usize]
    }
}

fn min_max(values: &[i64]) -> (i64, i64) {
    let min = values.iter().copied().min().unwrap_or(0);
    let max = values.iter().copied().max().unwrap_or(0);
    (min, max)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn dense_index_matches_exact_line(a in -9i64..=9, b in -9i64..=9, c in -9i64..=9,
                                          x in 0i32..13, y in 0i32..11, z in 0i32..7,
                                          x2 in 0i32..13, y2 in 0i32..11, z2 in 0i32..7) {
            prop_assume!(a != 0 || b != 0 || c != 0);
            let dims = [13, 11, 7];
            let frame = LineFrame::new([a, b, c], dims);
            let p = [x, y, z];
            let q = [x2, y2, z2];
            let same_exact = line_of([a, b, c], p.map(i64::from)) == line_of([a, b, c], q.map(i64::from));
            let same_dense = frame.line_index(p) == frame.line_index(q);
            prop_assert_eq!(same_exact, same_dense);
            prop_assert!(frame.line_index(p) < frame.line_count);
        }

        #[test]
        fn one_voxel_per_layer_and_26_connected(a in -6i64..=6, b in -6i64..=6, c in -6i64..=6,
                                                x in -50i64..50, y in -50i64..50, z in -50i64..50) {
            prop_assume!(a != 0 || b != 0 || c != 0);
            let s = [a, b, c];
            let (main, _, _) = axes(s);
            // Walking one layer along the main axis from a voxel on a line reaches exactly one
            // voxel of the same line among the 9 candidates, a 26-neighbour.
            let p = [x, y, z];
            let line = line_of(s, p);
            let mut found = 0;
            for du in -1..=1 {
                for dv in -1..=1 {
                    let mut q = p;
                    q[main] += 1;
                    q[(main + 1) % 3] += du;
                    q[(main + 2) % 3] += dv;
                    if line_of(s, q) == line { found += 1; }
                }
            }
            prop_assert_eq!(found, 1);
        }
    }

    #[test]
    fn far_from_origin_matches_wide_arithmetic() {
        // Coordinates near 2^40 with direction components near 20 stay far inside i64; check
        // against 128-bit arithmetic that nothing wrapped.
        let s = [20i64, -19, 20];
        for far in [
            [1i64 << 40, -(1i64 << 40), 1i64 << 39],
            [-(1i64 << 41) + 7, 3, -(1i64 << 40) - 1],
        ] {
            let (i, j) = line_of(s, far);
            let (main, u, v) = axes(s);
            let sign = s[main].signum() as i128;
            let (a, b, c) = (
                sign * s[u] as i128,
                sign * s[v] as i128,
                sign * s[main] as i128,
            );
            let wide_i = (c * far[u] as i128 - a * far[main] as i128).div_euclid(c);
            let wide_j = (c * far[v] as i128 - b * far[main] as i128).div_euclid(c);
            assert_eq!((i as i128, j as i128), (wide_i, wide_j));
        }
    }
}

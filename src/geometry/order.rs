//! Lexicographic orders in which the voxels of every discrete line come out sorted along the
//! line's direction (paper, sections 2.2 and 4.2).
//!
//! Consecutive voxels of a line for direction `s = (a, b, c)` differ by a step whose components
//! are 0 or the sign of the matching component of `s` (and exactly that sign on the main axis).
//! So any lexicographic order whose per-axis directions match the signs of `s` lists each line's
//! voxels in increasing position along `s`, whatever the priority of the axes. We use the priority
//! `(z, y, x)`. Line directions are stored with `c >= 0` (see `directions`), so four orders
//! suffice, one per sign pair of `(a, b)`; a zero component can use either sign.

/// Index (0..4) of the order to traverse for a line direction stored with `vector[2] >= 0`.
pub fn order_of(vector: [i64; 3]) -> usize {
    debug_assert!(vector[2] >= 0);
    (vector[0] < 0) as usize | (((vector[1] < 0) as usize) << 1)
}

/// Per-axis signs `(sx, sy, sz)` of order `order`.
pub fn signs(order: usize) -> [i64; 3] {
    [
        if order & 1 != 0 { -1 } else { 1 },
        if order & 2 != 0 { -1 } else { 1 },
        1,
    ]
}

/// Sort key of a voxel in order `order`: compare keys to compare positions.
#[inline]
pub fn sort_key(order: usize, voxel: [i32; 3]) -> (i64, i64, i64) {
    let s = signs(order);
    (
        s[2] * voxel[2] as i64,
        s[1] * voxel[1] as i64,
        s[0] * voxel[0] as i64,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::lines::line_of;

    #[test]
    fn every_line_is_sorted_along_its_direction() {
        let dirs = [[3, -2, 5], [-4, -4, 1], [1, 7, 0], [-2, 0, 0], [0, -3, 2]];
        let mut voxels = Vec::new();
        for x in 0..9 {
            for y in 0..8 {
                for z in 0..7 {
                    voxels.push([x, y, z]);
                }
            }
        }
        for s in dirs {
            let order = order_of(s);
            let mut sorted = voxels.clone();
            sorted.sort_by_key(|v| sort_key(order, *v));
            let mut last_pos: std::collections::HashMap<(i64, i64), f64> = Default::default();
            for v in sorted {
                let line = line_of(s, v.map(i64::from));
                let along = v[0] as f64 * s[0] as f64
                    + v[1] as f64 * s[1] as f64
                    + v[2] as f64 * s[2] as f64;
                if let Some(prev) = last_pos.insert(line, along) {
                    assert!(along > prev, "line {line:?} of {s:?} not sorted");
                }
            }
        }
    }
}

//! An independent ray-marching oracle for the discrete lines.
//!
//! Visibility in voxrad rests on one structure: per direction, every surfel sits on one discrete
//! line, the line's list is sorted along the direction, and the partner search walks that list.
//! If the list of a line skipped a voxel, held one twice, or came out of order, light would leak
//! or be shadowed and no energy test would say exactly where. So this file checks the lists built
//! by `voxrad::solve::dispatch::dispatch` (over the lexicographic orders of
//! `voxrad::geometry::order`, exactly as `solve::jacobi` builds them) against a completely
//! separate computation: from every occupied voxel, march the discrete line with an incremental
//! integer walk (3D Bresenham along the main axis with two error accumulators, the start residuals
//! derived from the voxel itself; no call to `line_of` or `LineFrame`) and find the first occupied
//! voxel ahead along `s` and behind along `-s`. Those must be the next and previous *different
//! voxel* on the surfel's list (voxels hold one to three surfels, so a list holds runs of equal
//! voxels). The lists must also be identical for every thread count, and the comparison itself
//! must be able to fail: a table with one neighbour deliberately skipped is rejected.
//!
//! Voxel sets are random (a seeded splitmix64, so every run checks the same cases): sparse and
//! dense clouds, and thick random planes (the shape a tunnel-free voxelization produces), on grids
//! up to 24^3, with all directions of `DirectionSet::cube(1..=4)`, the axes, the diagonals and
//! random integer vectors with components up to 11.

use std::collections::{HashMap, HashSet};
use voxrad::geometry::directions::DirectionSet;
use voxrad::geometry::lines::LineFrame;
use voxrad::geometry::order;
use voxrad::solve::dispatch::{dispatch, Lines, OrderedEntry};

type Voxel = [i32; 3];

/// Next and previous different voxel of a surfel along a direction (`None`: nothing there).
type Neighbours = (Option<Voxel>, Option<Voxel>);

/// splitmix64: a tiny deterministic PRNG, so the test needs no crate and never changes its cases.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }

    fn int(&mut self, lo: i64, hi: i64) -> i64 {
        lo + self.below((hi - lo + 1) as u64) as i64
    }

    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A test case: grid dimensions and the voxel of every surfel (a voxel may appear up to three
/// times, like an edge or corner voxel holding two or three surfels).
struct Case {
    name: String,
    dims: [u32; 3],
    surfel_voxels: Vec<Voxel>,
}

impl Case {
    fn occupancy(&self) -> HashSet<Voxel> {
        self.surfel_voxels.iter().copied().collect()
    }
}

/// Adds each distinct voxel once, then repeats some of them (one or two extra surfels), and
/// shuffles the surfel order so that surfel indices say nothing about position.
fn make_case(name: String, dims: [u32; 3], voxels: HashSet<Voxel>, rng: &mut Rng) -> Case {
    let mut distinct: Vec<Voxel> = voxels.into_iter().collect();
    distinct.sort();
    let mut surfel_voxels = Vec::new();
    for v in distinct {
        surfel_voxels.push(v);
        let extra = match rng.below(10) {
            0 => 2,
            1 | 2 => 1,
            _ => 0,
        };
        for _ in 0..extra {
            surfel_voxels.push(v);
        }
    }
    for k in (1..surfel_voxels.len()).rev() {
        let j = rng.below(k as u64 + 1) as usize;
        surfel_voxels.swap(k, j);
    }
    Case {
        name,
        dims,
        surfel_voxels,
    }
}

fn random_dims(rng: &mut Rng, lo: i64, hi: i64) -> [u32; 3] {
    [0; 3].map(|_| rng.int(lo, hi) as u32)
}

fn random_voxel(rng: &mut Rng, dims: [u32; 3]) -> Voxel {
    [0, 1, 2].map(|k| rng.below(dims[k] as u64) as i32)
}

/// Sparse clouds, dense clouds and thick random planes.
fn cases() -> Vec<Case> {
    let mut rng = Rng(0x05EE_D0F0_AC1E);
    let mut out = Vec::new();
    for k in 0..4 {
        let dims = random_dims(&mut rng, 12, 24);
        let mut set = HashSet::new();
        let count = rng.int(200, 400);
        while (set.len() as i64) < count {
            set.insert(random_voxel(&mut rng, dims));
        }
        out.push(make_case(format!("sparse {k}"), dims, set, &mut rng));
    }
    for k in 0..3 {
        let dims = random_dims(&mut rng, 5, 9);
        let fill = 0.3 + 0.4 * rng.unit();
        let mut set = HashSet::new();
        for x in 0..dims[0] as i32 {
            for y in 0..dims[1] as i32 {
                for z in 0..dims[2] as i32 {
                    if rng.unit() < fill {
                        set.insert([x, y, z]);
                    }
                }
            }
        }
        out.push(make_case(format!("dense {k}"), dims, set, &mut rng));
    }
    for k in 0..4 {
        // Voxels whose centre lies within a slab of half-thickness 0.5..1.2 around a random plane
        // through the grid: one to three voxels thick along oblique lines.
        let dims = random_dims(&mut rng, 14, 24);
        let n = [0; 3].map(|_| rng.unit() * 2.0 - 1.0);
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().max(1e-9);
        let n = n.map(|c| c / len);
        let centre = [0, 1, 2].map(|a| dims[a] as f64 * (0.3 + 0.4 * rng.unit()));
        let half = 0.5 + 0.7 * rng.unit();
        let mut set = HashSet::new();
        for x in 0..dims[0] as i32 {
            for y in 0..dims[1] as i32 {
                for z in 0..dims[2] as i32 {
                    let p = [x, y, z];
                    let d: f64 = (0..3).map(|a| (p[a] as f64 + 0.5 - centre[a]) * n[a]).sum();
                    if d.abs() <= half {
                        set.insert(p);
                    }
                }
            }
        }
        out.push(make_case(format!("plane {k}"), dims, set, &mut rng));
    }
    out
}

/// Stored form of a line direction: the last non-zero component positive (what
/// `DirectionSet` stores and what `order::order_of` expects).
fn canonical(mut s: [i64; 3]) -> [i64; 3] {
    let last = if s[2] != 0 {
        s[2]
    } else if s[1] != 0 {
        s[1]
    } else {
        s[0]
    };
    if last < 0 {
        s = s.map(|c| -c);
    }
    s
}

fn directions() -> Vec<[i64; 3]> {
    let mut set: Vec<[i64; 3]> = Vec::new();
    for n in 1..=4 {
        set.extend(DirectionSet::cube(n).directions.iter().map(|d| d.vector));
    }
    set.extend([
        [1, 0, 0],
        [0, 1, 0],
        [0, 0, 1],
        [1, 1, 1],
        [-1, 1, 1],
        [1, -1, 1],
        [-1, -1, 1],
        [1, 1, 0],
        [-1, 1, 0],
        [1, 0, 1],
        [-1, 0, 1],
        [0, 1, 1],
        [0, -1, 1],
        [3, 3, 1],
        [-5, 2, 5],
    ]);
    let mut rng = Rng(0xD1EC7);
    while set.len() < 380 {
        let s = [0; 3].map(|_| rng.int(-11, 11));
        if s != [0, 0, 0] {
            set.push(canonical(s));
        }
    }
    let mut seen = HashSet::new();
    set.retain(|s| seen.insert(*s));
    set
}

/// The first occupied voxel met when marching the discrete line of `s` from `start`, ahead
/// (`forward`) or behind, inside the grid. The walk is incremental: one step per layer of the
/// main axis, the two other coordinates advanced by Bresenham error accumulators.
fn march(
    occupied: &HashSet<Voxel>,
    dims: [u32; 3],
    s: [i64; 3],
    start: Voxel,
    forward: bool,
) -> Option<Voxel> {
    // Main axis: largest |component|, the last one on ties (the brief's "|c| largest").
    let mut m = 2;
    for k in [1, 0] {
        if s[k].abs() > s[m].abs() {
            m = k;
        }
    }
    let (u, v) = ((m + 1) % 3, (m + 2) % 3);
    // The same family of lines with the main component positive.
    let sign = s[m].signum();
    let (a, b, c) = (sign * s[u], sign * s[v], sign * s[m]);
    let p = start.map(i64::from);
    // Residuals of the start voxel: e_u = (c x - a z) mod c, e_v = (c y - b z) mod c, in [0, c).
    // The voxel (x, y, z) belongs to a line exactly when those stay in [0, c) as z moves.
    let mut e_u = (c * p[u] - a * p[m]).rem_euclid(c);
    let mut e_v = (c * p[v] - b * p[m]).rem_euclid(c);
    let (mut x, mut y, mut z) = (p[u], p[v], p[m]);
    let inside = |x: i64, y: i64, z: i64| {
        (0..dims[u] as i64).contains(&x)
            && (0..dims[v] as i64).contains(&y)
            && (0..dims[m] as i64).contains(&z)
    };
    // In the (c > 0) frame a step raises z; that is a step along s if s's own main component is
    // positive, along -s otherwise.
    let dz = if forward { sign } else { -sign };
    loop {
        // z -> z + dz changes c x - a z by -a dz; bring the residual back into [0, c) by moving x.
        e_u -= a * dz;
        if e_u < 0 {
            e_u += c;
            x += 1;
        } else if e_u >= c {
            e_u -= c;
            x -= 1;
        }
        e_v -= b * dz;
        if e_v < 0 {
            e_v += c;
            y += 1;
        } else if e_v >= c {
            e_v -= c;
            y -= 1;
        }
        z += dz;
        debug_assert!((0..c).contains(&e_u) && (0..c).contains(&e_v));
        if !inside(x, y, z) {
            // Lines are monotone in every coordinate: once out of the grid, always out.
            return None;
        }
        let mut q = [0i64; 3];
        q[u] = x;
        q[v] = y;
        q[m] = z;
        let q = q.map(|t| t as i32);
        if occupied.contains(&q) {
            return Some(q);
        }
    }
}

/// Builds the lists of direction `s` exactly as the solver does and returns, per surfel, the
/// next and previous different voxel on its list.
fn list_neighbours(case: &Case, s: [i64; 3], threads: usize) -> (Vec<Neighbours>, Lines) {
    let o = order::order_of(s);
    let mut ordered: Vec<OrderedEntry> = case
        .surfel_voxels
        .iter()
        .enumerate()
        .map(|(i, &voxel)| OrderedEntry {
            voxel,
            index: i as u32,
        })
        .collect();
    ordered.sort_by_key(|e| (order::sort_key(o, e.voxel), e.index));
    let frame = LineFrame::new(s, case.dims);
    let mut lines = Lines::default();
    dispatch(&ordered, &frame, threads, &mut lines);
    let voxel = |m: u32| case.surfel_voxels[m as usize];
    let mut out = vec![(None, None); case.surfel_voxels.len()];
    for l in 0..lines.line_count() {
        let line = lines.line(l);
        for (k, &m) in line.iter().enumerate() {
            let here = voxel(m);
            let next = line[k + 1..].iter().map(|&q| voxel(q)).find(|&w| w != here);
            let prev = line[..k]
                .iter()
                .rev()
                .map(|&q| voxel(q))
                .find(|&w| w != here);
            out[m as usize] = (next, prev);
        }
    }
    (out, lines)
}

/// Compares a neighbour table against the oracle; the first disagreement is the error.
fn compare(case: &Case, s: [i64; 3], table: &[Neighbours]) -> Result<(), String> {
    let occupied = case.occupancy();
    // Memoise per voxel: surfels of one voxel share the answer.
    let mut oracle: HashMap<Voxel, Neighbours> = HashMap::new();
    for (k, &v) in case.surfel_voxels.iter().enumerate() {
        let expected = *oracle.entry(v).or_insert_with(|| {
            (
                march(&occupied, case.dims, s, v, true),
                march(&occupied, case.dims, s, v, false),
            )
        });
        if table[k] != expected {
            return Err(format!(
                "{}: direction {s:?}, surfel {k} at voxel {v:?}: lists give (next, previous) = \
                 {:?}, the ray-marching oracle {:?}",
                case.name, table[k], expected
            ));
        }
    }
    Ok(())
}

#[test]
fn marching_finds_the_list_neighbours() {
    let dirs = directions();
    assert!(dirs.len() > 300, "{} directions", dirs.len());
    let mut checked = 0u64;
    let mut with_neighbour = 0u64;
    for case in cases() {
        assert!(!case.surfel_voxels.is_empty(), "{}", case.name);
        for &s in &dirs {
            let (table, _) = list_neighbours(&case, s, 1);
            if let Err(e) = compare(&case, s, &table) {
                panic!("{e}");
            }
            checked += table.len() as u64;
            with_neighbour += table
                .iter()
                .filter(|n| n.0.is_some() || n.1.is_some())
                .count() as u64;
        }
    }
    // The check means something only if many surfels have neighbours at all.
    assert!(checked > 1_000_000, "only {checked} surfel-directions");
    assert!(
        with_neighbour * 4 > checked,
        "only {with_neighbour} of {checked} surfel-directions have a neighbour"
    );
}

#[test]
fn lists_do_not_depend_on_thread_count() {
    let dirs = directions();
    for case in cases() {
        for &s in dirs.iter().step_by(3) {
            let (reference, one) = list_neighbours(&case, s, 1);
            for threads in [2, 3, 5, 8] {
                let (table, lines) = list_neighbours(&case, s, threads);
                assert_eq!(
                    lines.starts, one.starts,
                    "{}: {s:?}, {threads} threads",
                    case.name
                );
                assert_eq!(
                    lines.members, one.members,
                    "{}: {s:?}, {threads} threads",
                    case.name
                );
                assert_eq!(table, reference);
                compare(&case, s, &table).unwrap();
            }
        }
    }
}

#[test]
fn the_oracle_catches_a_skipped_neighbour() {
    // A wrong table, one voxel skipped: a surfel whose next voxel has itself a next voxel gets
    // that one instead. The comparison must reject it, for every case and many directions.
    let dirs = directions();
    let mut caught = 0;
    for case in cases() {
        for &s in dirs.iter().step_by(7) {
            let (mut table, _) = list_neighbours(&case, s, 2);
            compare(&case, s, &table).unwrap();
            let index: HashMap<Voxel, usize> = case
                .surfel_voxels
                .iter()
                .enumerate()
                .map(|(k, &v)| (v, k))
                .collect();
            let victim = (0..table.len()).find_map(|k| {
                let next = table[k].0?;
                let after = table[index[&next]].0?;
                Some((k, after))
            });
            let Some((k, after)) = victim else { continue };
            table[k].0 = Some(after);
            assert!(
                compare(&case, s, &table).is_err(),
                "{}: {s:?}: a skipped voxel went unnoticed",
                case.name
            );
            // And a lost previous neighbour too.
            let (mut table, _) = list_neighbours(&case, s, 2);
            if let Some(k) = (0..table.len()).find(|&k| table[k].1.is_some()) {
                table[k].1 = None;
                assert!(compare(&case, s, &table).is_err());
            }
            caught += 1;
        }
    }
    assert!(caught > 50, "only {caught} wrong tables tried");
}

#[test]
fn the_march_walks_26_connected_lines_one_voxel_per_layer() {
    // Sanity of the oracle itself, on a full grid: marching from a voxel visits, per layer of the
    // main axis, one voxel that is a 26-neighbour of the previous, and the forward and backward
    // walks are inverse (the voxel behind the voxel ahead of v is v).
    let dims = [9u32, 8, 7];
    let mut all = HashSet::new();
    for x in 0..9 {
        for y in 0..8 {
            for z in 0..7 {
                all.insert([x, y, z]);
            }
        }
    }
    for s in directions() {
        for &v in all.iter() {
            if let Some(n) = march(&all, dims, s, v, true) {
                assert!(
                    (0..3).all(|k| (n[k] - v[k]).abs() <= 1),
                    "{s:?} {v:?} {n:?}"
                );
                // The step goes along s, never against it.
                let along: i64 = (0..3).map(|k| (n[k] - v[k]) as i64 * s[k]).sum();
                assert!(along > 0, "{s:?} {v:?} -> {n:?}");
                assert_eq!(march(&all, dims, s, n, false), Some(v), "{s:?} {v:?}");
            }
        }
    }
}

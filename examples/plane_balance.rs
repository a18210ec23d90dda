//! What the senders' balance would do if every plane had it in the iterations, not only the
//! emitters in the direct pass (`solve::direct`): a small solver of its own (no direct pass,
//! links of every direction kept in memory, so small scenes only) that scales, per direction,
//! the light each plane side sends to the power its own rays carry, and divides each receiver's
//! gather by its scaled weights (so a uniform field stays uniform), then prints the power balance
//! `(emitted - absorbed) / emitted` and the mean front-side radiosity by region (the regions of
//! the corridor scene: its corridor is z in [4, 6]).
//!
//! `cargo run --release --example plane_balance SCENE.obj RESOLUTION DIRECTIONS MODE`, MODE:
//! - 0: the plain gather, as the solver has it (its balance is the solver's without the pass);
//! - 1: the scales settled before the iterations by `STEPS` alternations (default 1) of the
//!   senders' scales and the receivers' sums (Sinkhorn's method), the target of a side being the
//!   share its own rays meet;
//! - 2: as 1, the target being the side's whole projected area (light that met nothing sent on);
//! - 3: one alternation per iteration, damped (what a solver could afford without kept links);
//! - 4: one scale per receiver side and one per sender side over all directions (not per plane
//!   and direction), settled by `STEPS` Sinkhorn alternations on the power matrix: each row keeps
//!   the share of its side's hemisphere that meets a surface (a uniform field stays uniform),
//!   each column is brought to the power its side's rays can deliver (light sent toward a piece
//!   of no area, covered by a solid resting on it, is absorbed by nothing and not counted);
//! - 5: in every iteration, one scale per direction and channel: what the receivers' own sides
//!   send along that direction's links (their radiosity) against what they gather through them
//!   (their partners'), so that each direction hands on the power its met rays carry;
//! - 6: as 5, one scale per channel over all directions.
//!
//! It also prints the plane sides whose light goes missing most: what each sends over all
//! directions against what receivers took from it, and the lost power split into the share of
//! the senders' own rays that meets nothing ("unmet") and the difference between what receivers
//! take from a side and what its own rays meet ("unreciprocal": the links are not mutual).
//! `REF=DIR` compares the answer with a path-traced reference (`DIR/reference.csv`, errors as
//! docs/accuracy.md measures them); `GROUP=g` (mode 4) lists the sides of plane group `g` whose
//! rays meet least. `TRACE=1` prints each iteration's relative change. Measured figures:
//! docs/accuracy.md.
use std::collections::HashMap;
use voxrad::geometry::directions::DirectionSet;
use voxrad::geometry::lines::LineFrame;
use voxrad::geometry::order;
use voxrad::solve::dispatch::{dispatch, Lines};
use voxrad::solve::propagate::{find_partners, for_each_link, prop_surfels, LineScratch};
use voxrad::voxel::voxelize::{voxelize, GridSpec};

/// One kept link: receiver `r`'s side `to` gathers `f = |n.s| W/pi share` of partner `p`'s side
/// `from`.
struct L {
    r: u32,
    to: u8,
    p: u32,
    from: u8,
    f: f64,
}

/// Modes 5 and 6: per channel, what the receivers' own sides send along `links` (their
/// radiosity `b`, weighted as their gather weights it) over what they gather through them (their
/// partners'); 1 where nothing is gathered.
fn conserving_scale<'a>(
    links: impl Iterator<Item = &'a L>,
    set: &voxrad::voxel::SurfelSet,
    norm: &[f64],
    b: &[[[f64; 3]; 2]],
) -> [f64; 3] {
    let (mut own, mut got) = ([0f64; 3], [0f64; 3]);
    for l in links {
        let r = l.r as usize;
        let weight = set.surfels[r].area as f64 * l.f / norm[r];
        for c in 0..3 {
            own[c] += weight * b[r][l.to as usize][c];
            got[c] += weight * b[l.p as usize][l.from as usize][c];
        }
    }
    std::array::from_fn(|c| if got[c] > 0.0 { own[c] / got[c] } else { 1.0 })
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let scene = voxrad::scene::obj::load_obj(std::path::Path::new(&a[1])).unwrap();
    let res: u32 = a[2].parse().unwrap();
    let dirs = DirectionSet::with_count(a[3].parse().unwrap());
    let mode: u32 = a[4].parse().unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(res)).unwrap();
    let surfels = prop_surfels(&set);
    let n = surfels.len();
    let cs = voxrad::solve::normalize::cosine_sums(&set.normals, &dirs);
    let norm: Vec<f64> = set
        .surfels
        .iter()
        .map(|s| cs[s.normal_id as usize])
        .collect();
    let entries = voxrad::solve::dispatch::lexicographic_orders(&set);
    let mut lines = Lines::default();
    let mut scratch = LineScratch::default();
    let mut all: Vec<Vec<L>> = Vec::new();
    // Per direction: scale by (group, side).
    let mut scales: Vec<HashMap<(u32, u8), f64>> = Vec::new();
    let mut shift = vec![[0f64; 2]; n];
    for d in &dirs.directions {
        let frame = LineFrame::new(d.vector, set.grid.dims);
        dispatch(&entries[order::order_of(d.vector)], &frame, 1, &mut lines);
        let w = d.solid_angle / std::f64::consts::PI;
        let mut links = Vec::new();
        for l in 0..lines.line_count() {
            let line = lines.line(l);
            if line.len() < 2 {
                continue;
            }
            find_partners(line, &surfels, d.unit, &mut scratch);
            for_each_link(&scratch, d.unit, |k| {
                if k.cosine == 0.0 {
                    return;
                }
                links.push(L {
                    r: line[k.receiver],
                    to: k.to_side as u8,
                    p: line[k.partner],
                    from: k.from_side as u8,
                    f: k.cosine * w * k.share as f64,
                });
            });
        }
        all.push(links);
    }

    // Own power by (direction, group, side).
    let mut own: Vec<HashMap<(u32, u8), f64>> = vec![HashMap::new(); all.len()];
    for (d, links) in all.iter().enumerate() {
        let dd = &dirs.directions[d];
        let w = dd.solid_angle / std::f64::consts::PI;
        if mode == 1 || mode == 3 {
            for l in links {
                let r = l.r as usize;
                *own[d].entry((set.surfels[r].group, l.to)).or_default() +=
                    set.surfels[r].area as f64 * l.f / norm[r];
            }
        } else if mode == 2 {
            for (i, s) in set.surfels.iter().enumerate() {
                let c = voxrad::solve::normalize::cosine(s.normal, dd.unit);
                if c == 0.0 {
                    continue;
                }
                for side in 0..2u8 {
                    *own[d].entry((s.group, side)).or_default() += s.area as f64 * c * w / norm[i];
                }
            }
        }
    }
    let steps: usize = std::env::var("STEPS")
        .ok()
        .map(|v| v.parse().unwrap())
        .unwrap_or(1);
    let mut rown = norm.iter().map(|&x| [x, x]).collect::<Vec<[f64; 2]>>();
    for _ in 0..if mode == 0 || mode >= 3 { 0 } else { steps } {
        scales.clear();
        for (d, links) in all.iter().enumerate() {
            let mut sent: HashMap<(u32, u8), f64> = HashMap::new();
            for l in links {
                let r = l.r as usize;
                *sent
                    .entry((set.surfels[l.p as usize].group, l.from))
                    .or_default() += set.surfels[r].area as f64 * l.f / rown[r][l.to as usize];
            }
            let mut sc = HashMap::new();
            for (k, s) in &sent {
                if let Some(o) = own[d].get(k) {
                    if *s > 0.0 && *o > 0.0 {
                        sc.insert(*k, (o / s).clamp(0.25, 4.0));
                    }
                }
            }
            scales.push(sc);
        }
        let mut rows = vec![[0f64; 2]; n];
        for (d, links) in all.iter().enumerate() {
            for l in links {
                let g = set.surfels[l.p as usize].group;
                let s = scales[d].get(&(g, l.from)).copied().unwrap_or(1.0);
                rows[l.r as usize][l.to as usize] += l.f * s;
            }
        }
        for k in 0..n {
            for side in 0..2 {
                // Sides that gather nothing keep S.
                if rows[k][side] > 0.0 {
                    rown[k][side] = rows[k][side];
                }
            }
        }
    }
    if mode == 0 || mode == 3 || mode >= 4 {
        scales = vec![HashMap::new(); all.len()];
    }
    // Mode 4: one scale per receiver side (a) and per sender side (b) over all directions,
    // Sinkhorn's alternation on the power matrix M_rp = A_r f_rp / S_r: rows keep A_r t_r,
    // columns reach A_p t_p (t: the share of a side's hemisphere that meets a surface).
    let mut sa = vec![[1f64; 2]; n];
    let mut sb = vec![[1f64; 2]; n];
    if mode == 4 {
        let area = |k: usize| set.surfels[k].area as f64;
        let mut target = vec![[0f64; 2]; n];
        for links in &all {
            for l in links {
                let r = l.r as usize;
                // Light sent toward a piece of no area (covered by a solid resting on it) is
                // absorbed by nothing: it is not part of what the side's rays can deliver.
                if area(l.p as usize) > 0.0 || std::env::var("ALL").is_ok() {
                    target[r][l.to as usize] += area(r) * l.f / norm[r];
                }
            }
        }
        let mut share = vec![[0f64; 2]; n];
        for links in &all {
            for l in links {
                let r = l.r as usize;
                share[r][l.to as usize] += l.f / norm[r];
            }
        }
        {
            let mut t: Vec<f64> = (0..n)
                .flat_map(|k| [target[k][0] / area(k), target[k][1] / area(k)])
                .filter(|&v| v > 0.0)
                .collect();
            t.sort_by(f64::total_cmp);
            let q = |f: f64| t[((t.len() - 1) as f64 * f) as usize];
            eprintln!(
                "share of a side's hemisphere met: min {:.4} 1% {:.4} 50% {:.4} 99% {:.4} max {:.4} ({} sides)",
                q(0.0), q(0.01), q(0.5), q(0.99), q(1.0), t.len()
            );
        }
        {
            let mut by: HashMap<(u32, u8), (f64, f64)> = HashMap::new();
            for (k, sides) in share.iter().enumerate() {
                for (side, &t) in sides.iter().enumerate() {
                    if t > 0.0 {
                        let e = by.entry((set.surfels[k].group, side as u8)).or_default();
                        e.0 += area(k) * (1.0 - t);
                        e.1 += area(k);
                    }
                }
            }
            let total: f64 = by.values().map(|v| v.1).sum();
            let lost: f64 = by.values().map(|v| v.0).sum();
            eprintln!("area-weighted share not met: {:.3} %", 100.0 * lost / total);
            if let Ok(g) = std::env::var("GROUP") {
                let g: u32 = g.parse().unwrap();
                let mut list: Vec<(usize, usize)> = (0..n)
                    .filter(|&k| set.surfels[k].group == g)
                    .flat_map(|k| [(k, 0), (k, 1)])
                    .filter(|&(k, side)| share[k][side] > 0.0 && share[k][side] < 0.999)
                    .collect();
                list.sort_by(|a, b| share[a.0][a.1].total_cmp(&share[b.0][b.1]));
                for &(k, side) in list.iter().take(12) {
                    let sf = &set.surfels[k];
                    let p = set
                        .grid
                        .to_world(voxrad::voxel::absolute_position(sf.voxel, sf.point));
                    eprintln!(
                        "    surfel {k} side {side} voxel {:?} at {:.3?} area {:.3} met {:.4}",
                        sf.voxel, p, sf.area, share[k][side]
                    );
                }
            }
            let mut v: Vec<_> = by.into_iter().collect();
            v.sort_by(|a, b| b.1 .0.total_cmp(&a.1 .0));
            for ((g, side), (l, a)) in v.iter().take(8) {
                let k = set.surfels.iter().position(|s| s.group == *g).unwrap();
                let sf = &set.surfels[k];
                eprintln!(
                    "  group {g} side {side} ({}, normal {:?}): {:.3} % of all, {:.2} % of its own",
                    set.materials[sf.material[*side as usize] as usize].name,
                    sf.normal.map(|x| (x * 100.0).round() / 100.0),
                    100.0 * l / total,
                    100.0 * l / a
                );
            }
        }
        for step in 0..steps {
            let mut cols = vec![[0f64; 2]; n];
            for links in &all {
                for l in links {
                    let r = l.r as usize;
                    cols[l.p as usize][l.from as usize] +=
                        sa[r][l.to as usize] * area(r) * l.f / norm[r];
                }
            }
            let mut worst: f64 = 0.0;
            for k in 0..n {
                for side in 0..2 {
                    if cols[k][side] > 0.0 && target[k][side] > 0.0 {
                        let was = sb[k][side];
                        sb[k][side] = target[k][side] / cols[k][side];
                        let err = (cols[k][side] * was / target[k][side] - 1.0).abs();
                        worst = worst.max(err);
                    }
                }
            }
            let mut rows = vec![[0f64; 2]; n];
            for links in &all {
                for l in links {
                    let r = l.r as usize;
                    rows[r][l.to as usize] += sb[l.p as usize][l.from as usize] * l.f / norm[r];
                }
            }
            for k in 0..n {
                for side in 0..2 {
                    if rows[k][side] > 0.0 {
                        sa[k][side] = share[k][side] / rows[k][side];
                    }
                }
            }
            eprintln!("sinkhorn step {step}: largest column error {worst:.3e}");
        }
    }
    for k in 0..n {
        for side in 0..2 {
            shift[k][side] = rown[k][side] - norm[k];
        }
    }
    let mat = |k: usize, side: usize| &set.materials[set.surfels[k].material[side] as usize];
    let mut b = vec![[[0f64; 3]; 2]; n];
    for (k, bk) in b.iter_mut().enumerate() {
        for (side, e) in bk.iter_mut().enumerate() {
            *e = mat(k, side).emission;
        }
    }
    let mut h = vec![[[0f64; 3]; 2]; n];
    for it in 0..200 {
        // Mode 6: one scale per channel over all directions, what the receivers' own sides send
        // along their links against what they gather through them.
        let global = if mode == 6 {
            conserving_scale(all.iter().flatten(), &set, &norm, &b)
        } else {
            [1.0; 3]
        };
        h.iter_mut().for_each(|x| *x = [[0.0; 3]; 2]);
        let mut rows = vec![[0f64; 2]; n];
        let mut next = Vec::new();
        for (d, links) in all.iter().enumerate() {
            // Mode 5: one scale per direction and channel, what the receivers' own sides send
            // along their links against what they gather through them.
            let per_direction = if mode == 5 {
                conserving_scale(links.iter(), &set, &norm, &b)
            } else {
                [1.0; 3]
            };
            let mut sent: HashMap<(u32, u8), f64> = HashMap::new();
            for l in links {
                let g = set.surfels[l.p as usize].group;
                let s = scales[d].get(&(g, l.from)).copied().unwrap_or(1.0)
                    * sa[l.r as usize][l.to as usize]
                    * sb[l.p as usize][l.from as usize];
                let from = b[l.p as usize][l.from as usize];
                let to = &mut h[l.r as usize][l.to as usize];
                for c in 0..3 {
                    to[c] += from[c] * l.f * s * per_direction[c] * global[c];
                }
                rows[l.r as usize][l.to as usize] += l.f * s;
                let r = l.r as usize;
                *sent.entry((g, l.from)).or_default() +=
                    set.surfels[r].area as f64 * l.f / rown[r][l.to as usize];
            }
            let mut sc = HashMap::new();
            for (k, s) in &sent {
                if let Some(o) = own[d].get(k) {
                    if *s > 0.0 && *o > 0.0 {
                        let old = scales[d].get(k).copied().unwrap_or(1.0);
                        sc.insert(*k, (old * (o / s).clamp(0.25, 4.0)).sqrt());
                    }
                }
            }
            next.push(sc);
        }
        if mode == 3 {
            for k in 0..n {
                for side in 0..2 {
                    if rows[k][side] > 0.0 {
                        rown[k][side] = rows[k][side];
                    }
                    shift[k][side] = rown[k][side] - norm[k];
                }
            }
            scales = next;
        }
        let mut change = 0.0;
        let mut total = 0.0;
        for k in 0..n {
            for side in 0..2 {
                let m = mat(k, side);
                for c in 0..3 {
                    let nb = m.emission[c]
                        + m.reflectance[c] * h[k][side][c] / (norm[k] + shift[k][side]);
                    change += (nb - b[k][side][c]).abs() * set.surfels[k].area as f64;
                    total += nb * set.surfels[k].area as f64;
                    b[k][side][c] = nb;
                }
            }
        }
        if std::env::var("TRACE").is_ok() {
            eprintln!("it {it} change {:.3e}", change / total);
        }
        if change / total < 1e-6 {
            eprintln!("converged after {it}");
            break;
        }
    }
    let (mut em, mut ab) = (0.0, 0.0);
    for k in 0..n {
        for side in 0..2 {
            let m = mat(k, side);
            let area = set.surfels[k].area as f64;
            for (c, gathered) in h[k][side].iter().enumerate() {
                em += m.emission[c] * area;
                ab += (1.0 - m.reflectance[c]) * gathered / (norm[k] + shift[k][side]) * area;
            }
        }
    }
    println!("mode {mode}: balance {:+.3} %", 100.0 * (em - ab) / em);
    {
        // The power each side sends that reaches no receiver, split into the share of its own
        // rays that meets nothing (lost by propagation) and the rest (what receivers take from
        // it differs from what its own rays meet: the links are not reciprocal).
        let mut own = vec![[0f64; 2]; n];
        let mut col = vec![[0f64; 2]; n];
        for links in &all {
            for l in links {
                let (r, p) = (l.r as usize, l.p as usize);
                own[r][l.to as usize] += set.surfels[r].area as f64 * l.f / norm[r];
                col[p][l.from as usize] += set.surfels[r].area as f64
                    * l.f
                    * sa[r][l.to as usize]
                    * sb[p][l.from as usize]
                    / norm[r];
            }
        }
        let (mut unmet, mut unreciprocal) = (0.0, 0.0);
        for k in 0..n {
            for side in 0..2 {
                let bp: f64 = b[k][side].iter().sum();
                let a = set.surfels[k].area as f64;
                if own[k][side] > 0.0 {
                    unmet += (a - own[k][side]) * bp;
                }
                unreciprocal += (own[k][side] - col[k][side]) * bp;
            }
        }
        println!(
            "  of the emitted power: lost unmet {:+.3} %, lost unreciprocal {:+.3} %",
            100.0 * unmet / em,
            100.0 * unreciprocal / em
        );
    }
    // Where the power goes missing: by plane side, what it sends over all directions (its
    // projected area times its radiosity, channels summed) against what receivers took from it.
    let mut sends: HashMap<(u32, u8), f64> = HashMap::new();
    let mut taken: HashMap<(u32, u8), f64> = HashMap::new();
    for (d, links) in all.iter().enumerate() {
        let dd = &dirs.directions[d];
        let w = dd.solid_angle / std::f64::consts::PI;
        for (i, sf) in set.surfels.iter().enumerate() {
            let c = voxrad::solve::normalize::cosine(sf.normal, dd.unit);
            for side in 0..2u8 {
                let bp: f64 = b[i][side as usize].iter().sum();
                *sends.entry((sf.group, side)).or_default() +=
                    sf.area as f64 * c * w / norm[i] * bp;
            }
        }
        for l in links {
            let (r, p) = (l.r as usize, l.p as usize);
            let g = set.surfels[p].group;
            let scale = scales[d].get(&(g, l.from)).copied().unwrap_or(1.0)
                * sa[r][l.to as usize]
                * sb[p][l.from as usize];
            let bp: f64 = b[p][l.from as usize].iter().sum();
            *taken.entry((g, l.from)).or_default() +=
                set.surfels[r].area as f64 * l.f * scale / (norm[r] + shift[r][l.to as usize]) * bp;
        }
    }
    let sent_total: f64 = sends.values().sum();
    let mut lost: Vec<((u32, u8), f64)> = sends
        .iter()
        .map(|(k, v)| (*k, v - taken.get(k).copied().unwrap_or(0.0)))
        .collect();
    lost.sort_by(|a, b| b.1.abs().total_cmp(&a.1.abs()));
    println!("  largest losses (share of all power sent; negative: taken more than sent):");
    for ((g, side), v) in lost.iter().take(8) {
        let k = set.surfels.iter().position(|s| s.group == *g).unwrap();
        let sf = &set.surfels[k];
        println!(
            "    group {g} side {side} ({}, normal {:?}): {:+.3} %",
            set.materials[sf.material[*side as usize] as usize].name,
            sf.normal.map(|x| (x * 100.0).round() / 100.0),
            100.0 * v / sent_total
        );
    }
    // REF=DIR: the error against a path-traced reference (DIR/reference.csv), as
    // docs/accuracy.md measures it (channels summed, probes below 5 % of the median left out).
    if let Ok(dir) = std::env::var("REF") {
        let results = voxrad::output::results::Results {
            grid: set.grid,
            records: set
                .surfels
                .iter()
                .zip(&b)
                .map(|(s, v)| {
                    voxrad::output::results::Record::from_surfel(
                        s,
                        v.map(|side| side.map(|c| c as f32)),
                    )
                })
                .collect(),
            materials: set
                .materials
                .iter()
                .map(voxrad::output::results::SideMaterial::of)
                .collect(),
        };
        let index = voxrad::output::ProbeIndex::new(&results);
        let text = std::fs::read_to_string(format!("{dir}/reference.csv")).unwrap();
        let mut rows: Vec<(f64, f64)> = Vec::new();
        for line in text.lines().skip(1) {
            let f: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
            let got = index.lookup(
                glam::DVec3::new(f[0], f[1], f[2]),
                glam::DVec3::new(f[3], f[4], f[5]),
            );
            rows.push((got.radiosity.iter().sum(), f[6] + f[7] + f[8]));
        }
        let mut refs: Vec<f64> = rows.iter().map(|r| r.1).collect();
        refs.sort_by(f64::total_cmp);
        let median = refs[refs.len() / 2];
        let kept: Vec<f64> = rows
            .iter()
            .filter(|r| r.1 >= 0.05 * median)
            .map(|r| (r.0 - r.1) / r.1)
            .collect();
        let mean = kept.iter().map(|e| e.abs()).sum::<f64>() / kept.len() as f64;
        let signed = kept.iter().sum::<f64>() / kept.len() as f64;
        let max = kept.iter().fold(0f64, |m, e| m.max(e.abs()));
        println!(
            "  against the reference: mean {:.2} %, signed {:+.2} %, max {:.1} % ({} probes)",
            100.0 * mean,
            100.0 * signed,
            100.0 * max,
            kept.len()
        );
    }
    // Mean radiosity of front sides by region (corridor scene: z in [4, 6] is the corridor).
    let mut by: std::collections::BTreeMap<String, (f64, f64)> = Default::default();
    for (k, s) in set.surfels.iter().enumerate() {
        let p = set
            .grid
            .to_world(voxrad::voxel::absolute_position(s.voxel, s.point));
        let n = s.normal;
        let corridor = (4.0..=6.0).contains(&p.z)
            && (n[2].abs() < 0.5 || (p.z < 4.01 && n[2] > 0.5) || (p.z > 5.99 && n[2] < -0.5));
        let kind = if n[1] > 0.5 {
            "floor"
        } else if n[1] < -0.5 {
            "ceil"
        } else {
            "wall"
        };
        let name = &set.materials[s.material[0] as usize].name;
        if name == "lamp" {
            continue;
        }
        let key = format!("{} {kind}", if corridor { "corridor" } else { "rooms" });
        let e = by.entry(key).or_default();
        e.0 += (b[k][0].iter().sum::<f64>()) * s.area as f64;
        e.1 += s.area as f64;
    }
    for (k, (v, a)) in by {
        println!("  {k}: {:.3}", v / a);
    }
}

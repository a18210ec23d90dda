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
//! - 3: one alternation per iteration, damped (what a solver could afford without kept links).
//!
//! It also prints the plane sides whose light goes missing most: what each sends over all
//! directions against what receivers took from it. `TRACE=1` prints each iteration's relative
//! change. Measured figures: docs/accuracy.md.
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
    for _ in 0..if mode == 0 || mode == 3 { 0 } else { steps } {
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
    if mode == 0 || mode == 3 {
        scales = vec![HashMap::new(); all.len()];
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
        h.iter_mut().for_each(|x| *x = [[0.0; 3]; 2]);
        let mut rows = vec![[0f64; 2]; n];
        let mut next = Vec::new();
        for (d, links) in all.iter().enumerate() {
            let mut sent: HashMap<(u32, u8), f64> = HashMap::new();
            for l in links {
                let g = set.surfels[l.p as usize].group;
                let s = scales[d].get(&(g, l.from)).copied().unwrap_or(1.0);
                let from = b[l.p as usize][l.from as usize];
                let to = &mut h[l.r as usize][l.to as usize];
                for c in 0..3 {
                    to[c] += from[c] * l.f * s;
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
            let scale = scales[d].get(&(g, l.from)).copied().unwrap_or(1.0);
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

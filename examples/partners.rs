//! Which surfaces see the wrong partner: every link that propagation makes is checked against a
//! ray cast from the receiver's surface point along the link's direction through the scene's own
//! triangles (brute force, no voxels). A link is right when its partner lies on the plane of the
//! triangle the ray hits first; its share is otherwise wrong, and the part of a ray that hits a
//! triangle but has no link is missing.
//!
//! A ray from one point is a point sample of a voxel-wide tube, so pieces by an edge disagree
//! with it at some directions however right the rules are; a whole face that disagrees is a wrong
//! partner rule. A wrong partner on the right surface costs nothing, one on another surface (or
//! on a solid's inner side, which is dark) can cost much: with `VALUES=1` the scene is also
//! solved (grey, no direct pass) and each plane group's gathered radiosity is compared with what
//! the true hits would have given it (the solved radiosity of the surfel nearest each hit, on the
//! hit's plane, on the side facing the ray). Brute-force ray casting makes this a tool for small
//! scenes (the hard-case twins, the thin-slab boxes).
//!
//! `cargo run --release --example partners SCENE.obj RESOLUTION DIRECTIONS` prints, per plane
//! group and side, the share of its rays (solid angle, area and cosine weighted) that are right,
//! wrong and missing, worst first. With `GROUP=g` also that group's wrong shares by direction and
//! partner group, and with `VALUES=1` its largest losses by partner group and true triangle; with
//! `SHOW=t` as well, the links whose ray truly hits triangle `t` but gathers less than that.
//! This found the dark underside of the tilted thin slab (`propagate::side_of`).
use glam::DVec3;
use std::collections::{BTreeMap, HashMap};
use voxrad::geometry::directions::DirectionSet;
use voxrad::geometry::lines::LineFrame;
use voxrad::geometry::order;
use voxrad::solve::direct::DirectPass;
use voxrad::solve::dispatch::{dispatch, Lines};
use voxrad::solve::propagate::{find_partners, for_each_link, prop_surfels, LineScratch};
use voxrad::solve::{solve, Solution, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};
use voxrad::voxel::{absolute_position, SurfelSet, BACK, FRONT};

/// A scene triangle in voxel units.
struct Tri {
    a: DVec3,
    e1: DVec3,
    e2: DVec3,
    normal: DVec3,
}

impl Tri {
    /// Whether a surfel with `normal` at `point` (voxel units) lies on this triangle's plane.
    fn holds(&self, normal: [f32; 3], point: DVec3) -> bool {
        let n = DVec3::from(normal.map(f64::from));
        n.dot(self.normal).abs() > 0.9999 && self.normal.dot(point - self.a).abs() < 0.02
    }
}

/// Distance along `dir` from `origin` to the first triangle hit (Moller-Trumbore), and its index.
fn first_hit(tris: &[Tri], origin: DVec3, dir: DVec3) -> Option<(f64, usize)> {
    let mut best: Option<(f64, usize)> = None;
    for (i, t) in tris.iter().enumerate() {
        let p = dir.cross(t.e2);
        let det = t.e1.dot(p);
        if det.abs() < 1e-12 {
            continue;
        }
        let o = origin - t.a;
        let u = o.dot(p) / det;
        if !(-1e-9..=1.0 + 1e-9).contains(&u) {
            continue;
        }
        let q = o.cross(t.e1);
        let v = dir.dot(q) / det;
        if v < -1e-9 || u + v > 1.0 + 1e-9 {
            continue;
        }
        let d = t.e2.dot(q) / det;
        if d > 1e-6 && best.is_none_or(|(b, _)| d < b) {
            best = Some((d, i));
        }
    }
    best
}

/// The side of a surface with `normal` that faces along `dir`.
fn side_facing(normal: [f32; 3], dir: DVec3) -> usize {
    if DVec3::from(normal.map(f64::from)).dot(dir) > 0.0 {
        FRONT
    } else {
        BACK
    }
}

#[derive(Default, Clone, Copy)]
struct Tally {
    projected: f64,
    right: f64,
    wrong: f64,
    missing: f64,
}

/// The solved radiosity a ray along `dir` meets where it truly hits triangle `t` at `h`: that of
/// the surfel nearest `h` on the triangle's plane, on its side facing the ray.
fn true_value(
    set: &SurfelSet,
    by_voxel: &HashMap<[i32; 3], Vec<usize>>,
    solution: &Solution,
    t: &Tri,
    h: DVec3,
    dir: DVec3,
) -> Option<f64> {
    let v = h.floor().as_ivec3();
    let mut best: Option<(f64, f64)> = None;
    for dx in -1..=1 {
        for dy in -1..=1 {
            for dz in -1..=1 {
                let key = [v.x + dx, v.y + dy, v.z + dz];
                for &i in by_voxel.get(&key).into_iter().flatten() {
                    let p = &set.surfels[i];
                    let at = absolute_position(p.voxel, p.point);
                    if !t.holds(p.normal, at) {
                        continue;
                    }
                    let distance = (at - h).length();
                    let b = solution.radiosity[i][side_facing(p.normal, -dir)][0] as f64;
                    if best.is_none_or(|(d, _)| distance < d) {
                        best = Some((distance, b));
                    }
                }
            }
        }
    }
    best.map(|b| b.1)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 4 {
        eprintln!("usage: partners SCENE.obj RESOLUTION DIRECTIONS");
        std::process::exit(2);
    }
    let scene = voxrad::scene::obj::load_obj(std::path::Path::new(&args[1])).unwrap();
    let res: u32 = args[2].parse().unwrap();
    let count: usize = args[3].parse().unwrap();
    let env_number = |name: &str| std::env::var(name).ok().map(|g| g.parse::<u32>().unwrap());
    let only_group = env_number("GROUP");
    let show_triangle = env_number("SHOW");
    let set = voxelize(&scene, GridSpec::Resolution(res)).unwrap();
    let grid = set.grid;
    let tris: Vec<Tri> = scene
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.vertices.map(|v| grid.to_voxel_units(v));
            Tri {
                a,
                e1: b - a,
                e2: c - a,
                normal: (b - a).cross(c - a).normalize(),
            }
        })
        .collect();
    let surfels = prop_surfels(&set);
    let solution = std::env::var("VALUES").is_ok().then(|| {
        let options = SolveOptions {
            directions: count,
            max_iterations: 500,
            tolerance: Some(1e-4),
            threads: 2,
            grey: true,
            accelerate: false,
            direct: DirectPass::Off,
            ..Default::default()
        };
        solve(&set, &options).unwrap()
    });
    let mut by_voxel: HashMap<[i32; 3], Vec<usize>> = HashMap::new();
    for (i, s) in set.surfels.iter().enumerate() {
        by_voxel.entry(s.voxel).or_default().push(i);
    }
    let directions = DirectionSet::with_count(count);
    let entries = voxrad::solve::dispatch::lexicographic_orders(&set);
    let mut lines = Lines::default();
    let mut scratch = LineScratch::default();
    // Per (plane group, side).
    let mut tallies: BTreeMap<(u32, usize), Tally> = BTreeMap::new();
    // Per (plane group, side): radiosity gathered, and what the true hits would give.
    let mut gathered: BTreeMap<(u32, usize), (f64, f64)> = BTreeMap::new();
    // GROUP=g: wrong share by (direction, partner group); loss by (partner group, triangle).
    let mut wrong_by_direction: BTreeMap<([i64; 3], u32), f64> = BTreeMap::new();
    let mut loss_by_partner: BTreeMap<(u32, usize), f64> = BTreeMap::new();
    let mut missing_shown = 0;
    for d in &directions.directions {
        let frame = LineFrame::new(d.vector, grid.dims);
        dispatch(&entries[order::order_of(d.vector)], &frame, 1, &mut lines);
        for l in 0..lines.line_count() {
            let line = lines.line(l);
            find_partners(line, &surfels, d.unit, &mut scratch);
            // Per (line position, 0 ahead / 1 behind): the first true hit, the right and wrong
            // shares, and a wrong partner.
            let mut hits: HashMap<(usize, u8), Option<(f64, usize)>> = HashMap::new();
            let mut got: HashMap<(usize, u8), (f64, f64, u32)> = HashMap::new();
            for_each_link(&scratch, d.unit, |link| {
                let r = &set.surfels[line[link.receiver] as usize];
                let partner = line[link.partner] as usize;
                let p = &set.surfels[partner];
                let dir = if link.which == 0 { d.unit } else { -d.unit };
                let origin = absolute_position(r.voxel, r.point);
                let hit = *hits
                    .entry((link.receiver, link.which))
                    .or_insert_with(|| first_hit(&tris, origin, dir));
                let entry = got.entry((link.receiver, link.which)).or_default();
                if hit.is_some_and(|(_, i)| {
                    tris[i].holds(p.normal, absolute_position(p.voxel, p.point))
                }) {
                    entry.0 += link.share as f64;
                } else {
                    entry.1 += link.share as f64;
                    entry.2 = p.group;
                }
                let (Some(solution), Some((distance, i))) = (&solution, hit) else {
                    return;
                };
                let side = side_facing(r.normal, dir);
                let weight = d.solid_angle * r.area as f64 * link.cosine * link.share as f64;
                let partner_value = solution.radiosity[partner][link.from_side][0] as f64;
                let truth = true_value(
                    &set,
                    &by_voxel,
                    solution,
                    &tris[i],
                    origin + dir * distance,
                    dir,
                )
                .unwrap_or(f64::NAN);
                let e = gathered.entry((r.group, side)).or_default();
                e.0 += weight * partner_value;
                e.1 += weight * truth;
                if only_group == Some(r.group) {
                    *loss_by_partner.entry((p.group, i)).or_default() +=
                        weight * (truth - partner_value);
                    if show_triangle == Some(i as u32) && partner_value < truth {
                        println!(
                            "  link: receiver v{:?} point {:?} direction {:?} ({}) partner v{:?} group {} share {:.3}: {partner_value:.3} where the hit has {truth:.3}",
                            r.voxel,
                            r.point,
                            d.vector,
                            if link.which == 0 { "ahead" } else { "behind" },
                            p.voxel,
                            p.group,
                            link.share
                        );
                    }
                }
            });
            for (k, &m) in line.iter().enumerate() {
                let r = &set.surfels[m as usize];
                let cosine = voxrad::solve::normalize::cosine(r.normal, d.unit);
                if cosine == 0.0 {
                    continue;
                }
                for which in 0..2u8 {
                    let dir = if which == 0 { d.unit } else { -d.unit };
                    let hit = match hits.get(&(k, which)) {
                        Some(h) => *h,
                        None => first_hit(&tris, absolute_position(r.voxel, r.point), dir),
                    };
                    let (right, wrong, wrong_group) =
                        got.get(&(k, which)).copied().unwrap_or_default();
                    let weight = d.solid_angle * r.area as f64 * cosine;
                    let t = tallies
                        .entry((r.group, side_facing(r.normal, dir)))
                        .or_default();
                    t.projected += weight;
                    t.right += weight * right;
                    t.wrong += weight * wrong;
                    if hit.is_some() {
                        let gone = (1.0 - right - wrong).max(0.0);
                        t.missing += weight * gone;
                        if only_group == Some(r.group) && gone > 0.05 && missing_shown < 6 {
                            missing_shown += 1;
                            println!(
                                "  missing {gone:.3}: receiver v{:?} point {:?} direction {:?} ({}); line:",
                                r.voxel,
                                r.point,
                                d.vector,
                                if which == 0 { "ahead" } else { "behind" }
                            );
                            let lo = k.saturating_sub(4);
                            for (j, &q) in line.iter().enumerate().take(k + 5).skip(lo) {
                                let s = &set.surfels[q as usize];
                                println!(
                                    "    {}{j}: v{:?} group {} point {:?} normal {:?} area {:.3} box {:?}",
                                    if j == k { "*" } else { " " },
                                    s.voxel,
                                    s.group,
                                    s.point,
                                    s.normal,
                                    s.area,
                                    s.extent
                                );
                            }
                        }
                    }
                    if only_group == Some(r.group) && wrong > 0.0 {
                        *wrong_by_direction
                            .entry((d.vector, wrong_group))
                            .or_default() += weight * wrong;
                    }
                }
            }
        }
    }
    // Describe each group by its normal, material and the centroid of its surfels (world units).
    let mut about: BTreeMap<u32, (DVec3, [f32; 3], u32, usize)> = BTreeMap::new();
    for s in &set.surfels {
        let e = about
            .entry(s.group)
            .or_insert((DVec3::ZERO, s.normal, s.material[FRONT], 0));
        e.0 += grid.to_world(absolute_position(s.voxel, s.point));
        e.3 += 1;
    }
    let mut rows: Vec<((u32, usize), Tally)> = tallies.into_iter().collect();
    let bad = |t: &Tally| (t.wrong + t.missing) / t.projected.max(1e-300);
    rows.sort_by(|a, b| bad(&b.1).total_cmp(&bad(&a.1)));
    println!("group side   right    wrong  missing gathered/true surfels material normal centroid");
    for ((g, side), t) in rows {
        if t.right + t.wrong == 0.0 {
            continue;
        }
        let (sum, normal, material, count) = about[&g];
        let c = sum / count as f64;
        let value = gathered
            .get(&(g, side))
            .map_or(String::from("-"), |(a, b)| {
                format!("{:+.2} %", 100.0 * (a / b - 1.0))
            });
        println!(
            "{g:5} {:>4} {:6.2} % {:6.2} % {:6.2} % {value:>13} {count:7} {} [{:.2},{:.2},{:.2}] [{:.3},{:.3},{:.3}]",
            if side == FRONT { "fr" } else { "bk" },
            100.0 * t.right / t.projected,
            100.0 * t.wrong / t.projected,
            100.0 * t.missing / t.projected,
            set.materials[material as usize].name,
            normal[0],
            normal[1],
            normal[2],
            c.x,
            c.y,
            c.z,
        );
    }
    if let Some(g) = only_group {
        println!("group {g}: wrong shares by direction and partner group");
        let mut rows: Vec<_> = wrong_by_direction.into_iter().collect();
        rows.sort_by(|a, b| b.1.total_cmp(&a.1));
        for ((v, partner), w) in rows.into_iter().take(20) {
            println!("  direction {v:?} partner group {partner}: {w:.3e}");
        }
        if solution.is_some() {
            println!("group {g}: radiosity lost by partner group and true triangle");
            let mut rows: Vec<_> = loss_by_partner.into_iter().collect();
            rows.sort_by(|a, b| b.1.total_cmp(&a.1));
            for ((partner, i), loss) in rows.into_iter().take(15) {
                let t = &tris[i];
                println!(
                    "  partner group {partner}, triangle {i} (normal {:.2?}, corner {:.2?}): {loss:.3e}",
                    t.normal.to_array(),
                    t.a.to_array()
                );
            }
        }
    }
}

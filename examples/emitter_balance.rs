//! Where a scene's power balance goes wrong, direction by direction: for every line direction,
//! the light the emitters' sides send to their receivers along the lines (receivers' area times
//! the gather weight, with the emitting sides at radiosity 1 and everything else at 0) against
//! the emitters' projected area along the direction, which is what they would send in a scene
//! that conserves energy. The totals are weighted by the directions' solid angles.
//!
//! `cargo run --release --example emitter_balance SCENE.obj RESOLUTION DIRECTIONS [v]` prints the
//! total (`sent / own - 1`; 0 is exact); with `v` also each direction; with `DIR=a,b,c` in the
//! environment only that direction, with every line that carries an emitter (surfels, partners
//! and weights, and the line's sent and own sums); with `SEND=NAME` the sides of material
//! `NAME` send instead of the emitters' (where a reflecting object creates light). That is how
//! the open-edge, lamp-under-ceiling and rim rules of `solve::propagate` were found.
use voxrad::geometry::directions::DirectionSet;
use voxrad::geometry::lines::LineFrame;
use voxrad::geometry::order;
use voxrad::solve::dispatch::{dispatch, Lines};
use voxrad::solve::propagate::{gather_line, prop_surfels, DirectionInput, LineScratch};
use voxrad::voxel::voxelize::{voxelize, GridSpec};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let scene = voxrad::scene::obj::load_obj(std::path::Path::new(&args[1])).unwrap();
    let res: u32 = args[2].parse().unwrap();
    let ndir: usize = args[3].parse().unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(res)).unwrap();
    let surfels = prop_surfels(&set);
    let n = surfels.len();
    // radiosity 1 on emitting sides, or with SEND=NAME on the sides of material NAME
    let send = std::env::var("SEND").ok();
    let mut rad = vec![[[0f32; 3]; 2]; n];
    for (r, s) in rad.iter_mut().zip(&set.surfels) {
        for (side, &material) in s.material.iter().enumerate() {
            let m = &set.materials[material as usize];
            let chosen = match &send {
                Some(name) => &m.name == name,
                None => m.emission[0] > 0.0,
            };
            if chosen {
                r[side] = [1.0; 3];
            }
        }
    }
    let dirs = DirectionSet::with_count(ndir);
    let entries = voxrad::solve::dispatch::lexicographic_orders(&set);
    let mut lines = Lines::default();
    let (mut tot_sent, mut tot_own) = (0.0, 0.0);
    let only: Option<Vec<i64>> = std::env::var("DIR")
        .ok()
        .map(|v| v.split(',').map(|x| x.parse().unwrap()).collect());
    for d in &dirs.directions {
        if let Some(o) = &only {
            if o.as_slice() != d.vector {
                continue;
            }
        }
        let frame = LineFrame::new(d.vector, set.grid.dims);
        dispatch(&entries[order::order_of(d.vector)], &frame, 1, &mut lines);
        let input = DirectionInput {
            unit: d.unit,
            weight: 1.0,
            surfels: &surfels,
            radiosity: &rad,
            channels: 1,
        };
        let mut acc = vec![[[0f64; 3]; 2]; n];
        let mut scratch = LineScratch::default();
        for l in 0..lines.line_count() {
            let line = lines.line(l);
            if line.len() < 2 {
                continue;
            }
            unsafe {
                gather_line::<(), _, true>(line, &input, &mut scratch, acc.as_mut_ptr(), &mut ())
            };
            if only.is_some()
                && line
                    .iter()
                    .any(|&m| rad[m as usize][0][0] > 0.0 || rad[m as usize][1][0] > 0.0)
            {
                let sent_line: f64 = line
                    .iter()
                    .map(|&m| {
                        let a = &acc[m as usize];
                        set.surfels[m as usize].area as f64 * (a[0][0] + a[1][0])
                    })
                    .sum();
                let own_line: f64 = line
                    .iter()
                    .map(|&m| {
                        let s = &set.surfels[m as usize];
                        let sides = rad[m as usize].iter().filter(|r| r[0] > 0.0).count();
                        sides as f64
                            * s.area as f64
                            * voxrad::solve::normalize::cosine(s.normal, d.unit)
                    })
                    .sum();
                println!(
                    "line {l} dir {:?}: sent {sent_line:.3} own {own_line:.3}",
                    d.vector
                );
                for (k, &m) in line.iter().enumerate() {
                    let p = &surfels[m as usize];
                    let [a, b] = scratch.partners[k];
                    let show = |x: (u32, f32)| {
                        if x.0 == u32::MAX {
                            "-".to_string()
                        } else {
                            format!(
                                "{}@{:.2}{}",
                                x.0,
                                x.1,
                                if rad[line[x.0 as usize] as usize].iter().any(|r| r[0] > 0.0) {
                                    "*"
                                } else {
                                    ""
                                }
                            )
                        }
                    };
                    println!("  {k:3} v{:?} g{} n[{:.0},{:.0},{:.0}] pt[{:.2},{:.2},{:.2}] cov{:.2}  ahead {} behind {}", p.voxel, p.group, p.normal[0], p.normal[1], p.normal[2], p.point[0], p.point[1], p.point[2], p.coverage, show(a), show(b));
                }
                for e in &scratch.extra {
                    println!("  extra {:?}", e);
                }
            }
        }
        let sent: f64 = set
            .surfels
            .iter()
            .zip(&acc)
            .map(|(s, a)| s.area as f64 * (a[0][0] + a[1][0]))
            .sum();
        // own projected area: emitting sides whose normal faces +s or -s (both handled)
        let mut own = 0.0;
        for (r, s) in rad.iter().zip(&set.surfels) {
            for side_light in r {
                if side_light[0] > 0.0 {
                    let c = voxrad::solve::normalize::cosine(s.normal, d.unit);
                    own += s.area as f64 * c;
                }
            }
        }
        tot_sent += sent * d.solid_angle;
        tot_own += own * d.solid_angle;
        if args.len() > 4 {
            println!(
                "{:?} {:.4} {:.4} {:+.4}",
                d.vector,
                sent,
                own,
                sent / own - 1.0
            );
        }
    }
    println!("total sent/own - 1 = {:+.5}", tot_sent / tot_own - 1.0);
}

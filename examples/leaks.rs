//! Where light leaks out of a closed scene, direction by direction: every surfel side sends
//! radiosity 1, and each front side (the side its triangles face: into the air for a scene whose
//! solids face outwards and whose shell faces inwards) should then gather exactly its cosine with
//! the direction, because every ray from it ends on some surface. What is missing is light that a
//! ray let through a surface (out of the scene, or into a solid).
//!
//! Front sides whose rays meet nothing in any direction are faces in contact (a wall's foot on
//! the floor) and are left out.
//!
//! `cargo run --release --example leaks SCENE.obj RESOLUTION DIRECTIONS [v]` prints, per material,
//! the missing fraction of the front sides' projected area over all directions, weighted by
//! solid angle (with `v` also each direction's missing fraction); with `DIR=a,b,c` in the environment only that direction, and the front sides that
//! lose most, with their voxel, normal and surface point; with `LINE_OF=x,y,z` as well the line
//! through that voxel, surfel by surfel with its partners.
use voxrad::geometry::directions::DirectionSet;
use voxrad::geometry::lines::LineFrame;
use voxrad::geometry::order;
use voxrad::solve::dispatch::{dispatch, Lines};
use voxrad::solve::propagate::{gather_line, prop_surfels, DirectionInput, LineScratch};
use voxrad::voxel::voxelize::{voxelize, GridSpec};
use voxrad::voxel::FRONT;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 4 {
        eprintln!("usage: leaks SCENE.obj RESOLUTION DIRECTIONS");
        std::process::exit(2);
    }
    let scene = voxrad::scene::obj::load_obj(std::path::Path::new(&args[1])).unwrap();
    let res: u32 = args[2].parse().unwrap();
    let count: usize = args[3].parse().unwrap();
    let set = voxelize(&scene, GridSpec::Resolution(res)).unwrap();
    let surfels = prop_surfels(&set);
    let n = surfels.len();
    let radiosity = vec![[[1f32; 3]; 2]; n];
    let only: Option<Vec<i64>> = std::env::var("DIR")
        .ok()
        .map(|v| v.split(',').map(|x| x.parse().unwrap()).collect());
    // LINE_OF=x,y,z (with DIR): also print the line through that voxel, surfel by surfel.
    let line_of: Option<[i32; 3]> = std::env::var("LINE_OF").ok().map(|v| {
        let c: Vec<i32> = v.split(',').map(|x| x.parse().unwrap()).collect();
        [c[0], c[1], c[2]]
    });
    let verbose = args.get(4).is_some_and(|a| a == "v");
    let directions = DirectionSet::with_count(count);
    let entries = voxrad::solve::dispatch::lexicographic_orders(&set);
    let materials = set.materials.len();
    // Per surfel: (missing, projected) area of its front side, solid-angle weighted, and whether
    // any ray from it met a surface (a face in contact with another, such as a wall's foot on the
    // floor, never does: it is left out).
    let mut per_side = vec![(0.0f64, 0.0f64, false); n];
    let mut lines = Lines::default();
    let mut scratch = LineScratch::default();
    for d in &directions.directions {
        if only.as_ref().is_some_and(|o| o.as_slice() != d.vector) {
            continue;
        }
        let frame = LineFrame::new(d.vector, set.grid.dims);
        dispatch(&entries[order::order_of(d.vector)], &frame, 1, &mut lines);
        let input = DirectionInput {
            unit: d.unit,
            weight: 1.0,
            surfels: &surfels,
            radiosity: &radiosity,
            channels: 1,
        };
        let mut acc = vec![[[0f64; 3]; 2]; n];
        for l in 0..lines.line_count() {
            let line = lines.line(l);
            // SAFETY: one accumulator entry per surfel, one thread, each surfel on one line.
            unsafe {
                gather_line::<(), _, true>(line, &input, &mut scratch, acc.as_mut_ptr(), &mut ())
            };
            if let Some(v) = &line_of {
                if line.iter().any(|&m| surfels[m as usize].voxel == *v) {
                    println!("line {l} dir {:?}", d.vector);
                    for (k, &m) in line.iter().enumerate() {
                        let p = &surfels[m as usize];
                        let [a, b] = scratch.partners[k];
                        let show = |x: (u32, f32)| {
                            if x.0 == u32::MAX {
                                "-".to_string()
                            } else {
                                format!("{}@{:.2}", x.0, x.1)
                            }
                        };
                        println!(
                            "  {k:3} v{:?} g{} n[{:.2},{:.2},{:.2}] pt[{:.2},{:.2},{:.2}] \
                             box[{:.2?}] cov{:.2} ahead {} behind {}",
                            p.voxel,
                            p.group,
                            p.normal[0],
                            p.normal[1],
                            p.normal[2],
                            p.point[0],
                            p.point[1],
                            p.point[2],
                            p.extent,
                            p.coverage,
                            show(a),
                            show(b)
                        );
                    }
                }
            }
        }
        let mut worst = Vec::new();
        let (mut dir_missing, mut dir_projected) = (0.0, 0.0);
        for (i, s) in set.surfels.iter().enumerate() {
            let cos = voxrad::solve::normalize::cosine(s.normal, d.unit);
            if cos < 1e-9 {
                continue;
            }
            let got = acc[i][FRONT][0] / cos;
            let missing = (1.0 - got).max(0.0);
            per_side[i].0 += d.solid_angle * s.area as f64 * cos * missing;
            per_side[i].1 += d.solid_angle * s.area as f64 * cos;
            per_side[i].2 |= got > 1e-6;
            dir_missing += s.area as f64 * cos * missing;
            dir_projected += s.area as f64 * cos;
            if only.is_some() && missing > 1e-3 {
                worst.push((missing * s.area as f64, i, got));
            }
        }
        if verbose {
            println!(
                "{:?} missing {:.3} %",
                d.vector,
                100.0 * dir_missing / dir_projected
            );
        }
        worst.sort_by(|a, b| b.0.total_cmp(&a.0));
        for &(_, i, got) in worst.iter().take(400) {
            let s = &set.surfels[i];
            println!(
                "  v{:?} n[{:.2},{:.2},{:.2}] pt[{:.2},{:.2},{:.2}] area {:.2} {} got {:.3}",
                s.voxel,
                s.normal[0],
                s.normal[1],
                s.normal[2],
                s.point[0],
                s.point[1],
                s.point[2],
                s.area,
                set.materials[s.material[FRONT] as usize].name,
                got
            );
        }
    }
    let mut totals = vec![(0.0f64, 0.0f64); materials];
    let mut contact = 0usize;
    for (s, &(a, b, seen)) in set.surfels.iter().zip(&per_side) {
        if seen {
            let m = s.material[FRONT] as usize;
            totals[m].0 += a;
            totals[m].1 += b;
        } else {
            contact += 1;
        }
    }
    println!("{contact} front sides in contact (no ray met anything) left out");
    let (mut missing, mut projected) = (0.0, 0.0);
    for (m, &(a, b)) in totals.iter().enumerate() {
        if b > 0.0 {
            println!(
                "{:>16} missing {:.3} %",
                set.materials[m].name,
                100.0 * a / b
            );
        }
        missing += a;
        projected += b;
    }
    println!(
        "all front sides missing {:.3} %",
        100.0 * missing / projected
    );
}

//! The direct-light pass (`solve::direct`): the emitters' light gathered once with a dense
//! direction set, the bounces with the solve's own. It must keep the physics of a plain solve
//! (the furnace's `E / (1 - rho)`, the power balance of a closed box) and bring the light of a
//! small lamp on a floor closer to the analytic answer than the plain solve with the same bounce
//! directions. That its emitters' lines gather what a full pass over the dense set gathers is a
//! unit test of `solve::direct`.

mod common;

use glam::DVec3;
use voxrad::scene::{Material, Scene};
use voxrad::solve::direct::DirectPass;
use voxrad::solve::{solve, Solution, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};
use voxrad::voxel::SurfelSet;

fn run(scene: &Scene, resolution: u32, options: SolveOptions) -> (SurfelSet, Solution) {
    let set = voxelize(scene, GridSpec::Resolution(resolution)).unwrap();
    let solution = solve(
        &set,
        &SolveOptions {
            threads: 2,
            ..options
        },
    )
    .unwrap();
    (set, solution)
}

/// `(emitted - absorbed) / emitted`, all channels together.
fn imbalance(solution: &Solution) -> f64 {
    let emitted: f64 = solution.stats.emitted_power.iter().sum();
    let absorbed: f64 = solution.stats.absorbed_power.iter().sum();
    (emitted - absorbed) / emitted
}

/// A closed unit box with black walls, a grey floor of reflectance `floor_rho` and a square lamp
/// of side `side` and emission `e` at height `h`, facing down (its back side is black).
fn lamp_over_floor(side: f64, h: f64, e: f64, floor_rho: f64) -> Scene {
    let mut scene = Scene::default();
    let black = scene.add_material(Material::new("black", [0.0; 3], [0.0; 3]));
    let floor = scene.add_material(Material::new("floor", [floor_rho; 3], [0.0; 3]));
    let lamp = scene.add_material(Material::new("lamp", [0.0; 3], [e; 3]));
    scene.add_box(DVec3::ZERO, DVec3::ONE, black, true);
    // add_box lists -z fifth: its two triangles are the floor.
    for t in &mut scene.triangles[8..10] {
        t.material = floor;
    }
    let (a, b) = (0.5 - side / 2.0, 0.5 + side / 2.0);
    // Counter-clockwise seen from below: the front faces the floor.
    scene.add_polygon(
        &[
            DVec3::new(a, a, h),
            DVec3::new(a, b, h),
            DVec3::new(b, b, h),
            DVec3::new(b, a, h),
        ],
        lamp,
    );
    scene
}

/// Irradiance at floor point `p` from a Lambertian square lamp (side `side`, radiosity `e`,
/// centred over (0.5, 0.5) at height `h`, parallel to the floor): the point-to-area form factor
/// `integral of cos cos' / (pi r^2) dA`, integrated on a 64 x 64 midpoint grid (the lamp spans a
/// few degrees, so the rule is exact far below the errors compared).
fn analytic_irradiance(p: DVec3, side: f64, h: f64, e: f64) -> f64 {
    let n = 64;
    let cell = side / n as f64;
    let mut sum = 0.0;
    for i in 0..n {
        for j in 0..n {
            let q = DVec3::new(
                0.5 - side / 2.0 + (i as f64 + 0.5) * cell,
                0.5 - side / 2.0 + (j as f64 + 0.5) * cell,
                h,
            );
            let d = q - p;
            let r2 = d.length_squared();
            let cos = (h - p.z) / r2.sqrt();
            sum += cos * cos / (std::f64::consts::PI * r2) * cell * cell;
        }
    }
    e * sum
}

/// Mean and largest relative error of the floor's radiosity against `rho * irradiance`, over
/// the floor's whole-voxel surfels.
fn floor_errors(
    set: &SurfelSet,
    solution: &Solution,
    side: f64,
    h: f64,
    e: f64,
    rho: f64,
) -> (f64, f64) {
    let (mut sum, mut worst, mut count) = (0.0, 0.0f64, 0);
    for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
        let p = set.grid.to_world(s.position());
        if s.normal[2].abs() < 0.99 || p.z > 0.01 || s.area < 0.5 {
            continue;
        }
        let exact = rho * analytic_irradiance(p, side, h, e);
        let got = b[common::inner_side(s, set)][0] as f64;
        let err = (got - exact).abs() / exact;
        sum += err;
        worst = worst.max(err);
        count += 1;
    }
    assert!(count > 500, "{count} floor surfels");
    (sum / count as f64, worst)
}

#[test]
fn furnace_stays_exact_with_the_direct_pass() {
    let (e, rho) = (1.0, 0.7);
    let expected = e / (1.0 - rho);
    let (set, solution) = run(
        &common::furnace(e, rho),
        8,
        SolveOptions {
            directions: 49,
            tolerance: Some(1e-7),
            direct: DirectPass::On(1000),
            ..Default::default()
        },
    );
    let direct = solution.stats.direct.as_ref().expect("the pass ran");
    assert_eq!(direct.emitting_surfels, set.surfels.len());
    let mut worst = 0.0f64;
    for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
        for &v in &b[common::inner_side(s, &set)] {
            worst = worst.max((v as f64 - expected).abs() / expected);
        }
    }
    let balance = imbalance(&solution);
    println!(
        "furnace with a {}-direction direct pass: worst {worst:.2e}, imbalance {balance:.2e}",
        direct.directions
    );
    assert!(worst < 1e-5, "worst {worst}");
    assert!(balance.abs() < 1e-5, "imbalance {balance}");
}

#[test]
fn direct_pass_is_independent_of_the_thread_count() {
    let scene = voxrad::gen::cornell_box();
    let options = |threads| SolveOptions {
        directions: 49,
        tolerance: Some(1e-4),
        direct: DirectPass::On(2000),
        threads,
        ..Default::default()
    };
    let set = voxelize(&scene, GridSpec::Resolution(16)).unwrap();
    let one = solve(&set, &options(1)).unwrap();
    let three = solve(&set, &options(3)).unwrap();
    assert_eq!(one.radiosity, three.radiosity);
}

#[test]
fn small_lamp_over_a_floor_is_closer_to_the_form_factor() {
    // A lamp 0.06 wide (two voxels at resolution 32) at height 0.7; black walls, so the floor's
    // B is rho times the lamp's irradiance, given by the form factor.
    let (side, h, e, rho) = (0.06, 0.7, 100.0, 0.5);
    let scene = lamp_over_floor(side, h, e, rho);
    let base = SolveOptions {
        directions: 193,
        tolerance: Some(1e-6),
        ..Default::default()
    };
    let (set, plain) = run(&scene, 32, base.clone());
    let (_, split) = run(
        &scene,
        32,
        SolveOptions {
            direct: DirectPass::On(20_000),
            ..base
        },
    );
    let (plain_mean, plain_max) = floor_errors(&set, &plain, side, h, e, rho);
    let (split_mean, split_max) = floor_errors(&set, &split, side, h, e, rho);
    let direct = split.stats.direct.as_ref().unwrap();
    println!(
        "floor against the form factor, 193 bounce directions: plain mean {:.1} % max {:.0} %; \
         with {} direct directions mean {:.1} % max {:.0} % ({:.3} s for the pass); imbalance \
         plain {:.2e}, split {:.2e}",
        100.0 * plain_mean,
        100.0 * plain_max,
        direct.directions,
        100.0 * split_mean,
        100.0 * split_max,
        direct.seconds,
        imbalance(&plain),
        imbalance(&split)
    );
    assert!(
        split_mean < 0.5 * plain_mean,
        "{split_mean} against {plain_mean}"
    );
    assert!(split_max < plain_max);
}

#[test]
fn closed_box_keeps_its_power_balance() {
    // A grey closed box lit by a glowing cube (nine voxels wide, a closed object, so no open
    // lamp edge over-counts its power): what the cube emits, the surfaces absorb. Where a ray
    // meets a face's plane is sampled at one point per receiver, so one placement of the cube
    // against the grid sends a little too much or too little (its width rounded to rows of
    // receivers, differently per direction); over placements that averages out. Measured over
    // these five placements: plain (109 directions) mean +0.65 %, largest 2.0 %; with the pass
    // (10,000 directions) mean -0.04 %, largest 2.5 %. Before the rim test of
    // `propagate::off_the_run` every placement over-counted: means -1.3 % and -3.4 %, largest
    // 3.8 % and 7.5 %.
    let mut plain = Vec::new();
    let mut split = Vec::new();
    for offset in [0.0, 0.007, 0.013, 0.021, 0.027] {
        let mut scene = Scene::default();
        let wall = scene.add_material(Material::new("wall", [0.6; 3], [0.0; 3]));
        let lamp = scene.add_material(Material::new("lamp", [0.3; 3], [50.0; 3]));
        scene.add_box(DVec3::ZERO, DVec3::ONE, wall, true);
        let shift = DVec3::new(1.0, 0.7, 1.3) * offset;
        let (lo, hi) = (
            DVec3::new(0.35, 0.35, 0.5) + shift,
            DVec3::new(0.65, 0.65, 0.8) + shift,
        );
        scene.add_box(lo, hi, lamp, false);
        let base = SolveOptions {
            directions: 109,
            tolerance: Some(1e-6),
            accelerate: true,
            ..Default::default()
        };
        plain.push(imbalance(&run(&scene, 32, base.clone()).1));
        split.push(imbalance(
            &run(
                &scene,
                32,
                SolveOptions {
                    direct: DirectPass::On(10_000),
                    ..base
                },
            )
            .1,
        ));
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let largest = |v: &[f64]| v.iter().fold(0.0f64, |a, b| a.max(b.abs()));
    let (p, s) = (mean(&plain), mean(&split));
    println!(
        "closed box imbalance over placements: plain mean {p:.2e} (largest {:.2e}), with the \
         direct pass mean {s:.2e} (largest {:.2e})",
        largest(&plain),
        largest(&split)
    );
    assert!(p.abs() < 0.01, "plain mean imbalance {p}");
    assert!(s.abs() < 0.005, "direct pass mean imbalance {s}");
    assert!(largest(&plain) < 0.035 && largest(&split) < 0.035);
}

#[test]
fn auto_applies_to_small_emitters_only() {
    let auto = SolveOptions {
        directions: 13,
        max_iterations: 1,
        direct: DirectPass::Auto(500),
        ..Default::default()
    };
    let (_, furnace) = run(&common::furnace(1.0, 0.5), 8, auto.clone());
    assert!(furnace.stats.direct.is_none(), "every surfel emits");
    let (_, lamp) = run(&lamp_over_floor(0.06, 0.7, 1.0, 0.5), 32, auto);
    assert!(lamp.stats.direct.is_some(), "a lamp of a few surfels");
}

#[test]
fn grey_scene_solved_once_gives_the_three_channel_answer() {
    // One channel solved and copied (grey materials) must stay the three-channel answer, bit for
    // bit, with the pass's direct light added to it.
    let scene = lamp_over_floor(0.1, 0.7, 10.0, 0.6);
    let options = |grey| SolveOptions {
        directions: 49,
        tolerance: Some(1e-5),
        direct: DirectPass::On(2000),
        grey,
        ..Default::default()
    };
    let set = voxelize(&scene, GridSpec::Resolution(16)).unwrap();
    let three = solve(&set, &options(false)).unwrap();
    let one = solve(&set, &options(true)).unwrap();
    assert_eq!(one.stats.channels, 1);
    assert_eq!(one.radiosity, three.radiosity);
    assert_eq!(one.stats.absorbed_power, three.stats.absorbed_power);
}

/// The direct pass searches a line only where a link from an emitting side can be found
/// (`propagate::find_partners_toward`): ahead from the voxels up to the last emitter's whose
/// side facing back emits, behind from the first emitter's whose side facing along emits, and
/// the emitters' own searches. On every line of an office (walls, desks, partitions, open-edged
/// lamps) along 13 directions, for spans, one-sided spans and single further positions, those
/// searches give exactly the links the full search gives from them, and no other. With target
/// positions (`Toward::targets`: the pass's emitters), the searches that cannot reach a target
/// are left out, and the links to targets are still exactly the full search's.
#[test]
fn the_pass_finds_the_links_of_a_full_search_within_its_span() {
    use voxrad::geometry::lines::LineFrame;
    use voxrad::geometry::order;
    use voxrad::solve::dispatch::{dispatch, lexicographic_orders, Lines};
    use voxrad::solve::propagate::{
        find_partners, find_partners_toward, for_each_link, prop_surfels, LineScratch, Toward,
    };
    let set = voxelize(&voxrad::gen::office().scene, GridSpec::Resolution(32)).expect("voxelize");
    let props = prop_surfels(&set);
    let key = |l: &voxrad::solve::propagate::Link| {
        (l.receiver, l.which, l.partner, l.share.to_bits(), l.to_side)
    };
    let orders = lexicographic_orders(&set);
    let (mut full, mut part) = (LineScratch::default(), LineScratch::default());
    let (mut checked, mut pruned_checks) = (0, 0);
    let mut all_links = Vec::new();
    for d in &voxrad::geometry::directions::DirectionSet::with_count(13).directions {
        let ordered = &orders[order::order_of(d.vector)];
        let mut lines = Lines::default();
        dispatch(
            ordered,
            &LineFrame::new(d.vector, set.grid.dims),
            1,
            &mut lines,
        );
        for l in 0..lines.line_count() {
            let line = lines.line(l);
            let n = line.len();
            if n < 2 {
                continue;
            }
            find_partners(line, &props, d.unit, &mut full);
            let voxel = |k: usize| set.surfels[line[k] as usize].voxel;
            let (third, half) = (n / 3, n / 2);
            let (one, end) = ([third as u32], [(n - 1) as u32]);
            let cases = [
                Toward::span(0, n - 1),
                Toward::span(third, half),
                Toward::span(n - 1, n - 1),
                Toward::span(1.min(n - 1), 1.min(n - 1)),
                // One-sided emitters: only one of the two spans, and an emitter's own search.
                Toward {
                    ahead_upto: Some(half),
                    also_behind: &one,
                    ..Toward::default()
                },
                Toward {
                    behind_from: Some(third),
                    also_ahead: &end,
                    ..Toward::default()
                },
            ];
            // Targets: every third position from the first, then from the second (each a
            // line's surfels picked regardless of what they are).
            let target_sets: [Vec<bool>; 2] =
                [0, 1].map(|from| (0..n).map(|k| k % 3 == from).collect());
            for (toward, targets) in cases.iter().map(|&t| (t, None)).chain(
                target_sets
                    .iter()
                    .map(|t| (Toward::span(0, n - 1), Some(t))),
            ) {
                let toward = Toward {
                    targets: targets.map_or(&[][..], |t| &t[..]),
                    ..toward
                };
                find_partners_toward(line, &props, d.unit, &mut part, Some(toward));
                let mut expected = Vec::new();
                for_each_link(&full, d.unit, |link| {
                    let k = link.receiver;
                    let wanted = if link.which == 0 {
                        toward
                            .ahead_upto
                            .is_some_and(|last| k <= last || voxel(k) == voxel(last))
                            || toward.also_ahead.contains(&(k as u32))
                    } else {
                        toward
                            .behind_from
                            .is_some_and(|first| k >= first || voxel(k) == voxel(first))
                            || toward.also_behind.contains(&(k as u32))
                    };
                    // With targets, the links to them, and none that the full search lacks.
                    let to_target = targets.is_none_or(|t| t[link.partner]);
                    if wanted && to_target {
                        expected.push(key(&link));
                    }
                });
                let mut got = Vec::new();
                for_each_link(&part, d.unit, |link| {
                    if targets.is_none_or(|t| t[link.partner]) {
                        got.push(key(&link));
                    } else {
                        all_links.push(key(&link));
                    }
                });
                expected.sort_unstable();
                got.sort_unstable();
                assert_eq!(got, expected, "line {l} of {:?}, {toward:?}", d.vector);
                checked += got.len();
                if targets.is_some() {
                    // The links to other surfels that the pruned search still found are links
                    // of the full search.
                    let mut full_links = Vec::new();
                    for_each_link(&full, d.unit, |link| full_links.push(key(&link)));
                    full_links.sort_unstable();
                    for link in all_links.drain(..) {
                        assert!(
                            full_links.binary_search(&link).is_ok(),
                            "line {l}: {link:?}"
                        );
                    }
                    pruned_checks += 1;
                }
            }
        }
    }
    assert!(checked > 10_000, "{checked} links compared");
    assert!(pruned_checks > 1_000, "{pruned_checks} lines with targets");
}

//! Hard cases stay numerically stable: each scene here pushes one number to an extreme (a
//! reflectance next to 1, emissions twelve decades apart, a lamp smaller than a voxel, coordinates
//! far from the origin, huge grids, degenerate geometry, nothing to light, nothing that reflects)
//! and checks the answer physics gives, plus the power balance (emitted against absorbed) where the
//! scene is closed. Grids and direction sets are small so that the whole file runs in seconds.
//!
//! A furnace cannot show a wrong partner (every surfel has the same radiosity): the furnace cases
//! have twins lit by one lamp, checked against the path-traced reference, in
//! `tests/hard_case_twins.rs`.

mod common;

use glam::DVec3;
use voxrad::geometry::lines::{line_of, LineFrame};
use voxrad::scene::{Material, Scene, Triangle};
use voxrad::solve::{solve, Solution, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec, VoxelizeError, MAX_GRID_EDGE};
use voxrad::voxel::{SurfelSet, FRONT};

fn run(
    scene: &Scene,
    resolution: u32,
    directions: usize,
    options: SolveOptions,
) -> (SurfelSet, Solution) {
    let set = voxelize(scene, GridSpec::Resolution(resolution)).unwrap();
    let solution = solve(
        &set,
        &SolveOptions {
            directions,
            threads: 2,
            ..options
        },
    )
    .unwrap();
    (set, solution)
}

/// Largest relative deviation from `expected` over the inner sides of the unit furnace's walls.
fn furnace_worst(set: &SurfelSet, solution: &Solution, expected: f64) -> f64 {
    let mut worst = 0.0f64;
    for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
        let side = common::inner_side(s, set);
        for &v in &b[side] {
            worst = worst.max((v as f64 - expected).abs() / expected);
        }
    }
    worst
}

/// Relative power imbalance `(emitted - absorbed) / emitted`, all channels together.
fn imbalance(solution: &Solution) -> f64 {
    let emitted: f64 = solution.stats.emitted_power.iter().sum();
    let absorbed: f64 = solution.stats.absorbed_power.iter().sum();
    (emitted - absorbed) / emitted
}

#[test]
fn reflectance_0_999_converges_to_e_over_1_minus_rho_without_drift() {
    let (e, rho) = (1.0, 0.999);
    let expected = e / (1.0 - rho);
    let scene = common::furnace(e, rho);
    // The stopping rule must keep going about ln(1e-4) / ln(0.999) ~ 9,200 iterations, where a
    // bare change below 1e-4 would stop after about 2,300 with B 10 % short.
    let (set, converged) = run(
        &scene,
        6,
        13,
        SolveOptions {
            max_iterations: 40_000,
            tolerance: Some(1e-4),
            ..Default::default()
        },
    );
    let worst = furnace_worst(&set, &converged, expected);
    println!(
        "rho 0.999: worst error {worst:.2e} after {} iterations (residual {:.2e})",
        converged.stats.iterations, converged.stats.residual
    );
    assert!(converged.stats.converged);
    assert!(converged.stats.iterations > 5_000);
    assert!(worst < 2e-4, "worst relative error {worst}");
    // Many more iterations than needed: the fixed point must hold (no drift, no blow-up).
    let (_, long) = run(
        &scene,
        6,
        13,
        SolveOptions {
            max_iterations: converged.stats.iterations + 5_000,
            tolerance: None,
            ..Default::default()
        },
    );
    let drift = furnace_worst(&set, &long, expected);
    println!(
        "after {} iterations: worst error {drift:.2e}",
        long.stats.iterations
    );
    assert!(
        drift <= worst.max(5e-5),
        "drifted to a relative error of {drift}"
    );
    // Closed box: every emitted watt is absorbed, here through walls that absorb only 0.1 %.
    let balance = imbalance(&long);
    println!("power imbalance {balance:.2e}");
    assert!(balance.abs() < 1e-3, "imbalance {balance}");
}

/// A grey closed box with five small emitting patches (0.12 x 0.2) facing up at `height` above
/// its floor, emitting `scale` times 1e-6, 1e-3, 1, 1e3 and 1e6.
fn decades_scene(scale: f64, height: f64) -> (Scene, Vec<f64>) {
    let mut scene = Scene::default();
    let wall = scene.add_material(Material::new("wall", [0.5; 3], [0.0; 3]));
    scene.add_box(DVec3::ZERO, DVec3::ONE, wall, true);
    let emissions: Vec<f64> = [1e-6, 1e-3, 1.0, 1e3, 1e6]
        .iter()
        .map(|e| e * scale)
        .collect();
    for (k, &e) in emissions.iter().enumerate() {
        let m = scene.add_material(Material::new(&format!("lamp{k}"), [0.5; 3], [e; 3]));
        let x = 0.1 + 0.17 * k as f64;
        scene.add_polygon(
            &[
                DVec3::new(x, 0.4, height),
                DVec3::new(x + 0.12, 0.4, height),
                DVec3::new(x + 0.12, 0.6, height),
                DVec3::new(x, 0.6, height),
            ],
            m,
        );
    }
    (scene, emissions)
}

#[test]
fn emitters_twelve_decades_apart_are_all_kept() {
    let options = SolveOptions {
        tolerance: Some(1e-5),
        ..Default::default()
    };
    // At resolution 24 the lamps hang 2.3 voxels above the floor (see
    // `lamp_in_the_floor_voxels_keeps_its_energy` for lamps closer than a voxel).
    let (scene, emissions) = decades_scene(1.0, 0.1);
    let (set, solution) = run(&scene, 24, 49, options.clone());
    // Every emitter's own front keeps at least its emission, and nothing is infinite or NaN.
    let mut seen = vec![false; emissions.len()];
    for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
        assert!(b.iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
        let m = &set.materials[s.material[FRONT] as usize];
        if let Some(k) = m.name.strip_prefix("lamp") {
            let k: usize = k.parse().unwrap();
            seen[k] = true;
            assert!(
                b[FRONT][0] >= emissions[k] as f32,
                "lamp {k}: B {} below E {}",
                b[FRONT][0],
                emissions[k]
            );
        }
    }
    assert!(seen.iter().all(|&s| s), "every lamp got surfels: {seen:?}");
    let balance = imbalance(&solution);
    // Measured -4.2 %: each lamp is 3 x 5 voxels, and rays that graze a lamp's rim voxels see a
    // whole voxel's worth of it (the open-edge coverage corrects this only on average).
    println!("decades: power imbalance {balance:.2e}");
    assert!(balance.abs() < 0.06, "imbalance {balance}");

    // The equation is linear: emissions scaled by 1e-30 or 1e25 must scale every B exactly as
    // much (no flush to zero of the small values, no overflow of the large ones in f32 storage:
    // 1e31 is still below f32::MAX = 3.4e38).
    for scale in [1e-30, 1e25] {
        let (scaled_scene, _) = decades_scene(scale, 0.1);
        let (_, scaled) = run(&scaled_scene, 24, 49, options.clone());
        assert_eq!(scaled.stats.iterations, solution.stats.iterations);
        let mut worst = 0.0f64;
        for (a, b) in solution.radiosity.iter().zip(&scaled.radiosity) {
            for (&x, &y) in a.iter().flatten().zip(b.iter().flatten()) {
                assert!(y.is_finite());
                let x = x as f64 * scale;
                if x > 0.0 {
                    worst = worst.max((y as f64 - x).abs() / x);
                }
            }
        }
        println!("scale {scale:e}: worst relative deviation from linearity {worst:.2e}");
        assert!(worst < 1e-5, "scale {scale}: deviation {worst}");
    }
}

/// Lamps hanging 0.46 voxel above the floor share their rim voxels with the floor. Their rim
/// pieces are open edges all the same (the floor's plane is parallel, so it bounds nothing), and a
/// ray through such a voxel takes the lamp piece's share and goes on to the floor piece in the
/// same voxel. Before both were handled the lamps looked a voxel wider on every side: 86 % more
/// power absorbed than emitted. Measured now: 1.7 % more.
#[test]
fn lamp_in_the_floor_voxels_keeps_its_energy() {
    let (scene, _) = decades_scene(1.0, 0.02);
    let (_, solution) = run(
        &scene,
        24,
        49,
        SolveOptions {
            tolerance: Some(1e-5),
            ..Default::default()
        },
    );
    let balance = imbalance(&solution);
    println!("lamps 0.46 voxel above the floor: power imbalance {balance:.2e}");
    assert!(balance.abs() < 0.05, "imbalance {balance}");
}

/// A closed box whose walls are black except a grey floor, with a square lamp of side `side`
/// hanging at height `h`, facing down.
fn tiny_lamp_scene(side: f64, h: f64, emission: f64, floor_rho: f64) -> Scene {
    let mut scene = Scene::default();
    let black = scene.add_material(Material::new("black", [0.0; 3], [0.0; 3]));
    let floor = scene.add_material(Material::new("floor", [floor_rho; 3], [0.0; 3]));
    let lamp = scene.add_material(Material::new("lamp", [0.0; 3], [emission; 3]));
    scene.add_box(DVec3::ZERO, DVec3::ONE, black, true);
    // add_box lists -z fifth: its two triangles are the floor.
    for t in &mut scene.triangles[8..10] {
        t.material = floor;
    }
    let (a, b) = (0.5 - side / 2.0, 0.5 + side / 2.0);
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

#[test]
fn tiny_bright_lamp_keeps_its_energy() {
    // At resolution 32 a voxel is 1/31 wide: the lamp is a third of a voxel across.
    let (side, h, e, rho) = (0.01, 0.7, 1e6, 0.5);
    let scene = tiny_lamp_scene(side, h, e, rho);
    let (set, solution) = run(
        &scene,
        32,
        193,
        SolveOptions {
            tolerance: Some(1e-6),
            ..Default::default()
        },
    );
    assert!(solution
        .radiosity
        .iter()
        .flatten()
        .flatten()
        .all(|v| v.is_finite()));
    let emitted = solution.stats.emitted_power[0];
    let exact_emitted = e * side * side;
    let balance = imbalance(&solution);
    println!(
        "tiny lamp: emitted {emitted:.4} (geometric {exact_emitted:.4}), imbalance {balance:.3e}"
    );
    // The lamp's voxel pieces carry its exact area.
    assert!((emitted - exact_emitted).abs() < 1e-6 * exact_emitted);
    // Closed box: what is emitted is absorbed. Measured: 29 % more absorbed than emitted. A lamp a
    // third of a voxel wide is seen through whole discrete lines: along a line whose main axis
    // lies in the lamp's plane, its coverage (area / voxel face) is compared with the line's
    // cross-section, which is |s_main| / |n . s| times smaller than the voxel face as seen along s,
    // so grazing directions over-count it. The bound states the measured figure.
    assert!(balance.abs() < 0.35, "imbalance {balance}");

    // The aliasing: the floor's B against the point-source answer
    // rho * E A cos^2 / (pi r^2) (the lamp is tiny and the other walls black, so one bounce is
    // the whole answer on the floor).
    let floor = |solution: &Solution| {
        let lamp_centre = DVec3::new(0.5, 0.5, h);
        let (mut sum, mut worst, mut count) = (0.0, 0.0f64, 0);
        let (mut floor_total, mut exact_total) = (0.0, 0.0);
        for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
            let p = set.grid.to_world(s.position());
            if s.normal[2].abs() < 0.99 || p.z > 0.01 || s.area < 0.5 {
                continue;
            }
            let d = lamp_centre - p;
            let r2 = d.length_squared();
            let cos = d.z / r2.sqrt();
            let exact = rho * e * side * side * cos * cos / (std::f64::consts::PI * r2);
            let got = b[common::inner_side(s, &set)][0] as f64;
            let err = (got - exact).abs() / exact;
            sum += err;
            worst = worst.max(err);
            count += 1;
            floor_total += got * s.area as f64;
            exact_total += exact * s.area as f64;
        }
        assert!(count > 500);
        (sum / count as f64, worst, floor_total / exact_total - 1.0)
    };
    let (mean, worst, total_error) = floor(&solution);
    println!(
        "tiny lamp aliasing on the floor with {} directions: pointwise mean {:.0} %, max {:.0} %; \
         floor total {:+.1} %",
        solution.stats.directions,
        100.0 * mean,
        100.0 * worst,
        100.0 * total_error
    );
    // Pointwise, a floor voxel sees the lamp through one discrete line or none (measured mean
    // error 163 %, max 707 % with 193 directions): that is the aliasing the brief warns of. The
    // floor's total must match the point-source answer; measured -10 % (the floor sees the lamp
    // face on, so the grazing over-count above hits the walls, not the floor).
    assert!(total_error.abs() < 0.2, "floor total off by {total_error}");

    // The remedy (`solve::direct`): the lamp's light gathered once along 80,000 directions from
    // its own lines, the bounces with the same 193. Measured: pointwise mean 8 %, max 22 %,
    // floor total -2.2 %. The imbalance grows to 36 % (from 29 %): the grazing over-count of the
    // lamp's stand-in above, now sampled by many more grazing directions.
    let (_, split) = run(
        &scene,
        32,
        193,
        SolveOptions {
            tolerance: Some(1e-6),
            direct: voxrad::solve::direct::DirectPass::On(80_000),
            ..Default::default()
        },
    );
    let (split_mean, split_worst, split_total) = floor(&split);
    println!(
        "with a direct pass of {} directions: pointwise mean {:.0} %, max {:.0} %; floor total \
         {:+.1} %; imbalance {:.3e}",
        split.stats.direct.as_ref().map_or(0, |d| d.directions),
        100.0 * split_mean,
        100.0 * split_worst,
        100.0 * split_total,
        imbalance(&split)
    );
    assert!(split_mean < 0.25 * mean, "pointwise mean {split_mean}");
    assert!(split_worst < 0.25 * worst, "pointwise max {split_worst}");
    assert!(split_total.abs() < 0.05, "floor total off by {split_total}");
    assert!(
        imbalance(&split).abs() < 0.4,
        "imbalance {}",
        imbalance(&split)
    );
}

/// Inside a glowing furnace, any closed object with the same E and rho leaves
/// B = E / (1 - rho) on every visible side. The objects: a slab thinner than a voxel (0.01, that is
/// 0.24 voxel at resolution 25), tilted by `tilt` radians off the floor (lines meet it at grazing
/// angles), and a cube whose edges and corners lie exactly on voxel corners. Returns the median,
/// 99th percentile and largest relative error over front sides, and the power imbalance.
fn thin_slab_furnace(tilt: f64) -> (f64, f64, f64, f64) {
    let (e, rho) = (1.0, 0.5);
    let mut scene = common::furnace(e, rho);
    let m = 0;
    let (c, s) = (tilt.cos(), tilt.sin());
    let thickness = 0.01;
    let corner = |x: f64, y: f64, z: f64| {
        // Rotate about the x axis through (0.5, 0.5, 0.3).
        let (y0, z0) = (y - 0.5, z);
        DVec3::new(x, 0.5 + c * y0 - s * z0, 0.3 + s * y0 + c * z0)
    };
    let lo = [0.2, 0.2, 0.0];
    let hi = [0.8, 0.8, thickness];
    let p = |i: usize, j: usize, k: usize| {
        corner(
            if i == 0 { lo[0] } else { hi[0] },
            if j == 0 { lo[1] } else { hi[1] },
            if k == 0 { lo[2] } else { hi[2] },
        )
    };
    // Faces counter-clockwise seen from outside (fronts outwards).
    let faces = [
        [p(0, 0, 0), p(0, 0, 1), p(0, 1, 1), p(0, 1, 0)],
        [p(1, 0, 0), p(1, 1, 0), p(1, 1, 1), p(1, 0, 1)],
        [p(0, 0, 0), p(1, 0, 0), p(1, 0, 1), p(0, 0, 1)],
        [p(0, 1, 0), p(0, 1, 1), p(1, 1, 1), p(1, 1, 0)],
        [p(0, 0, 0), p(0, 1, 0), p(1, 1, 0), p(1, 0, 0)],
        [p(0, 0, 1), p(1, 0, 1), p(1, 1, 1), p(0, 1, 1)],
    ];
    for f in faces {
        scene.add_polygon(&f, m);
    }
    // Resolution 25: voxel centres at multiples of 1/24 from the origin, voxel corners half a
    // voxel off. A cube from corner to corner: 13.5 / 24 to 18.5 / 24.
    let (a, b) = (13.5 / 24.0, 18.5 / 24.0);
    scene.add_box(DVec3::new(a, a, a), DVec3::new(b, b, b), m, false);
    let (set, solution) = run(
        &scene,
        25,
        193,
        SolveOptions {
            tolerance: Some(1e-6),
            ..Default::default()
        },
    );
    let expected = e / (1.0 - rho);
    // Front sides face into the air everywhere (walls inwards, objects outwards) except where
    // two objects touch; the slab and the cube do not touch anything.
    let mut errors: Vec<f64> = set
        .surfels
        .iter()
        .zip(&solution.radiosity)
        .filter(|(s, _)| s.area >= 0.05)
        .map(|(_, b)| (b[FRONT][0] as f64 - expected).abs() / expected)
        .collect();
    errors.sort_by(|x, y| x.total_cmp(y));
    let n = errors.len();
    let (median, p99, worst) = (errors[n / 2], errors[n * 99 / 100], errors[n - 1]);
    let balance = imbalance(&solution);
    println!(
        "thin slab tilted {tilt} rad and aligned cube: {n} fronts, median {median:.2e}, \
         99th {p99:.2e}, max {worst:.2e}; power imbalance {balance:.2e}"
    );
    (median, p99, worst, balance)
}

#[test]
fn thin_slab_and_grid_aligned_corners_in_a_furnace() {
    // Measured: median, 99th percentile and max 9.5e-7, imbalance 1.9e-6. Until the sides
    // inside closed solids went dark (`voxel::enclosed`) and a ray that met one was given the
    // face it entered by or let pass a corner it only grazed (`propagate`, `entry_face`): median
    // 2.8e-3, 99th percentile 3.8e-2, max 7.1e-2 (the slab's rim voxels, which hold three
    // planes, saw the slab's edge as a whole voxel), imbalance up to 1e-2.
    let (median, p99, worst, balance) = thin_slab_furnace(0.0);
    assert!(median < 1e-4, "median {median}");
    assert!(p99 < 1e-3, "99th percentile {p99}");
    assert!(worst < 0.01, "worst {worst}");
    assert!(balance.abs() < 1e-3, "imbalance {balance}");
}

/// Tilted by 0.05 rad. The box of the slab's end face, a strip sheared in its own plane, reaches
/// 0.05 voxel past the slab's top and bottom planes, which it only touches; until
/// `propagate::side_of` allowed for that, rays passing just by the slab's end were taken as
/// hitting the end face's inside, and the top surfels next to the end faces were up to 15 % dark
/// (median 6.8e-3, 99th percentile 0.051, max 0.155); then, until rays that meet a side inside a
/// solid were given the face they entered by (`propagate`, `entry_face`), median 4e-3,
/// 99th percentile 0.05, max 0.1. Measured now: median 5.1e-6, 99th percentile 1.4e-4, max 3.2e-2,
/// imbalance 4.2e-5.
#[test]
fn tilted_thin_slab_in_a_furnace() {
    let (median, p99, worst, balance) = thin_slab_furnace(0.05);
    println!("tilted slab furnace: median {median:.2e}, p99 {p99:.3}, worst {worst:.3}, balance {balance:.2e}");
    assert!(median < 1e-4, "median {median}");
    assert!(p99 < 2e-3, "99th percentile {p99}");
    assert!(worst < 0.05, "worst {worst}");
    assert!(balance.abs() < 1e-3, "imbalance {balance}");
}

/// The small-lamp room of `trivial_scenes`, shifted by `offset`.
fn lamp_room(offset: DVec3) -> Scene {
    let mut scene = Scene::default();
    let wall = scene.add_material(Material::new("wall", [0.6; 3], [0.0; 3]));
    let red = scene.add_material(Material::new("red", [0.7, 0.1, 0.1], [0.0; 3]));
    let lamp = scene.add_material(Material::new("lamp", [0.0; 3], [4.0; 3]));
    scene.add_box(DVec3::ZERO, DVec3::ONE, wall, true);
    scene.add_box(
        DVec3::new(0.2, 0.2, 0.0),
        DVec3::new(0.45, 0.5, 0.35),
        red,
        false,
    );
    scene.add_polygon(
        &[
            DVec3::new(0.35, 0.35, 0.95),
            DVec3::new(0.35, 0.65, 0.95),
            DVec3::new(0.65, 0.65, 0.95),
            DVec3::new(0.65, 0.35, 0.95),
        ],
        lamp,
    );
    for t in &mut scene.triangles {
        t.vertices = t.vertices.map(|v| v + offset);
    }
    scene
}

#[test]
fn far_from_the_origin_gives_the_same_answer() {
    let options = SolveOptions {
        tolerance: Some(1e-5),
        ..Default::default()
    };
    let (near_set, near) = run(&lamp_room(DVec3::ZERO), 24, 49, options.clone());
    for offset in [DVec3::splat(1e7), DVec3::new(-3e7, 1e7, 5e6)] {
        let (far_set, far) = run(&lamp_room(offset), 24, 49, options.clone());
        assert_eq!(far_set.surfels.len(), near_set.surfels.len());
        assert_eq!(far_set.grid.dims, near_set.grid.dims);
        let mut worst = 0.0f64;
        for ((s, t), (a, b)) in near_set
            .surfels
            .iter()
            .zip(&far_set.surfels)
            .zip(near.radiosity.iter().zip(&far.radiosity))
        {
            assert_eq!(s.voxel, t.voxel);
            for (&x, &y) in a.iter().flatten().zip(b.iter().flatten()) {
                worst = worst.max((x - y).abs() as f64 / x.abs().max(1e-3) as f64);
            }
        }
        println!("offset {offset}: worst relative difference {worst:.2e}");
        // Coordinates near 1e7 keep about 1e-9 of a unit in f64; voxel-relative points (f32)
        // may move by one rounding step, which changes nothing visible.
        assert!(worst < 1e-3, "offset {offset}: {worst}");
    }
}

#[test]
fn largest_grid_line_indices_do_not_overflow() {
    // The largest grid the voxelizer accepts, with steep and oblique directions: every corner
    // voxel's dense line index is in range, and two voxels share a dense index exactly when they
    // share the exact (i, j) line.
    let edge = MAX_GRID_EDGE as u32;
    let dims = [edge, edge, edge];
    let far = (edge - 1) as i32;
    let corners: Vec<[i32; 3]> = (0..8)
        .map(|k| [k & 1, (k >> 1) & 1, (k >> 2) & 1].map(|b| b * far))
        .collect();
    for vector in [
        [20i64, -19, 20],
        [1, 1, 1],
        [-20, 3, 1],
        [0, 0, 1],
        [7, 20, -13],
    ] {
        let frame = LineFrame::new(vector, dims);
        // (ni * nj) below 2^64 and above the voxel count of a layer.
        assert!(frame.line_count >= (edge as u64) * (edge as u64));
        for &p in &corners {
            assert!(frame.line_index(p) < frame.line_count, "{vector:?} {p:?}");
            for &q in &corners {
                let exact = line_of(vector, p.map(i64::from)) == line_of(vector, q.map(i64::from));
                assert_eq!(
                    exact,
                    frame.line_index(p) == frame.line_index(q),
                    "{vector:?} {p:?} {q:?}"
                );
            }
        }
    }
    // A grid beyond the limit is refused with an error, not a panic or a wrap-around.
    let mut scene = common::furnace(1.0, 0.5);
    scene.triangles.push(Triangle {
        vertices: [
            DVec3::ZERO,
            DVec3::new(1e9, 0.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
        ],
        material: 0,
    });
    match voxelize(&scene, GridSpec::VoxelSize(1.0)) {
        Err(VoxelizeError::GridTooLarge { .. }) => {}
        other => panic!("expected GridTooLarge, got {:?}", other.map(|s| s.grid)),
    }
}

#[test]
fn degenerate_and_duplicate_triangles_change_nothing() {
    let (e, rho) = (1.0, 0.8);
    let plain = common::furnace(e, rho);
    let mut messy = plain.clone();
    // Every wall triangle twice, plus zero-area triangles: a repeated vertex, three collinear
    // points, a single point, and a sliver 1e-12 wide.
    let copies = messy.triangles.clone();
    messy.triangles.extend(copies);
    let p = |x, y, z| DVec3::new(x, y, z);
    for vertices in [
        [p(0.3, 0.3, 0.3), p(0.3, 0.3, 0.3), p(0.6, 0.2, 0.4)],
        [p(0.1, 0.1, 0.1), p(0.5, 0.5, 0.5), p(0.9, 0.9, 0.9)],
        [p(0.4, 0.6, 0.2); 3],
        [p(0.2, 0.5, 0.5), p(0.8, 0.5, 0.5), p(0.5, 0.5 + 1e-12, 0.5)],
    ] {
        messy.triangles.push(Triangle {
            vertices,
            material: 0,
        });
    }
    let options = SolveOptions {
        tolerance: Some(1e-6),
        ..Default::default()
    };
    let expected = e / (1.0 - rho);
    let (set, solution) = run(&messy, 12, 49, options.clone());
    assert!(solution
        .radiosity
        .iter()
        .flatten()
        .flatten()
        .all(|v| v.is_finite()));
    // The walls' inner sides (the sliver is a real, if tiny, two-sided sheet: its back, which
    // does not emit, is rightly darker, so it is left out here).
    let mut worst = 0.0f64;
    for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
        let p = set.grid.to_world(s.position());
        if p.min_element() > 0.05 && p.max_element() < 0.95 {
            continue;
        }
        for &v in &b[common::inner_side(s, &set)] {
            worst = worst.max((v as f64 - expected).abs() / expected);
        }
    }
    let (_, clean) = run(&plain, 12, 49, options);
    println!(
        "degenerate and duplicate triangles: worst {worst:.2e}; surfels {} (clean {})",
        set.surfels.len(),
        clean.radiosity.len()
    );
    assert!(worst < 1e-3, "worst {worst}");
    // Duplicates must not double the emitted power: the wall's area is its geometric area.
    let (a, b) = (
        solution.stats.emitted_power[0],
        clean.stats.emitted_power[0],
    );
    println!("emitted power: messy {a:.6}, clean {b:.6} (geometric 6)");
    assert!((b - 6.0).abs() < 1e-6 * 6.0, "clean emitted {b}");
    assert!(
        (a - b).abs() < 1e-6 * b,
        "duplicates changed the emitted power: {a} vs {b}"
    );
}

#[test]
fn emitter_free_scene_runs_no_iteration() {
    let (set, solution) = run(&common::furnace(0.0, 0.9), 12, 49, SolveOptions::default());
    assert!(!set.surfels.is_empty());
    assert_eq!(solution.stats.iterations, 0);
    assert!(solution.stats.converged);
    assert!(solution
        .radiosity
        .iter()
        .flatten()
        .flatten()
        .all(|&b| b == 0.0));
    assert_eq!(solution.stats.emitted_power, [0.0; 3]);
    assert_eq!(solution.stats.absorbed_power, [0.0; 3]);
}

#[test]
fn black_furnace_is_one_pass_with_b_equal_e() {
    // Every wall emits and reflects nothing: B = E exactly after one pass, and all of it is
    // absorbed (the box is closed).
    let (set, solution) = run(&common::furnace(2.5, 0.0), 12, 49, SolveOptions::default());
    assert_eq!(solution.stats.iterations, 1);
    for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
        let side = common::inner_side(s, &set);
        for &v in &b[side] {
            assert_eq!(v, 2.5);
        }
    }
    let balance = imbalance(&solution);
    println!("black furnace: power imbalance {balance:.2e}");
    assert!(balance.abs() < 1e-3, "imbalance {balance}");
}

#[test]
fn tight_tolerance_at_reflectance_0_999_stops_at_the_f32_floor() {
    // A tolerance of 1e-6 is below what f32 storage can show at rho 0.999 (its rounding, about
    // 6e-8 relative, times rho / (1 - rho) = 999, is 6e-5): the changes stop shrinking. The
    // solve must notice, stop with the answer as close as f32 allows, and not claim convergence,
    // instead of running to max_iterations.
    let max_iterations = 40_000;
    let (set, solution) = run(
        &common::furnace(1.0, 0.999),
        6,
        13,
        SolveOptions {
            max_iterations,
            tolerance: Some(1e-6),
            ..Default::default()
        },
    );
    let stats = &solution.stats;
    let worst = furnace_worst(&set, &solution, 1000.0);
    println!(
        "rho 0.999, tolerance 1e-6: stopped after {} iterations (stalled {}), worst relative \
         error {worst:.2e}",
        stats.iterations, stats.stalled
    );
    assert!(stats.stalled && !stats.converged, "{stats:?}");
    assert!(stats.iterations < max_iterations / 2, "{stats:?}");
    // As close as the f32 floor allows: no drift, no blow-up.
    assert!(worst < 2e-4, "worst {worst:e}");
}

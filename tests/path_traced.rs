//! voxrad against an answer it did not produce: the path-traced reference data in
//! `tests/data/reference` (Mitsuba 3, see that directory's README), and the power balance of
//! closed scenes lit unevenly.
//!
//! - Thin slabs 0.3 to 2 voxels thick at resolution 128, axis-aligned and tilted, lit from one
//!   side or raked from above: the mean over each face within 3 % of the reference (one face,
//!   measured -3.04 %, within 3.5 %; all 32 faces measured: 1.06 to 3.04 %). (The whole
//!   set of 16 runs with `VOXRAD_REFERENCE_ALL=1`; by default a quarter of it, one of each
//!   thickness, so that CI stays short.)
//! - The realistic rooms (a furnished room lit by a window, a corridor of rooms with small
//!   lamps) and the Cornell box: mean error at their probes, against bounds measured when the
//!   open-edge rules of `solve::propagate` were made (the figures are in the closing notes and
//!   `docs/`); a change that makes voxrad worse against physics fails here.
//! - The same probes answered by gathering (`voxrad probe --gather`, `output::sensor`): the
//!   irradiance and the radiosity within 2 % on average of the reference; the `high` preset's
//!   gathered answer on the corridor within that preset's goal (0.5 % mean, 3 % most), and the
//!   `default` preset's on the office within its own (1.5 % mean, 10 % most).
//! - Closed scenes absorb what they emit: lamps floating under a ceiling, the window room, the
//!   corridor, the slab boxes.
//!
//! A furnace cannot see a wrong partner (every surfel has the same radiosity there); every scene
//! here is lit from one place.

use std::path::{Path, PathBuf};
use voxrad::output::sensor::SensorField;
use voxrad::output::{ProbeIndex, Results};
use voxrad::scene::Scene;
use voxrad::solve::direct::DirectPass;
use voxrad::solve::{solve, SolveOptions};
use voxrad::study::reference::{Comparison, Reference};
use voxrad::voxel::voxelize::{voxelize, GridSpec};

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/reference")
        .join(name)
}

fn scene_of(name: &str) -> Scene {
    let dir = data(name);
    let obj = if name == "cornell" {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj")
    } else {
        dir.join("scene.obj")
    };
    voxrad::scene::obj::load_obj(&obj).unwrap_or_else(|e| panic!("{}: {e}", obj.display()))
}

/// The settings of every solve here: tolerance 1e-4 with tail extrapolation, and a direct-light
/// pass of about `dense` directions (none for 0).
fn options(directions: usize, dense: usize) -> SolveOptions {
    SolveOptions {
        directions,
        max_iterations: 200,
        tolerance: Some(1e-4),
        threads: 2,
        accelerate: true,
        direct: if dense > 0 {
            DirectPass::On(dense)
        } else {
            DirectPass::Off
        },
        ..Default::default()
    }
}

/// `B_r + B_g + B_b` of each probe row answered by gathering (`voxrad probe --gather`); `None`
/// where the row found no surface.
fn gathered_radiosity(field: &SensorField, rows: &[voxrad::output::ProbeRow]) -> Vec<Option<f64>> {
    rows.iter()
        .map(|row| {
            let g = field.gather_row(row);
            g.found.then(|| g.radiosity.iter().sum())
        })
        .collect()
}

/// Solves `scene` and returns the comparison with its reference (of the radiosity, of the
/// irradiance `H` that `voxrad probe` reports beside it, and of the irradiance sensors gather at
/// the probes) and the power balance.
fn run(
    name: &str,
    resolution: u32,
    directions: usize,
    dense: usize,
) -> (Comparison, Comparison, Comparison, Comparison, f64) {
    let reference = Reference::load(&data(name)).unwrap_or_else(|e| panic!("{e}"));
    let scene = scene_of(name);
    let set = voxelize(&scene, GridSpec::Resolution(resolution)).unwrap();
    let solution = solve(&set, &options(directions, dense)).unwrap();
    let results = Results::from_solution(&set, &solution).unwrap();
    let index = ProbeIndex::new(&results);
    let rows: Vec<_> = reference
        .points()
        .iter()
        .map(|&(p, n)| index.lookup(p, n))
        .collect();
    let values: Vec<Option<f64>> = rows
        .iter()
        .map(|row| row.found.then(|| row.radiosity.iter().sum()))
        .collect();
    let comparison = reference.compare(&values);
    let irradiance: Vec<Option<f64>> = rows
        .iter()
        .map(|row| row.found.then(|| row.irradiance.iter().sum()))
        .collect();
    let irradiance_reference = reference
        .irradiance()
        .unwrap_or_else(|| panic!("{name}: the reference has no irradiance columns"));
    let irradiance = irradiance_reference.compare(&irradiance);
    // The same irradiance gathered by sensors at the probes (`voxrad grid`'s way: rays from the
    // point, and the emitters one by one), a hair off the surface.
    let field = SensorField::new(
        &results,
        voxrad::output::sensor::directions_for(set.grid.dims),
    );
    let lift = 1e-3 * set.grid.voxel_size;
    let sensed: Vec<Option<f64>> = reference
        .points()
        .iter()
        .map(|&(p, n)| {
            let n = n.normalize();
            Some(field.irradiance(p + n * lift, n).iter().sum())
        })
        .collect();
    let sensed = irradiance_reference.compare(&sensed);
    let gathered = reference.compare(&gathered_radiosity(&field, &rows));
    println!(
        "    gathered radiosity: mean {:.2} %, max {:.1} % over {} probes",
        100.0 * gathered.mean,
        100.0 * gathered.max,
        gathered.compared
    );
    println!(
        "    sensors: mean {:.2} %, max {:.1} % over {} probes",
        100.0 * sensed.mean,
        100.0 * sensed.max,
        sensed.compared
    );
    for (surface, error, count) in &sensed.surfaces {
        println!("      sensors {surface}: {:+.2} % ({count})", 100.0 * error);
    }
    let (e, a) = (
        solution.stats.emitted_power.iter().sum::<f64>(),
        solution.stats.absorbed_power.iter().sum::<f64>(),
    );
    let balance = (e - a) / e;
    println!(
        "{name} at {resolution}, {directions} + {dense} directions: mean {:.2} %, max {:.1} % \
         over {} probes (reference noise {:.2} %); balance {:+.3} %",
        100.0 * comparison.mean,
        100.0 * comparison.max,
        comparison.compared,
        100.0 * comparison.reference_noise,
        100.0 * balance
    );
    println!(
        "    irradiance: mean {:.2} %, max {:.1} % over {} probes",
        100.0 * irradiance.mean,
        100.0 * irradiance.max,
        irradiance.compared
    );
    for (surface, error, count) in &comparison.surfaces {
        println!("    {surface}: {:+.2} % ({count} probes)", 100.0 * error);
    }
    assert!(
        comparison.compared * 10 >= reference.probes.len() * 8,
        "{name}: only {} of {} probes compared",
        comparison.compared,
        reference.probes.len()
    );
    (comparison, irradiance, sensed, gathered, balance)
}

#[test]
fn thin_slab_faces_match_the_path_traced_reference() {
    let all = std::env::var_os("VOXRAD_REFERENCE_ALL").is_some();
    let mut names = Vec::new();
    for light in ["side", "top"] {
        for t in ["0.3", "0.5", "1", "2"] {
            for tilt in ["", "-tilted"] {
                names.push(format!("thin-{light}-t{t}{tilt}"));
            }
        }
    }
    let quick = [
        "thin-side-t0.3",
        "thin-side-t1-tilted",
        "thin-top-t0.5",
        "thin-top-t2-tilted",
    ];
    let mut failures = Vec::new();
    for name in names.iter().filter(|n| all || quick.contains(&n.as_str())) {
        let (comparison, _, _, _, balance) = run(name, 128, 589, 20_000);
        // The goals: each face within 3 %, the box's power balance within 0.5 %. Measured on all
        // sixteen: faces at most 2.17 % off, balances within 0.2 % (`docs/accuracy.md`).
        for (surface, error, _) in &comparison.surfaces {
            if surface.starts_with("slab") && error.abs() > 0.03 {
                failures.push(format!("{name} {surface}: {:+.2} %", 100.0 * error));
            }
        }
        if balance.abs() > 0.005 {
            failures.push(format!("{name}: power balance {:+.2} %", 100.0 * balance));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn realistic_rooms_and_the_cornell_box_against_the_reference() {
    // (scene, resolution, largest mean error, largest |balance| where the scene is closed);
    // measured: window room 2.21 % and +0.17 %, corridor 4.73 % and +0.85 % (7.64 % and +2.18 %
    // while the floor and ceiling under its walls were not taken out, `voxelize::merge_voxel`),
    // Cornell box (open at the front) 2.34 % (2.81 % while its blocks' footprints were not taken
    // out of the floor, 4.90 % before the box rule of `propagate::side_of`), office 7.67 % and
    // -0.22 % (its 6 cm lamp housings are a sixth of a voxel tall here; 14.0 % and -10.5 %
    // before the senders' balance of the direct pass, 30.7 % and -25 % before the rim test of
    // `propagate::off_the_run`). The window room at 128: 0.99 % and +0.13 % since its window's
    // rim voxels take their material by area share (3.20 % before, the whole room 3 % dark:
    // the window came out with 3.1 % too little emitting area, `voxelize::drawn_material`).
    let cases: [(&str, u32, f64, Option<f64>); 5] = [
        ("window-room", 64, 0.03, Some(0.005)),
        ("window-room", 128, 0.015, Some(0.005)),
        ("corridor", 64, 0.06, Some(0.005)),
        ("cornell", 64, 0.03, None),
        ("office", 64, 0.09, Some(0.005)),
    ];
    let mut failures = Vec::new();
    for (name, resolution, mean, balance_bound) in cases {
        let (comparison, irradiance, sensed, gathered, balance) =
            run(name, resolution, 589, 20_000);
        if comparison.mean > mean {
            failures.push(format!(
                "{name}: mean error {:.2} %",
                100.0 * comparison.mean
            ));
        }
        // The irradiance is read from the same surfels, `(B - E) / rho`, and held to the same
        // bound against the reference's own irradiance (measured: window room 2.00 and 1.01 %,
        // corridor 4.76 %, Cornell box 2.36 %, office 7.65 %).
        if irradiance.mean > mean {
            failures.push(format!(
                "{name}: irradiance mean error {:.2} %",
                100.0 * irradiance.mean
            ));
        }
        // Sensors gather the solved radiosity at the probes again, with rays that stop on the
        // surfels' own pieces and the emitters summed one by one (`output::sensor`): measured
        // 1.10 and 0.42 % (window room at 64 and 128), 1.21 % (corridor), 0.86 % (Cornell box),
        // 1.20 % (office), largest 8.8 %.
        if sensed.mean > 0.02 || sensed.max > 0.15 {
            failures.push(format!(
                "{name}: sensors' irradiance mean error {:.2} %, max {:.1} %",
                100.0 * sensed.mean,
                100.0 * sensed.max
            ));
        }
        // `voxrad probe --gather`: `E + rho H` from those sensors; measured 1.08, 0.41, 1.21,
        // 0.86 and 1.20 %, largest 8.7 %.
        if gathered.mean > 0.02 || gathered.max > 0.15 {
            failures.push(format!(
                "{name}: gathered radiosity mean error {:.2} %, max {:.1} %",
                100.0 * gathered.mean,
                100.0 * gathered.max
            ));
        }
        if let Some(bound) = balance_bound {
            if balance.abs() > bound {
                failures.push(format!("{name}: power balance {:+.2} %", 100.0 * balance));
            }
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

/// `voxrad solve --quality high` read by gathering (`voxrad probe --gather` with its default
/// directions) meets the accuracy goal of that preset, at most 0.5 % mean and 3 % largest
/// error against the reference, on the corridor: the scene with the largest mean error of the
/// four at that preset (measured 2026-12-03: corridor 0.44 % and 1.6 %, office 0.35 % and
/// 2.3 %, Cornell box 0.21 % and 1.9 %, window room 0.15 % and 0.7 %; at resolution 128 the
/// corridor and the office were at 0.9 %).
#[test]
fn the_high_preset_meets_its_goal_when_read_by_gathering() {
    let preset = voxrad::quality::Quality::High;
    assert_preset_meets(preset, "corridor", 0.005, 0.03, preset.preset().chebyshev);
}

/// `voxrad solve` at the `default` preset, read by gathering, meets that preset's goal (at most
/// 1.5 % mean and 10 % largest error) on the office: a scene with one of the largest mean errors
/// of the four at that preset (measured 2026-12-04 with 301 bounce directions and the closed
/// scenes' scales: office 1.20 % and 8.3 %, corridor 1.13 % and 8.5 %, window room 1.20 % and
/// 5.1 %, Cornell box 0.92 % and 6.4 %; 1.28 % on the office before the scales, 1.57 % with 193
/// directions), and on the corridor (six rooms off a corridor: the Chebyshev semi-iteration of
/// the preset runs there, 12 iterations instead of 14).
#[test]
fn the_default_preset_meets_its_goal_when_read_by_gathering() {
    let preset = voxrad::quality::Quality::Default;
    assert!(preset.preset().chebyshev);
    assert_preset_meets(preset, "office", 0.015, 0.10, true);
    let ran = assert_preset_meets(preset, "corridor", 0.015, 0.10, true);
    assert!(ran, "the corridor: the semi-iteration ran");
}

/// The same with `--no-chebyshev` (the tail extrapolation alone), on the same two scenes.
#[test]
fn the_default_preset_without_chebyshev_meets_its_goal_when_read_by_gathering() {
    for name in ["office", "corridor"] {
        assert_preset_meets(voxrad::quality::Quality::Default, name, 0.015, 0.10, false);
    }
}

/// Solves reference scene `name` at preset `quality` as the command line does (with the
/// Chebyshev semi-iteration allowed if `chebyshev`), reads its probes by gathering, and checks
/// the mean and largest relative error against the reference. Returns whether the
/// semi-iteration ran.
fn assert_preset_meets(
    quality: voxrad::quality::Quality,
    name: &str,
    mean: f64,
    max: f64,
    chebyshev: bool,
) -> bool {
    let preset = quality.preset();
    let reference = Reference::load(&data(name)).unwrap_or_else(|e| panic!("{e}"));
    let set = voxelize(&scene_of(name), GridSpec::Resolution(preset.resolution)).unwrap();
    let options = SolveOptions {
        directions: preset.directions,
        tolerance: Some(preset.tolerance),
        accelerate: preset.accelerate,
        chebyshev,
        direct: DirectPass::Auto(preset.direct),
        threads: 2,
        ..Default::default()
    };
    let solution = solve(&set, &options).unwrap();
    let ran = solution.stats.chebyshev_updates.is_some();
    assert!(
        chebyshev || !ran,
        "{name}: Chebyshev ran though not allowed"
    );
    let results = Results::from_solution(&set, &solution).unwrap();
    let index = ProbeIndex::new(&results);
    let field = SensorField::new(
        &results,
        voxrad::output::sensor::directions_for(set.grid.dims),
    );
    let rows: Vec<_> = reference
        .points()
        .iter()
        .map(|&(p, n)| index.lookup(p, n))
        .collect();
    let gathered = reference.compare(&gathered_radiosity(&field, &rows));
    let label = quality.name();
    println!(
        "{name} at the {label} preset, gathered: mean {:.3} %, max {:.2} % over {} probes",
        100.0 * gathered.mean,
        100.0 * gathered.max,
        gathered.compared
    );
    assert!(gathered.compared * 10 >= reference.probes.len() * 8);
    assert!(
        gathered.mean <= mean && gathered.max <= max,
        "{name}: the {label} preset's gathered answer is {:.3} % off on average, {:.2} % at most",
        100.0 * gathered.mean,
        100.0 * gathered.max
    );
    ran
}

/// A closed room 12 x 3 x 8 (reflectance 0.65) lit by twelve one-sided lamps 0.6 wide floating
/// at height 2.5, facing down: the case where open rims used to create energy (8.3 % at
/// resolution 64).
fn floating_lamps() -> Scene {
    use glam::DVec3;
    use voxrad::scene::Material;
    let mut scene = Scene::default();
    let wall = scene.add_material(Material::new("wall", [0.65; 3], [0.0; 3]));
    let lamp = scene.add_material(Material::new("lamp", [0.65; 3], [100.0; 3]));
    scene.add_box(DVec3::ZERO, DVec3::new(12.0, 3.0, 8.0), wall, true);
    for i in 0..4 {
        for k in 0..3 {
            let (x, z, y, s) = (1.5 + 3.0 * i as f64, 1.5 + 2.5 * k as f64, 2.5, 0.3);
            // Facing down (-y): counter-clockwise seen from below.
            scene.add_polygon(
                &[
                    DVec3::new(x - s, y, z - s),
                    DVec3::new(x + s, y, z - s),
                    DVec3::new(x + s, y, z + s),
                    DVec3::new(x - s, y, z + s),
                ],
                lamp,
            );
        }
    }
    scene
}

/// The office's luminaires alone in its closed shell (reflectance 0.65): housings 1.2 x 0.06 x
/// 0.3 with a one-sided lamp of their underside's size 1 mm below, facing down. A housing is a
/// closed solid smaller than a voxel across at resolution 32 and 64, where the lamps' rims are
/// point samples of the rays that meet them.
fn luminaires() -> Scene {
    use glam::DVec3;
    use voxrad::scene::Material;
    let mut scene = Scene::default();
    let wall = scene.add_material(Material::new("wall", [0.65; 3], [0.0; 3]));
    let housing = scene.add_material(Material::new("housing", [0.7; 3], [0.0; 3]));
    let lamp = scene.add_material(Material::new("lamp", [0.7; 3], [3000.0; 3]));
    scene.add_box(DVec3::ZERO, DVec3::new(12.0, 3.0, 8.0), wall, true);
    for cx in [1.5, 4.5, 7.5, 10.5] {
        for cz in [1.5, 4.0, 6.5] {
            let (lo, hi) = (
                DVec3::new(cx - 0.6, 2.44, cz - 0.15),
                DVec3::new(cx + 0.6, 2.5, cz + 0.15),
            );
            scene.add_box(lo, hi, housing, false);
            let y = lo.y - 0.001;
            // Facing down (-y): counter-clockwise seen from below.
            scene.add_polygon(
                &[
                    DVec3::new(lo.x, y, lo.z),
                    DVec3::new(hi.x, y, lo.z),
                    DVec3::new(hi.x, y, hi.z),
                    DVec3::new(lo.x, y, hi.z),
                ],
                lamp,
            );
        }
    }
    scene
}

/// Solves closed `scene` (named `name` in the output) at each (resolution, dense directions,
/// bound) with 589 directions, and asserts its power balance within the bound.
fn assert_balance(name: &str, scene: &Scene, cases: &[(u32, usize, f64)]) {
    assert_balance_with(name, scene, cases, false);
}

/// [`assert_balance`], with the Chebyshev semi-iteration if `chebyshev` (which must then run).
fn assert_balance_with(name: &str, scene: &Scene, cases: &[(u32, usize, f64)], chebyshev: bool) {
    let mut failures = Vec::new();
    for &(resolution, dense, bound) in cases {
        let set = voxelize(scene, GridSpec::Resolution(resolution)).unwrap();
        let options = SolveOptions {
            chebyshev,
            ..options(589, dense)
        };
        let stats = solve(&set, &options).unwrap().stats;
        assert_eq!(stats.chebyshev_updates.is_some(), chebyshev, "{name}");
        let (e, a) = (
            stats.emitted_power.iter().sum::<f64>(),
            stats.absorbed_power.iter().sum::<f64>(),
        );
        let balance = (e - a) / e;
        println!(
            "{name} at {resolution}, {dense} dense: balance {:+.3} %",
            100.0 * balance
        );
        if balance.abs() > bound {
            failures.push(format!(
                "{resolution}, {dense} dense: {:+.3} %",
                100.0 * balance
            ));
        }
    }
    assert!(failures.is_empty(), "{name}: {failures:#?}");
}

#[test]
fn luminaires_in_a_closed_room_conserve_energy() {
    // (resolution, dense directions, bound): the 0.5 % since a closed scene's scales
    // (`solve::closed`); +1.1 % at 32 and +0.13 % at 64 before them (+2.2 % and +0.35 % with the
    // senders balanced in the direct pass, before `propagate::where_crossed`; -14 % and -8.6 %,
    // light created at the lamps' rims, before the balance).
    assert_balance(
        "luminaires",
        &luminaires(),
        &[(32, 20_000, 0.005), (64, 20_000, 0.005)],
    );
}

#[test]
fn floating_lamps_in_a_closed_room_conserve_energy() {
    // (resolution, dense directions, bound): the 0.5 % since a closed scene's scales
    // (`solve::closed`), with the direct pass and without; before them +1.7 % and +3.3 % at 32,
    // +0.46 % and +1.6 % at 64 (with the pass and without), -7.8 % and -12.2 % at 64 before the
    // open-edge rule.
    assert_balance(
        "floating lamps",
        &floating_lamps(),
        &[(32, 20_000, 0.005), (64, 20_000, 0.005), (64, 0, 0.005)],
    );
}

#[test]
fn a_closed_room_conserves_energy_under_the_chebyshev_semi_iteration() {
    // Its updates mix each new value with the one before last; the closed scene's scales are
    // taken from each plain gather as before, so the balance holds as without it.
    assert_balance_with(
        "floating lamps, Chebyshev",
        &floating_lamps(),
        &[(32, 20_000, 0.005), (64, 0, 0.005)],
        true,
    );
}

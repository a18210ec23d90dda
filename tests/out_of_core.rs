//! The out-of-core solver gives the in-memory answer: same scene, same directions, same fixed
//! number of iterations, for budgets from roomy to a few hundred KiB (many bands per direction,
//! many sort buckets and permutation chunks) and for 1 and 2 threads. The brief's bar is 1e-5
//! relative; the two engines sum the same terms in a different order, so they agree to f32
//! rounding.

mod common;

use voxrad::geometry::directions::DirectionSet;
use voxrad::outcore::{solve_out_of_core, InMemorySource};
use voxrad::scene::Scene;
use voxrad::solve::jacobi::solve_with;
use voxrad::solve::SolveOptions;
use voxrad::voxel::voxelize::{voxelize, GridSpec};

fn compare(name: &str, scene: &Scene, resolution: u32, budgets: &[u64], threads: &[usize]) {
    let set = voxelize(scene, GridSpec::Resolution(resolution)).expect("voxelize");
    let directions = DirectionSet::with_count(49);
    let options = SolveOptions {
        directions: 49,
        max_iterations: 4,
        tolerance: None,
        threads: 1,
        ..Default::default()
    };
    let reference = solve_with(&set, &directions, &options).expect("solve");
    let peak = reference
        .radiosity
        .iter()
        .flatten()
        .flatten()
        .fold(0f32, |a, &b| a.max(b));
    assert!(peak > 0.0, "{name}: nothing lit");
    let work = tempfile::tempdir().expect("tempdir");
    for &budget in budgets {
        for &t in threads {
            let options = SolveOptions {
                threads: t,
                ..options.clone()
            };
            let source = InMemorySource::new(&set);
            let solution = solve_out_of_core(&source, &directions, &options, budget, work.path())
                .unwrap_or_else(|e| panic!("{name}, budget {budget}: {e}"));
            let radiosity = solution.radiosity().expect("read radiosity");
            assert_eq!(radiosity.len(), set.surfels.len());
            let worst = common::worst_relative_difference(&radiosity, &reference.radiosity);
            println!(
                "{name}: budget {budget}, {t} threads: worst relative difference {worst:.2e}, \
                 {} bands ({} columns in blocks), {} bytes read, {} written",
                solution.stats.bands,
                solution.stats.tiled_columns,
                solution.stats.bytes_read,
                solution.stats.bytes_written
            );
            assert!(
                worst <= 1e-5,
                "{name}, budget {budget}, {t} threads: {worst:e}"
            );
            assert_eq!(solution.stats.solve.iterations, 4);
            if budget < 1 << 20 {
                // A small budget must really cut directions into several bands.
                assert!(
                    solution.stats.bands > 2 * 4 * 49,
                    "{name}: {} bands",
                    solution.stats.bands
                );
            }
            let e = solution.stats.solve.emitted_power;
            let r = reference.stats.emitted_power;
            assert!(
                (e[0] - r[0]).abs() <= 1e-9 * r[0].abs().max(1e-30),
                "{e:?} {r:?}"
            );
        }
    }
}

#[test]
fn cornell_box_matches_the_in_memory_solver() {
    compare(
        "cornell",
        &voxrad::gen::cornell_box(),
        32,
        &[64 << 20, 400 << 10, 160 << 10],
        &[1, 2],
    );
}

#[test]
fn furnished_room_matches_the_in_memory_solver() {
    compare(
        "room",
        &voxrad::gen::room(5.0, 11, 6),
        40,
        &[600 << 10],
        &[2],
    );
}

/// The Chebyshev semi-iteration out of core (the radiosity before last kept in a work file)
/// gives the in-memory solver's answer with as many iterations and updates, under a budget
/// that cuts every direction into bands.
#[test]
fn chebyshev_out_of_core_matches_the_in_memory_solver() {
    let set = voxelize(&voxrad::gen::room(5.0, 11, 6), GridSpec::Resolution(40)).unwrap();
    let directions = DirectionSet::with_count(49);
    let options = SolveOptions {
        directions: 49,
        tolerance: Some(1e-5),
        threads: 2,
        accelerate: true,
        chebyshev: true,
        ..Default::default()
    };
    let reference = solve_with(&set, &directions, &options).expect("solve");
    let updates = reference.stats.chebyshev_updates;
    assert!(updates.is_some_and(|u| u >= 3), "{updates:?}");
    let work = tempfile::tempdir().expect("tempdir");
    let source = InMemorySource::new(&set);
    let solution = solve_out_of_core(&source, &directions, &options, 600 << 10, work.path())
        .expect("out of core");
    let radiosity = solution.radiosity().expect("read radiosity");
    let worst = common::worst_relative_difference(&radiosity, &reference.radiosity);
    println!(
        "Chebyshev: {} iterations, {updates:?} updates; out of core worst relative difference \
         {worst:.2e}",
        reference.stats.iterations
    );
    assert!(worst <= 1e-5, "{worst:e}");
    assert_eq!(solution.stats.solve.iterations, reference.stats.iterations);
    assert_eq!(solution.stats.solve.chebyshev_updates, updates);
}

/// The out-of-core solver simulates what the in-memory one does: a grey scene is solved in one
/// channel and the geometric tail is extrapolated. A furnace with `rho = 0.99` (about 900 plain
/// iterations to 1e-4) must land on `E / (1 - rho)` within a few iterations, out of core under a
/// small budget exactly as in memory.
#[test]
fn grey_extrapolated_furnace_out_of_core() {
    let (e, rho) = (1.0, 0.99);
    let scene = common::furnace(e, rho);
    let set = voxelize(&scene, GridSpec::Resolution(12)).expect("voxelize");
    let directions = DirectionSet::with_count(49);
    let options = SolveOptions {
        directions: 49,
        tolerance: Some(1e-4),
        threads: 2,
        grey: true,
        accelerate: true,
        ..Default::default()
    };
    let reference = solve_with(&set, &directions, &options).expect("solve");
    let work = tempfile::tempdir().expect("tempdir");
    let source = InMemorySource::new(&set);
    let solution = solve_out_of_core(&source, &directions, &options, 200 << 10, work.path())
        .expect("out-of-core solve");
    let stats = &solution.stats.solve;
    let radiosity = solution.radiosity().expect("read radiosity");
    let expected = e / (1.0 - rho);
    let mut worst = 0.0f64;
    for (s, b) in set.surfels.iter().zip(&radiosity) {
        for &v in &b[common::inner_side(s, &set)] {
            worst = worst.max((v as f64 - expected).abs() / expected);
        }
    }
    println!(
        "furnace rho {rho} out of core: {} iterations, {} extrapolations, {} channel(s), worst \
         error {worst:.2e} (in memory: {} iterations)",
        stats.iterations, stats.extrapolations, stats.channels, reference.stats.iterations
    );
    assert_eq!(stats.channels, 1);
    assert!(stats.extrapolations >= 1);
    assert!(stats.iterations <= 10, "{} iterations", stats.iterations);
    assert!(worst < 1e-4, "worst error {worst}");
    assert_eq!(stats.iterations, reference.stats.iterations);
    let apart = common::worst_relative_difference(&radiosity, &reference.radiosity);
    assert!(
        apart <= 1e-5,
        "out of core and in memory differ by {apart:e}"
    );
    // Every channel carries the solved one.
    assert!(radiosity
        .iter()
        .all(|b| b.iter().all(|s| s[0] == s[1] && s[1] == s[2])));
}

/// The direct-light pass out of core (`outcore::direct`): the emitters' lines gathered in parts
/// of whole direction groups within the budget give the in-memory pass's light, so the answer
/// and the energy balance are those of the in-memory solve, whatever the number of parts. A
/// budget too small for one group's lines takes the group a few directions at a time and
/// settles its senders' balance once the group is complete: the same bits as whole groups.
#[test]
fn direct_light_pass_out_of_core_matches_the_in_memory_pass() {
    // The Cornell box's one lamp, and the office's twelve small luminaires.
    // The last budget of each is too small for one group's lines.
    for (name, scene, resolution, split) in [
        ("cornell", voxrad::gen::cornell_box(), 32, 256 << 10),
        ("office", voxrad::gen::office().scene, 24, 400 << 10),
    ] {
        direct_pass_out_of_core(name, &scene, resolution, split);
    }
}

fn direct_pass_out_of_core(name: &str, scene: &Scene, resolution: u32, split: u64) {
    let set = voxelize(scene, GridSpec::Resolution(resolution)).expect("voxelize");
    let directions = DirectionSet::with_count(49);
    let options = SolveOptions {
        directions: 49,
        max_iterations: 3,
        tolerance: None,
        threads: 2,
        direct: voxrad::solve::direct::DirectPass::On(2000),
        ..Default::default()
    };
    let reference = solve_with(&set, &directions, &options).expect("solve");
    let in_memory = reference
        .stats
        .direct
        .as_ref()
        .expect("the pass ran in memory");
    let work = tempfile::tempdir().expect("tempdir");
    let mut whole_groups: Option<Vec<[[f32; 3]; 2]>> = None;
    for budget in [64u64 << 20, 1 << 20, split] {
        let source = InMemorySource::new(&set);
        let solution = solve_out_of_core(&source, &directions, &options, budget, work.path())
            .unwrap_or_else(|e| panic!("{name}, budget {budget}: {e}"));
        let direct = solution.stats.solve.direct.as_ref().expect("the pass ran");
        let radiosity = solution.radiosity().expect("read radiosity");
        let worst = common::worst_relative_difference(&radiosity, &reference.radiosity);
        println!(
            "{name}, budget {budget}: the pass in {} part(s), {} group(s) split, worst relative \
             difference {worst:.2e}",
            direct.parts, direct.split_groups
        );
        assert!(worst <= 1e-5, "budget {budget}: {worst:e}");
        // The same lines, the same surfels on them.
        assert_eq!(direct.lines, in_memory.lines, "budget {budget}");
        assert_eq!(
            direct.line_surfels, in_memory.line_surfels,
            "budget {budget}"
        );
        if budget <= 1 << 20 {
            assert!(direct.parts > 1, "budget {budget}: {} part", direct.parts);
        }
        if budget == split {
            assert!(
                direct.split_groups > 0,
                "{name}, budget {budget}: no group split"
            );
            let whole = whole_groups
                .as_ref()
                .expect("a budget of whole groups ran first");
            let same = radiosity
                .iter()
                .flatten()
                .flatten()
                .zip(whole.iter().flatten().flatten())
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(
                same,
                "{name}: groups taken in parts must add what whole groups add, in their order"
            );
        } else {
            assert_eq!(direct.split_groups, 0, "budget {budget}");
            whole_groups.get_or_insert(radiosity);
        }
        // Out of core the direct light is kept in f32 (`outcore::direct`) and the light of an
        // axis summed in f32 (`outcore::files`): each value within 2^-24 of the in-memory one,
        // relatively, and the power they add up to within 1e-7 (1.1e-9 measured on the Cornell
        // box here).
        for ch in 0..3 {
            let (got, want) = (
                solution.stats.solve.absorbed_power[ch],
                reference.stats.absorbed_power[ch],
            );
            assert!(
                (got - want).abs() <= 1e-7 * want,
                "channel {ch}: absorbed {got} out of core, {want} in memory"
            );
        }
    }
}

/// The data mode out of core decides grey on the materials its surfels use, as the one-process
/// solvers do: a caller asking for one channel on a coloured scene (the Cornell box's red and
/// green walls) gets the three-channel answer, not the first channel copied.
#[test]
fn data_mode_out_of_core_solves_a_coloured_scene_in_three_channels() {
    let set = voxelize(&voxrad::gen::cornell_box(), GridSpec::Resolution(24)).expect("voxelize");
    let directions = DirectionSet::with_count(49);
    let options = SolveOptions {
        directions: 49,
        max_iterations: 2,
        tolerance: None,
        threads: 1,
        grey: true,
        ..Default::default()
    };
    let reference = solve_with(&set, &directions, &options).expect("solve");
    assert_eq!(reference.stats.channels, 3);
    let source = InMemorySource::new(&set);
    let work = tempfile::tempdir().expect("tempdir");
    let solution = voxrad::distribute::ooc::solve_data_out_of_core(
        &source,
        &directions,
        &options,
        &voxrad::distribute::SingleProcess,
        1,
        16 << 20,
        work.path(),
        None,
    )
    .expect("data mode out of core");
    assert_eq!(solution.stats.channels, 3);
    let mut radiosity = Vec::new();
    solution
        .for_each(&source, |_, b| {
            radiosity.push(*b);
            Ok(())
        })
        .expect("results");
    let worst = common::worst_relative_difference(&radiosity, &reference.radiosity);
    println!("worst relative difference {worst:.2e}");
    assert!(worst <= 1e-5, "{worst:e}");
}

//! Partner links kept between iterations (`solve::links`): iterations that replay a direction's
//! links instead of searching its lines again give the bits of a solve that searches in every
//! iteration, with every link kept, some, or none, at 1 and 2 threads, with the direct-light
//! pass and the tail extrapolation on, under the non-uniform light of the Cornell box (its lamp,
//! its coloured walls and blocks) and in a furnished room lit by many small lamps with open
//! edges (shares below 1 and extra links on the same line). Out of core (one process and the
//! data mode), links kept in work files, band by band, give the bits of searching again too, with
//! every direction's file kept, some, or none.

mod common;

use voxrad::scene::obj::load_obj;
use voxrad::scene::Scene;
use voxrad::solve::direct::DirectPass;
use voxrad::solve::{solve, Solution, SolveOptions};
use voxrad::voxel::voxelize::{voxelize, GridSpec};
use voxrad::voxel::SurfelSet;

fn options(threads: usize, links_memory: u64) -> SolveOptions {
    SolveOptions {
        directions: 120,
        max_iterations: 6,
        tolerance: None,
        threads,
        accelerate: true,
        direct: DirectPass::On(200),
        links_memory: Some(links_memory),
        ..Default::default()
    }
}

fn bits(solution: &Solution) -> Vec<u32> {
    common::radiosity_bits(solution)
}

fn assert_links_change_no_bit(name: &str, set: &SurfelSet) {
    let searched = solve(set, &options(1, 0)).expect("solve");
    let none = searched
        .stats
        .links
        .clone()
        .expect("in-memory link figures");
    assert_eq!(none.kept_directions, 0, "{name}");
    for threads in [1, 2] {
        let all = solve(set, &options(threads, u64::MAX)).expect("solve");
        let kept = all.stats.links.clone().expect("in-memory link figures");
        assert_eq!(kept.kept_directions, kept.directions, "{name}");
        assert!(
            kept.bytes > 0 && kept.bytes_per_surfel_direction > 0.0,
            "{name}"
        );
        assert!(bits(&all) == bits(&searched), "{name}: {threads} threads");
        assert_eq!(all.stats.iterations, searched.stats.iterations, "{name}");
        // A budget for about half of them: the others are searched again each iteration.
        let half = solve(set, &options(threads, kept.bytes / 2)).expect("solve");
        let some = half.stats.links.clone().expect("in-memory link figures");
        assert!(
            some.kept_directions > 0 && some.kept_directions < some.directions,
            "{name}: {some:?}"
        );
        assert!(some.bytes <= kept.bytes / 2, "{name}");
        assert!(
            bits(&half) == bits(&searched),
            "{name}: half, {threads} threads"
        );
    }
}

#[test]
fn kept_links_give_the_bits_of_searching_again_on_the_cornell_box() {
    let obj = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj");
    let scene: Scene = load_obj(&obj).expect("load");
    let set = voxelize(&scene, GridSpec::Resolution(40)).expect("voxelize");
    assert_links_change_no_bit("cornell box", &set);
}

#[test]
fn kept_links_give_the_bits_of_searching_again_in_a_room_of_small_lamps() {
    let scene = voxrad::gen::office().scene;
    let set = voxelize(&scene, GridSpec::Resolution(40)).expect("voxelize");
    assert_links_change_no_bit("office", &set);
}

/// The out-of-core radiosity (canonical order) and link figures of `set`, one process or the
/// data mode on one rank, with `links_disk` bytes of links files, at a budget of many bands.
fn out_of_core(
    set: &SurfelSet,
    data_mode: bool,
    links_disk: u64,
    threads: usize,
) -> (Vec<u32>, voxrad::solve::stats::LinkStats, u64, u64) {
    let options = SolveOptions {
        links_disk: Some(links_disk),
        ..options(threads, 0)
    };
    let directions = voxrad::geometry::directions::DirectionSet::with_count(options.directions);
    let source = voxrad::outcore::InMemorySource::new(set);
    let work = tempfile::tempdir().expect("tempdir");
    let budget = 6 << 20;
    let mut radiosity = Vec::new();
    let (stats, read) = if data_mode {
        let solution = voxrad::distribute::ooc::solve_data_out_of_core(
            &source,
            &directions,
            &options,
            &voxrad::distribute::SingleProcess,
            1,
            budget,
            work.path(),
            None,
        )
        .expect("data mode out of core");
        solution
            .for_each(&source, |_, b| {
                radiosity.push(*b);
                Ok(())
            })
            .expect("results");
        (solution.stats.clone(), solution.bytes_read)
    } else {
        let solution =
            voxrad::outcore::solve_out_of_core(&source, &directions, &options, budget, work.path())
                .expect("out of core");
        assert!(
            solution.stats.bands > 2 * 120,
            "{} bands",
            solution.stats.bands
        );
        radiosity = solution.radiosity().expect("radiosity");
        (solution.stats.solve.clone(), solution.stats.bytes_read)
    };
    assert_eq!(radiosity.len(), set.surfels.len());
    let bits = radiosity
        .iter()
        .flatten()
        .flatten()
        .map(|v| v.to_bits())
        .collect();
    let later = stats.iterations as u64 - 1;
    (
        bits,
        stats.links.expect("link figures out of core"),
        read,
        later,
    )
}

#[test]
fn links_kept_in_files_out_of_core_give_the_bits_of_searching_again() {
    let scene = voxrad::gen::office().scene;
    let set = voxelize(&scene, GridSpec::Resolution(40)).expect("voxelize");
    for data_mode in [false, true] {
        let name = if data_mode {
            "data mode"
        } else {
            "one process"
        };
        let (searched, none, read_searching, _) = out_of_core(&set, data_mode, 0, 1);
        assert_eq!((none.kept_directions, none.kept_in.as_str()), (0, "none"));
        for threads in [1, 2] {
            let (bits, all, read, later) = out_of_core(&set, data_mode, u64::MAX, threads);
            assert_eq!(
                (all.kept_directions, all.kept_in.as_str()),
                (all.directions, "files"),
                "{name}"
            );
            // Two sides of each surfel search along each direction, less the sides inside solids.
            assert!(all.bytes_per_surfel_direction > 4.0, "{name}: {all:?}");
            assert!(bits == searched, "{name}, {threads} threads");
            // Replaying reads the light and the links, not the surfels' static records: beyond
            // what searching in every iteration reads, at most the links once in each later
            // iteration, less the static records searching reads there. (The one process's
            // records are compressed and may take fewer bytes than the links.)
            let bound = read_searching + later * all.bytes;
            assert!(later > 0 && read < bound, "{name}: {read} >= {bound}");
            // An allowance for about half of them: the others are searched again.
            let (bits, some, _, _) = out_of_core(&set, data_mode, all.bytes / 2, threads);
            assert!(
                some.kept_directions > 0 && some.kept_directions < some.directions,
                "{name}: {some:?}"
            );
            assert!(bits == searched, "{name}, half kept, {threads} threads");
        }
    }
}

/// Out of core, a replay reads the light of several bands of a direction at once and replays
/// each band's links in place (`outcore::band`): at a budget of many bands a direction, the
/// groups must join bands, directions of one slope must be replayed together, and the answer
/// must keep the bits of searching again.
#[test]
fn replays_out_of_core_join_bands_and_keep_the_bits() {
    let scene = voxrad::gen::cornell_box();
    let set = voxelize(&scene, GridSpec::Resolution(48)).expect("voxelize");
    let source = voxrad::outcore::InMemorySource::new(&set);
    let solve = |links_disk: u64| {
        let options = SolveOptions {
            directions: 49,
            max_iterations: 4,
            tolerance: None,
            threads: 2,
            accelerate: true,
            direct: DirectPass::Off,
            links_disk: Some(links_disk),
            ..Default::default()
        };
        let directions = voxrad::geometry::directions::DirectionSet::with_count(49);
        let work = tempfile::tempdir().expect("tempdir");
        let solution = voxrad::outcore::solve_out_of_core(
            &source,
            &directions,
            &options,
            1 << 20,
            work.path(),
        )
        .expect("out of core");
        let bits: Vec<u32> = solution
            .radiosity()
            .expect("radiosity")
            .iter()
            .flatten()
            .flatten()
            .map(|v| v.to_bits())
            .collect();
        (bits, solution.stats)
    };
    let (searched, none) = solve(0);
    assert_eq!(none.replayed_bands, 0);
    let (replayed, kept) = solve(u64::MAX);
    let directions = kept.solve.directions as u64;
    assert!(
        kept.replayed_bands > 3 * 3 * directions,
        "several bands a direction: {} bands replayed over 3 iterations of {directions} directions",
        kept.replayed_bands
    );
    assert!(
        kept.replay_groups * 2 <= kept.replayed_bands,
        "the groups join bands: {} groups for {} bands",
        kept.replay_groups,
        kept.replayed_bands
    );
    // Directions of one slope along `v` share their bands (`outcore::solver`'s
    // `replayed_together`): of the 3 x 49 replayed, at least a third are replayed with an
    // earlier one.
    assert!(
        kept.joint_passes > 0 && kept.joint_directions >= directions,
        "directions replayed together: {} passes, {} directions beyond one each, over 3 \
         iterations of {directions} directions",
        kept.joint_passes,
        kept.joint_directions
    );
    assert!(
        replayed == searched,
        "replaying in groups changed the answer"
    );
}

//! A closed scene absorbs what it emits (`solve::closed`, `solve::enclosure`): the three
//! realistic reference rooms (their lamps small, floating, under ceilings, a window-sized panel)
//! within 0.5 % at every resolution from 32 to 128, and at 256 for the window room; the same
//! answer in every solve path (in memory, out of core from the shard set an OBJ is converted to,
//! the data mode in memory and out of core); an open scene (the Cornell box, open at the front)
//! keeps the light it loses. Across ranks under `mpirun`: `tests/mpi.rs`.
//!
//! Before the closed scenes' scales (2026-12-04), with 589 + 20,000 directions, the corridor's
//! balance was +1.83 % at 32 and +1.16 % at 64, the window room's +0.95 % at 32 (docs/accuracy.md,
//! "Closed scenes"); the bound here is the 0.5 %.

use std::path::{Path, PathBuf};
use voxrad::app::{run_solve_on, SolveCommand};
use voxrad::distribute::{Mode, SingleProcess};
use voxrad::output::Report;
use voxrad::solve::direct::DirectPass;
use voxrad::solve::SolveOptions;
use voxrad::voxel::voxelize::GridSpec;

fn reference_scene(name: &str) -> PathBuf {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/reference")
        .join(name)
        .join("scene.obj");
    assert!(path.is_file(), "missing {}", path.display());
    path
}

/// Solves `scene` at `resolution` with few directions (the balance does not need many) in
/// `mode`, in memory or under `memory` bytes, and returns its report.
fn solve(
    scene: &Path,
    out: &Path,
    resolution: u32,
    mode: Mode,
    memory: Option<u64>,
    directions: usize,
) -> Report {
    let cmd = SolveCommand {
        scene: scene.to_path_buf(),
        out: out.to_path_buf(),
        grid: GridSpec::Resolution(resolution),
        solve: SolveOptions {
            directions,
            threads: 2,
            tolerance: Some(1e-3),
            direct: DirectPass::Auto(2000),
            ..Default::default()
        },
        image_size: (32, 24),
        memory,
        checkpoint: Default::default(),
        work_dir: None,
    };
    run_solve_on(&cmd, &SingleProcess, mode).unwrap_or_else(|e| panic!("{}: {e}", out.display()))
}

/// The report's word on the closed scene: whether it was found closed.
fn found_closed(report: &Report) -> bool {
    report
        .effects
        .iter()
        .find(|e| e.name == "energy conservation of a closed scene")
        .unwrap_or_else(|| panic!("no closure effect in {:?}", report.effects))
        .simulated
}

#[test]
fn closed_rooms_absorb_what_they_emit_at_every_resolution() {
    let dir = tempfile::tempdir().unwrap();
    let mut failures = Vec::new();
    let mut cases: Vec<(&str, u32)> = Vec::new();
    for name in ["corridor", "window-room", "office"] {
        for resolution in [32, 48, 64, 128] {
            cases.push((name, resolution));
        }
    }
    cases.push(("window-room", 256));
    for (name, resolution) in cases {
        let out = dir.path().join(format!("{name}-{resolution}"));
        let directions = if resolution > 128 { 25 } else { 49 };
        let report = solve(
            &reference_scene(name),
            &out,
            resolution,
            Mode::Single,
            None,
            directions,
        );
        let balance = report.energy.balance;
        println!("{name} at {resolution}: balance {:+.4} %", 100.0 * balance);
        if !found_closed(&report) {
            failures.push(format!("{name} at {resolution}: not found closed"));
        }
        if balance.abs() > 0.005 {
            failures.push(format!(
                "{name} at {resolution}: balance {:+.3} %",
                100.0 * balance
            ));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn every_solve_path_conserves_a_closed_rooms_energy_alike() {
    let dir = tempfile::tempdir().unwrap();
    let scene = reference_scene("corridor");
    let paths: [(&str, Mode, Option<u64>); 4] = [
        ("in memory", Mode::Single, None),
        ("out of core", Mode::Single, Some(24 << 20)),
        ("data mode", Mode::Data { compress: false }, None),
        (
            "data mode out of core",
            Mode::Data { compress: false },
            Some(24 << 20),
        ),
    ];
    let mut balances = Vec::new();
    for (name, mode, memory) in paths {
        let out = dir.path().join(name.replace(' ', "-"));
        let report = solve(&scene, &out, 32, mode, memory, 49);
        println!(
            "{name}: balance {:+.5} %, closed {}",
            100.0 * report.energy.balance,
            found_closed(&report)
        );
        assert!(found_closed(&report), "{name}: not found closed");
        assert!(
            report.energy.balance.abs() < 0.005,
            "{name}: balance {}",
            report.energy.balance
        );
        balances.push((name, report.energy.balance));
    }
    // The scales are exact sums, the same in every path: so is the balance, to rounding.
    for (name, balance) in &balances[1..] {
        assert!(
            (balance - balances[0].1).abs() < 1e-6,
            "{name}: {balance} against {} in memory",
            balances[0].1
        );
    }
}

#[test]
fn an_open_scene_keeps_the_light_it_loses() {
    // The Cornell box is open at the front: a third of its light leaves it.
    let dir = tempfile::tempdir().unwrap();
    let report = solve(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj"),
        &dir.path().join("cornell"),
        32,
        Mode::Single,
        None,
        49,
    );
    println!(
        "Cornell box: balance {:+.2} %",
        100.0 * report.energy.balance
    );
    assert!(!found_closed(&report));
    assert!(report.energy.balance > 0.2, "{:?}", report.energy);
}

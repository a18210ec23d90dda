//! `voxrad grid`, the real binary: irradiance sensors on a workplane.
//!
//! In a closed furnace (every wall emits `E` and reflects `rho`) the light arriving anywhere
//! inside, from any side, is `B = E / (1 - rho)`: every sensor of a grid across the box must read
//! it, whichever way the rays and the emitter sum share it. The CSV has its header and one row a
//! sensor; the picture is a PNG; bad options exit with status 2 and say why.

use tempfile::TempDir;

mod common;
use common::cli::*;

#[test]
fn a_grid_in_a_furnace_reads_its_radiosity_everywhere() {
    let tmp = TempDir::new().unwrap();
    let obj = tmp.path().join("furnace.obj");
    assert_ok(
        &voxrad(&["generate", "furnace", "--out", &s(&obj)]),
        "generate",
    );
    let out = tmp.path().join("solved");
    assert_ok(
        &voxrad(&[
            "solve",
            &s(&obj),
            "--out",
            &s(&out),
            "--resolution",
            "24",
            "--directions",
            "200",
        ]),
        "solve",
    );
    let prefix = tmp.path().join("plane");
    let o = voxrad(&[
        "grid",
        &s(&out),
        "--height",
        "0.4",
        "--spacing",
        "0.1",
        "--out",
        &s(&prefix),
        "--directions",
        "800",
    ]);
    assert_ok(&o, "grid");
    let summary = String::from_utf8_lossy(&o.stdout);
    assert!(summary.contains("10 x 10 sensors"), "{summary}");
    assert!(summary.contains("uniformity"), "{summary}");
    let csv = std::fs::read_to_string(tmp.path().join("plane.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("x,y,z,nx,ny,nz,H_r,H_g,H_b,H"));
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|x| x.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 100);
    // E = 1, rho = 0.5 (`voxrad generate furnace`): B = 2.
    let mut worst: f64 = 0.0;
    for r in &rows {
        assert_eq!(r[1], 0.4);
        assert_eq!(&r[3..6], &[0.0, 1.0, 0.0]);
        for h in &r[6..10] {
            worst = worst.max((h - 2.0).abs() / 2.0);
        }
    }
    println!(
        "worst relative departure from B = 2: {:.3} %",
        100.0 * worst
    );
    assert!(worst < 0.02, "a sensor reads {:.2} % off", 100.0 * worst);
    let png = std::fs::read(tmp.path().join("plane.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");

    // Bad options: exit 2, saying what is wrong.
    let (dir, prefix) = (s(&out), s(&prefix));
    for (args, needle) in [
        (["--spacing", "0"].as_slice(), "spacing"),
        (&["--spacing", "0.1", "--first", "1,0"], "LOW,HIGH"),
    ] {
        let mut all = vec!["grid", &dir, "--height", "0.4", "--out", &prefix];
        all.extend(args);
        let o = voxrad(&all);
        assert_eq!(o.status.code(), Some(2), "{all:?}");
        assert!(
            String::from_utf8_lossy(&o.stderr).contains(needle),
            "{all:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
}

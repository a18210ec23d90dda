//! Damaged data: every way a shard set or a results file can be damaged on disk, fed to the real
//! binaries.
//!
//! A tiny shard set (the Cornell box at resolution 10, two shards) is made with
//! `voxrad-shard convert`; each case damages a copy of it (a flipped byte at every header and
//! footer field and at seeded random places, truncations at several lengths, an extra byte, two
//! shards swapped, a shard deleted, manifest edits) and runs `voxrad solve SET --memory ...`,
//! `voxrad-shard verify SET` and `voxrad-shard pack SET` on it. Then the same for a solve's results file under
//! `voxrad render` and `voxrad probe`.
//!
//! What must hold, every time:
//! - exit status 2: a damaged input is the user's input, including a shard that is missing
//!   (the manifest lists it) or cut to nothing. Status 1 is kept for I/O failures of the machine
//!   (a device error, a full disk), which no case here produces;
//! - the message names the damaged file;
//! - never a panic (no "panicked at");
//! - never status 0 with a wrong answer: a run that succeeds must give the clean run's results
//!   bit for bit (possible only where a flip lands in bytes no reader depends on, such as the
//!   white space after a manifest's checksum);
//! - the earlier results in the output directory are left as they were.
//!
//! About 380 runs of binaries taking 2 to 200 ms each, 3 s in all.

mod common;

use common::files::{copy_dir, edit};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use tempfile::TempDir;

const SHARD_0: &str = "shard-00000.vxs";
const SHARD_1: &str = "shard-00001.vxs";
const MANIFEST: &str = "manifest.json";
/// Shard header and footer sizes (`storage::shard`).
const SHARD_HEADER: usize = 32;
const SHARD_FOOTER: usize = 20;
/// Results file header and footer sizes (`output::results`).
const RESULTS_HEADER: usize = 72;
const RESULTS_FOOTER: usize = 20;

fn run(program: &str, args: &[&str]) -> Output {
    Command::new(program)
        .args(args)
        .env("RUST_LOG", "error")
        .output()
        .unwrap_or_else(|e| panic!("cannot run {program}: {e}"))
}

fn voxrad(args: &[&str]) -> Output {
    run(env!("CARGO_BIN_EXE_voxrad"), args)
}

fn shard_tool(args: &[&str]) -> Output {
    run(env!("CARGO_BIN_EXE_voxrad-shard"), args)
}

fn s(p: &Path) -> String {
    p.to_str().expect("UTF-8 path").to_string()
}

/// A deterministic generator (SplitMix64) so every run damages the same bytes.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }

    /// A non-zero byte to XOR with, so a flip always changes the byte.
    fn flip(&mut self) -> u8 {
        (self.next() % 255) as u8 + 1
    }
}

/// The clean shard set and the clean solve's results, made once per test.
struct Clean {
    tmp: TempDir,
    set: PathBuf,
    results: Vec<u8>,
}

/// The options of every solve here: out of core (`--memory`), one thread so that the answer is
/// the same bit for bit on every run.
const SOLVE: [&str; 8] = [
    "--memory",
    "4MiB",
    "--directions",
    "13",
    "--iterations",
    "2",
    "--threads",
    "1",
];

fn solve(set: &Path, out: &Path) -> Output {
    let (set, out) = (s(set), s(out));
    let mut args = vec!["solve", set.as_str(), "--out", out.as_str()];
    args.extend_from_slice(&SOLVE);
    voxrad(&args)
}

fn clean() -> Clean {
    let tmp = TempDir::new().unwrap();
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/cornell_box.obj");
    let set = tmp.path().join("clean.shards");
    let o = shard_tool(&[
        "convert",
        &s(&scene),
        "--resolution",
        "10",
        "--ranks",
        "2",
        "--out",
        &s(&set),
        "--threads",
        "1",
    ]);
    assert!(o.status.success(), "convert: {o:?}");
    let out = tmp.path().join("clean.out");
    let o = solve(&set, &out);
    assert!(o.status.success(), "clean solve: {o:?}");
    let results = std::fs::read(out.join("surfels.bin")).unwrap();
    Clean { tmp, set, results }
}

fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// One kind of damage to a shard set.
struct Case {
    what: String,
    /// File names any of which the messages may name (the damaged file; for a swap, either).
    files: Vec<&'static str>,
    damage: Box<dyn Fn(&Path)>,
}

fn case(what: String, files: &[&'static str], damage: impl Fn(&Path) + 'static) -> Case {
    Case {
        what,
        files: files.to_vec(),
        damage: Box::new(damage),
    }
}

/// Checks one binary's run on damaged input; returns whether it succeeded.
fn check_run(o: &Output, what: &str, files: &[&str]) -> bool {
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!err.contains("panicked at"), "{what}: a panic: {err}");
    match o.status.code() {
        Some(0) => true,
        Some(2) => {
            assert!(
                files.iter().any(|f| err.contains(f)),
                "{what}: the message names none of {files:?}: {err}"
            );
            assert!(err.contains("error"), "{what}: {err}");
            false
        }
        other => panic!("{what}: exit status {other:?}, expected 2 (or 0): {err}"),
    }
}

/// Runs every case on a fresh copy of the clean set: solve and verify. Returns the number of
/// cases that succeeded (with the clean answer).
fn run_cases(clean: &Clean, cases: &[Case], tag: &str) -> usize {
    let set = clean.tmp.path().join(format!("{tag}.shards"));
    let out = clean.tmp.path().join(format!("{tag}.out"));
    // The output directory holds a finished earlier result, which a failed run must not touch.
    let o = solve(&clean.set, &out);
    assert!(o.status.success(), "{o:?}");
    let before = names(&out);
    let mut succeeded = 0;
    for c in cases {
        copy_dir(&clean.set, &set);
        (c.damage)(&set);
        let o = solve(&set, &out);
        let solved = check_run(&o, &format!("solve, {}", c.what), &c.files);
        let results = std::fs::read(out.join("surfels.bin")).unwrap();
        assert!(
            results == clean.results,
            "{}: the results file differs from the clean run's (exit {:?})",
            c.what,
            o.status.code()
        );
        assert_eq!(names(&out), before, "{}: files left in --out", c.what);
        let o = shard_tool(&["verify", &s(&set)]);
        let verified = check_run(&o, &format!("verify, {}", c.what), &c.files);
        let pack = clean.tmp.path().join(format!("{tag}.vxpack"));
        let o = shard_tool(&["pack", &s(&set), "--out", &s(&pack)]);
        let packed = check_run(&o, &format!("pack, {}", c.what), &c.files);
        assert_eq!(pack.exists(), packed, "{}: a pack of a damaged set", c.what);
        let _ = std::fs::remove_file(&pack);
        // Both readers see the same damage: if either accepts the set, it is unchanged in what
        // they read (the solve's answer was checked above).
        if solved || verified {
            succeeded += 1;
            eprintln!(
                "accepted (damage in bytes no reader depends on): {}",
                c.what
            );
        }
    }
    succeeded
}

#[test]
fn damaged_shards_are_refused_naming_the_file() {
    let clean = clean();
    let len = std::fs::metadata(clean.set.join(SHARD_0)).unwrap().len() as usize;
    let mut cases = Vec::new();
    // Every header field's first and last byte, the reserved word, every footer field.
    let header = [0, 3, 7, 8, 11, 12, 15, 16, 19, 20, 23, 24, 27, 31];
    let footer = [0, 7, 8, 11, 12, 19].map(|k| len - SHARD_FOOTER + k);
    for at in header.into_iter().chain(footer) {
        for (file, bit) in [(SHARD_0, 0x01u8), (SHARD_1, 0x80)] {
            cases.push(case(
                format!("{file}: byte {at} ^ {bit:#04x}"),
                &[file],
                move |d| edit(&d.join(file), |b| b[at] ^= bit),
            ));
        }
    }
    // Seeded random places in the records, with random flips.
    let mut rng = Rng(0x5eed);
    for k in 0..16 {
        let at = SHARD_HEADER + rng.below(len - SHARD_HEADER - SHARD_FOOTER);
        let x = rng.flip();
        let file = if k % 2 == 0 { SHARD_0 } else { SHARD_1 };
        cases.push(case(
            format!("{file}: record byte {at} ^ {x:#04x}"),
            &[file],
            move |d| edit(&d.join(file), |b| b[at] ^= x),
        ));
    }
    for cut in [
        0,
        5,
        20,
        SHARD_HEADER,
        SHARD_HEADER + 80,
        len - SHARD_FOOTER,
        len - 1,
    ] {
        cases.push(case(
            format!("{SHARD_1} cut to {cut} bytes"),
            &[SHARD_1],
            move |d| edit(&d.join(SHARD_1), |b| b.truncate(cut)),
        ));
    }
    cases.push(case(
        format!("{SHARD_0} with a byte appended"),
        &[SHARD_0],
        |d| edit(&d.join(SHARD_0), |b| b.push(0)),
    ));
    cases.push(case(
        "the two shards swapped".into(),
        &[SHARD_0, SHARD_1],
        |d| {
            let (a, b) = (d.join(SHARD_0), d.join(SHARD_1));
            let tmp = d.join("swap.tmp");
            std::fs::rename(&a, &tmp).unwrap();
            std::fs::rename(&b, &a).unwrap();
            std::fs::rename(&tmp, &b).unwrap();
        },
    ));
    cases.push(case(format!("{SHARD_1} deleted"), &[SHARD_1], |d| {
        std::fs::remove_file(d.join(SHARD_1)).unwrap()
    }));
    cases.push(case(
        format!("{SHARD_0} replaced by {SHARD_1}"),
        &[SHARD_0],
        |d| {
            std::fs::copy(d.join(SHARD_1), d.join(SHARD_0)).unwrap();
        },
    ));
    let n = cases.len();
    let accepted = run_cases(&clean, &cases, "shards");
    // Every byte of a shard is under its checksum: nothing may be accepted.
    assert_eq!(accepted, 0, "of {n} damaged shard sets");
    eprintln!("{n} damaged shard sets refused by solve, verify and pack");
}

#[test]
fn damaged_manifests_are_refused_naming_the_file() {
    let clean = clean();
    let text = std::fs::read_to_string(clean.set.join(MANIFEST)).unwrap();
    let len = text.len();
    let mut cases = Vec::new();
    let mut rng = Rng(0xfeed);
    for _ in 0..20 {
        let at = rng.below(len);
        let x = rng.flip();
        cases.push(case(
            format!("{MANIFEST}: byte {at} ^ {x:#04x}"),
            &[MANIFEST],
            move |d| edit(&d.join(MANIFEST), |b| b[at] ^= x),
        ));
    }
    // The last bytes: the checksum's digits, the closing brace, the final newline.
    for back in 1..=4 {
        let at = len - back;
        cases.push(case(
            format!("{MANIFEST}: byte {at} ^ 0x01"),
            &[MANIFEST],
            move |d| edit(&d.join(MANIFEST), |b| b[at] ^= 0x01),
        ));
    }
    for cut in [0, 1, len / 2, len - 3] {
        cases.push(case(
            format!("{MANIFEST} cut to {cut} bytes"),
            &[MANIFEST],
            move |d| edit(&d.join(MANIFEST), |b| b.truncate(cut)),
        ));
    }
    // Edits that keep the JSON valid and every value plausible: only the checksum can tell.
    let edits: [(&str, &str); 4] = [
        ("0.725", "0.625"),                                 // a reflectance
        ("\"dims\": [\n      10", "\"dims\": [\n      11"), // the grid
        ("\"order\": 0", "\"order\": 1"),
        ("\"records\": 369", "\"records\": 368"),
    ];
    for (from, to) in edits {
        assert!(text.contains(from), "the manifest has no {from:?}: {text}");
        cases.push(case(
            format!("{MANIFEST}: {from:?} -> {to:?}"),
            &[MANIFEST],
            move |d| {
                let t = std::fs::read_to_string(d.join(MANIFEST)).unwrap();
                std::fs::write(d.join(MANIFEST), t.replacen(from, to, 1)).unwrap();
            },
        ));
    }
    cases.push(case(format!("{MANIFEST} deleted"), &[MANIFEST], |d| {
        std::fs::remove_file(d.join(MANIFEST)).unwrap()
    }));
    let n = cases.len();
    let accepted = run_cases(&clean, &cases, "manifest");
    eprintln!(
        "{n} damaged manifests: {} refused, {accepted} accepted with the clean answer",
        n - accepted
    );
}

/// A change made to the bytes of a results file.
type Damage = dyn Fn(&mut Vec<u8>);

#[test]
fn damaged_results_are_refused_by_render_and_probe() {
    let clean = clean();
    let dir = clean.tmp.path().join("results");
    let png = clean.tmp.path().join("view.png");
    let points = clean.tmp.path().join("points.csv");
    std::fs::write(&points, "0,-270,0,0,1,0\n0,0,0,0,0,1\n").unwrap();
    let len = clean.results.len();
    let mut damages: Vec<(String, Box<Damage>)> = Vec::new();
    // Every header field (magic, version, record length, count, grid, reserved) and footer field.
    let header = [0, 7, 8, 12, 16, 23, 24, 47, 48, 56, 67, 68, 71];
    let footer = [0, 8, 12, 19].map(|k| len - RESULTS_FOOTER + k);
    for at in header.into_iter().chain(footer) {
        damages.push((
            format!("byte {at} ^ 0x04"),
            Box::new(move |b| b[at] ^= 0x04),
        ));
    }
    let mut rng = Rng(0xbeef);
    for _ in 0..8 {
        let at = RESULTS_HEADER + rng.below(len - RESULTS_HEADER - RESULTS_FOOTER);
        let x = rng.flip();
        damages.push((
            format!("byte {at} ^ {x:#04x}"),
            Box::new(move |b| b[at] ^= x),
        ));
    }
    for cut in [0, 4, 40, RESULTS_HEADER, len - RESULTS_FOOTER, len - 1] {
        damages.push((
            format!("cut to {cut} bytes"),
            Box::new(move |b| b.truncate(cut)),
        ));
    }
    damages.push(("a byte appended".into(), Box::new(|b| b.push(7))));
    std::fs::create_dir_all(&dir).unwrap();
    let bin = dir.join("surfels.bin");
    for (what, damage) in &damages {
        let mut bytes = clean.results.clone();
        damage(&mut bytes);
        std::fs::write(&bin, &bytes).unwrap();
        for (command, o) in [
            (
                "render",
                voxrad(&["render", &s(&dir), "--out", &s(&png), "--size", "40x30"]),
            ),
            (
                "probe",
                voxrad(&["probe", &s(&dir), "--points", &s(&points)]),
            ),
        ] {
            let what = format!("{command}, surfels.bin {what}");
            // Every byte of a results file is under its checksum or its length checks.
            assert!(!check_run(&o, &what, &["surfels.bin"]), "{what}: accepted");
            assert!(o.stdout.is_empty(), "{what}: printed rows");
        }
        assert!(!png.exists(), "{what}: a picture was written");
    }
    eprintln!(
        "{} damaged results files refused by render and probe",
        damages.len()
    );
}

/// Re-checksums shard `file` of the set `dir` after an edit and lists the new checksum in the
/// manifest (which gets its own checksum again): what a buggy or hostile writer could produce.
fn rechecksum(dir: &Path, file: &str) {
    let path = dir.join(file);
    edit(&path, |b| {
        let body = b.len() - SHARD_FOOTER;
        let crc = crc32fast::hash(&b[..body]);
        b[body + 8..body + 12].copy_from_slice(&crc.to_le_bytes());
    });
    let info = voxrad::storage::ShardReader::open(&path)
        .unwrap()
        .info()
        .clone();
    let mut m = voxrad::storage::Manifest::read_dir(dir).unwrap();
    for e in m.shards.iter_mut().filter(|e| e.file == file) {
        e.crc32 = info.crc32;
    }
    m.write(dir).unwrap();
}

/// Records whose checksums are right but whose values cannot belong to the set (an index past
/// the manifest's tables, a voxel outside the grid, a NaN): refused with the shard's name, never
/// an index out of bounds in the solver.
#[test]
fn impossible_records_with_good_checksums_are_refused() {
    let clean = clean();
    // Offsets inside record 5 of shard 1 (layout in `storage::record`).
    let record = SHARD_HEADER + 5 * 80;
    let edits: [(&str, usize, [u8; 4]); 5] = [
        ("normal index 9999", 36, 9999u32.to_le_bytes()),
        ("front material 77", 48, 77u32.to_le_bytes()),
        (
            "back material 4000000000",
            52,
            4_000_000_000u32.to_le_bytes(),
        ),
        ("voxel x = 10 (the grid is 10 wide)", 0, 10i32.to_le_bytes()),
        ("area NaN", 44, f32::NAN.to_le_bytes()),
    ];
    let mut cases = Vec::new();
    for (what, offset, value) in edits {
        cases.push(case(
            format!("{SHARD_1}: record 5 with {what}, checksums repaired"),
            &[SHARD_1],
            move |d| {
                edit(&d.join(SHARD_1), |b| {
                    b[record + offset..record + offset + 4].copy_from_slice(&value)
                });
                rechecksum(d, SHARD_1);
            },
        ));
    }
    // Solve only: `verify` checks structure, checksums and order, not values against the
    // manifest's tables.
    let set = clean.tmp.path().join("impossible.shards");
    let out = clean.tmp.path().join("impossible.out");
    for c in &cases {
        copy_dir(&clean.set, &set);
        (c.damage)(&set);
        let o = solve(&set, &out);
        assert!(!check_run(&o, &c.what, &c.files), "{}: accepted", c.what);
        assert!(
            !out.join("surfels.bin").exists(),
            "{}: wrote results",
            c.what
        );
    }
}

//! Full disks and read-only places, made real: a run that cannot write stops with exit status 1
//! and a message naming the path and the cause, leaves what was written before intact, and works
//! again once space is back.
//!
//! How a disk is made full, best first (each test prints which it used):
//! - **tmpfs**: a small tmpfs mounted for the test (needs root and a kernel that lets this
//!   process mount, which CI machines and most containers running as root allow), then filled
//!   with a filler file up to `ENOSPC`; "space back" deletes the filler.
//! - **RLIMIT_FSIZE**: the child runs with a file-size limit (`setrlimit` in `pre_exec`, `SIGXFSZ`
//!   ignored so that a write past it fails with `EFBIG`, "File too large"). Works for anyone
//!   anywhere, so it always runs, as well as tmpfs where that works: it is the one mechanism
//!   whose free space `statvfs` does not see, so it also reaches the out-of-core solver's work
//!   files in the middle of a run (on a full tmpfs the solver refuses up front).
//!
//! A read-only place: the tmpfs remounted read-only, else a read-only bind mount, else
//! `chattr +i` on the directory; if none works (an unprivileged container), the read-only test
//! says so loudly and checks nothing.

use std::io::Write;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use tempfile::TempDir;

fn s(p: &Path) -> String {
    p.to_str().expect("UTF-8 path").to_string()
}

fn example(name: &str) -> String {
    s(&Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("examples")
        .join(name))
}

/// How a write is made to fail.
#[derive(Clone, Copy, Debug)]
enum Full<'a> {
    /// The tmpfs is filled before the run, leaving this many bytes free.
    Tmpfs(&'a SmallDisk, u64),
    /// The child may not write any file larger than this many bytes.
    FileSizeLimit(u64),
}

impl std::fmt::Display for Full<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        match self {
            Full::Tmpfs(_, 0) => write!(f, "tmpfs filled"),
            Full::Tmpfs(_, leave) => write!(f, "tmpfs filled but for {leave} bytes"),
            Full::FileSizeLimit(bytes) => write!(f, "RLIMIT_FSIZE {bytes} bytes"),
        }
    }
}

impl Full<'_> {
    /// What the message must say, lower case.
    fn cause(&self) -> &'static str {
        match self {
            Full::Tmpfs(..) => "no space left",
            Full::FileSizeLimit(_) => "file too large",
        }
    }
}

/// A small tmpfs mounted on a temporary directory, unmounted when dropped.
#[derive(Debug)]
struct SmallDisk {
    dir: TempDir,
}

impl SmallDisk {
    /// Mounts a tmpfs of `bytes`, or says why it cannot.
    fn mount(bytes: u64) -> Result<SmallDisk, String> {
        // SAFETY: `geteuid` has no preconditions.
        if unsafe { libc::geteuid() } != 0 {
            return Err("not running as root".to_string());
        }
        let dir = TempDir::new().map_err(|e| e.to_string())?;
        let o = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={bytes}"), "tmpfs"])
            .arg(dir.path())
            .output()
            .map_err(|e| format!("cannot run mount: {e}"))?;
        if !o.status.success() {
            return Err(format!(
                "mount -t tmpfs refused: {}",
                String::from_utf8_lossy(&o.stderr).trim()
            ));
        }
        Ok(SmallDisk { dir })
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }

    fn filler(&self) -> PathBuf {
        self.path().join("filler")
    }

    /// Fills the disk, leaving `leave` bytes: a file grown until the file system refuses, then
    /// cut back.
    fn fill(&self, leave: u64) {
        let mut f = std::fs::File::create(self.filler()).expect("create the filler");
        let chunk = vec![0xa5u8; 64 << 10];
        for size in [chunk.len(), 4096, 1] {
            while f.write_all(&chunk[..size]).is_ok() {}
        }
        let len = f.metadata().unwrap().len();
        f.set_len(len.saturating_sub(leave)).unwrap();
        let _ = f.sync_all();
    }

    fn unfill(&self) {
        std::fs::remove_file(self.filler()).expect("remove the filler");
    }
}

/// Remounts the file system mounted at `path` with option `how` (`ro`, `rw`).
fn remount(path: &Path, how: &str) -> bool {
    Command::new("mount")
        .args(["-o", &format!("remount,{how}")])
        .arg(path)
        .status()
        .is_ok_and(|st| st.success())
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(self.path()).status();
    }
}

/// The disks to test on: a mounted tmpfs where this process may mount one, and always a file-size
/// limit (in a directory of the ordinary temporary file system).
fn mechanisms(test: &str) -> (Option<SmallDisk>, TempDir) {
    let disk = match SmallDisk::mount(8 << 20) {
        Ok(d) => {
            eprintln!("{test}: mechanisms: a tmpfs of 8 MiB mounted, and RLIMIT_FSIZE");
            Some(d)
        }
        Err(why) => {
            eprintln!(
                "\n*** {test}: NO TMPFS ({why}); a full disk is simulated with RLIMIT_FSIZE only \
                 ***\n"
            );
            None
        }
    };
    (disk, TempDir::new().unwrap())
}

/// Runs a binary, under `full` if given (filling the tmpfs first and emptying it after).
fn run(program: &str, args: &[&str], full: Option<Full>) -> Output {
    let mut cmd = Command::new(program);
    cmd.args(args).env("RUST_LOG", "error");
    match full {
        Some(Full::Tmpfs(disk, leave)) => disk.fill(leave),
        Some(Full::FileSizeLimit(bytes)) => {
            // SAFETY: between fork and exec only async-signal-safe calls: `setrlimit` and
            // `signal` touch no locks or allocations.
            unsafe {
                cmd.pre_exec(move || {
                    libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
                    let limit = libc::rlimit {
                        rlim_cur: bytes,
                        rlim_max: bytes,
                    };
                    if libc::setrlimit(libc::RLIMIT_FSIZE, &limit) != 0 {
                        return Err(std::io::Error::last_os_error());
                    }
                    Ok(())
                });
            }
        }
        None => {}
    }
    let o = cmd.output().expect("run the binary");
    if let Some(Full::Tmpfs(disk, _)) = full {
        disk.unfill();
    }
    o
}

fn voxrad(args: &[&str], full: Option<Full>) -> Output {
    run(env!("CARGO_BIN_EXE_voxrad"), args, full)
}

fn shard_tool(args: &[&str], full: Option<Full>) -> Output {
    run(env!("CARGO_BIN_EXE_voxrad-shard"), args, full)
}

fn assert_ok(o: &Output, what: &str) {
    assert!(
        o.status.success(),
        "{what}: {:?}\n{}",
        o.status,
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Exit status 1, no panic, a message naming `path` and saying `cause`.
fn assert_write_failure(o: &Output, what: &str, path: &Path, cause: &str) {
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!err.contains("panicked at"), "{what}: a panic: {err}");
    assert_eq!(o.status.code(), Some(1), "{what}: {err}");
    assert!(
        err.contains(&s(path)),
        "{what}: does not name {path:?}: {err}"
    );
    assert!(
        err.to_lowercase().contains(cause),
        "{what}: does not say {cause:?}: {err}"
    );
    let message = err.lines().find(|l| l.starts_with("error")).unwrap_or("");
    eprintln!("  {what}: {message}");
}

/// Every file under `dir` (recursively) with its bytes, to compare before and after.
fn snapshot(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let bytes = std::fs::read(&p).unwrap();
                out.push((p, bytes));
            }
        }
    }
    out.sort();
    out
}

fn entries(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

const SMALL: [&str; 8] = [
    "--directions",
    "13",
    "--iterations",
    "2",
    "--threads",
    "1",
    "--image-size",
    "80x60",
];

fn solve_obj(scene: &str, out: &Path, resolution: &str, full: Option<Full>) -> Output {
    let out = s(out);
    let mut args = vec!["solve", scene, "--out", &out, "--resolution", resolution];
    args.extend_from_slice(&SMALL);
    voxrad(&args, full)
}

/// `voxrad solve scene.obj --out DIR` on a full disk: the earlier outputs stay as they were, no
/// temporary file is left, and the same run works once there is space.
fn solve_on_a_full_disk(base: &Path, full: Full) {
    let what = format!("solve on a full disk ({full})");
    let out = base.join("out");
    assert_ok(
        &solve_obj(&example("cornell_box.obj"), &out, "8", None),
        "earlier solve",
    );
    let before = snapshot(&out);
    let o = solve_obj(&example("cornell_box.obj"), &out, "12", Some(full));
    assert_write_failure(&o, &what, &out, full.cause());
    assert!(
        snapshot(&out) == before,
        "{what}: the earlier outputs changed"
    );
    // Space is back: the same run works and replaces them.
    assert_ok(
        &solve_obj(&example("cornell_box.obj"), &out, "12", None),
        "solve with space",
    );
    assert_eq!(
        entries(&out),
        [
            "baked.glb",
            "baked.ply",
            "render.exr",
            "render.png",
            "report.json",
            "surfels.bin",
            "surfels.ply"
        ]
    );
    assert!(snapshot(&out) != before);
    eprintln!("{what}: exit 1, earlier outputs intact, works again with space");
}

/// `voxrad-shard convert` into a full disk: no set appears under the new name, an existing set
/// there stays as it was, no staging directory is left.
fn convert_on_a_full_disk(base: &Path, full: Full) {
    let what = format!("convert on a full disk ({full})");
    let convert = |set: &Path, resolution: &str, full: Option<Full>| {
        shard_tool(
            &[
                "convert",
                &example("cornell_box.obj"),
                "--resolution",
                resolution,
                "--out",
                &s(set),
                "--ranks",
                "2",
                "--threads",
                "1",
            ],
            full,
        )
    };
    let old = base.join("old.shards");
    assert_ok(&convert(&old, "8", None), "earlier convert");
    let before = snapshot(&old);
    let listing = entries(base);
    // Replacing an existing set.
    let o = convert(&old, "16", Some(full));
    assert_write_failure(&o, &format!("{what}, replacing"), base, full.cause());
    assert!(snapshot(&old) == before, "{what}: the earlier set changed");
    // A new set.
    let new = base.join("new.shards");
    let o = convert(&new, "16", Some(full));
    assert_write_failure(&o, &format!("{what}, new"), base, full.cause());
    assert!(
        !new.exists(),
        "{what}: a half-written set under the real name"
    );
    assert_eq!(entries(base), listing, "{what}: staging files left");
    // Space is back.
    assert_ok(&convert(&new, "16", None), "convert with space");
    assert_ok(&shard_tool(&["verify", &s(&new)], None), "verify");
    eprintln!("{what}: exit 1, nothing under the real name, old set intact, works with space");
}

/// The out-of-core solver's work files on a full disk (they live in a temporary directory under
/// `--out`): exit 1, the earlier results intact, no work files left.
fn out_of_core_on_a_full_disk(base: &Path, set: &Path, full: Full) {
    let what = format!("out-of-core solve on a full disk ({full})");
    let out = base.join("ooc");
    let solve = |full: Option<Full>| {
        let (set, out) = (s(set), s(&out));
        let mut args = vec!["solve", &set, "--out", &out, "--memory", "4MiB"];
        args.extend_from_slice(&SMALL);
        voxrad(&args, full)
    };
    assert_ok(&solve(None), "earlier out-of-core solve");
    let before = snapshot(&out);
    let o = solve(Some(full));
    assert_write_failure(&o, &what, &out, full.cause());
    assert!(
        snapshot(&out) == before,
        "{what}: the earlier outputs changed"
    );
    assert_ok(&solve(None), "out-of-core solve with space");
    eprintln!("{what}: exit 1, earlier outputs intact, works with space");
}

/// A shard set on the ordinary disk, for the out-of-core solves.
fn shard_set(dir: &Path) -> PathBuf {
    let set = dir.join("scene.shards");
    let o = shard_tool(
        &[
            "convert",
            &example("cornell_box.obj"),
            "--resolution",
            "12",
            "--out",
            &s(&set),
        ],
        None,
    );
    assert_ok(&o, "convert");
    set
}

#[test]
fn a_full_disk_stops_the_run_and_keeps_what_was_written() {
    let (disk, plain) = mechanisms("full disk");
    let set = shard_set(plain.path());
    if let Some(disk) = &disk {
        let full = Full::Tmpfs(disk, 0);
        solve_on_a_full_disk(disk.path(), full);
        // Room for the first output (the results file, 65 KB here) but not for the next ones:
        // the earlier outputs must not end up mixed with new ones.
        solve_on_a_full_disk(disk.path(), Full::Tmpfs(disk, 96 << 10));
        convert_on_a_full_disk(disk.path(), full);
        out_of_core_on_a_full_disk(disk.path(), &set, full);
    }
    // Small enough that every output and work file of these runs is larger.
    let full = Full::FileSizeLimit(2048);
    let base = plain.path().join("limited");
    std::fs::create_dir(&base).unwrap();
    solve_on_a_full_disk(&base, full);
    convert_on_a_full_disk(&base, full);
    out_of_core_on_a_full_disk(&base, &set, full);
}

/// How a directory was made read-only, so it can be made writable again.
enum ReadOnly {
    Remounted(PathBuf),
    BindMount(PathBuf),
    Immutable(PathBuf),
}

impl ReadOnly {
    /// Makes `dir` (holding earlier outputs) read-only by the first mechanism that works.
    fn make(disk: Option<&SmallDisk>, dir: &Path) -> Result<ReadOnly, String> {
        if let Some(disk) = disk {
            if remount(disk.path(), "ro") {
                eprintln!("read-only: mechanism tmpfs remounted read-only");
                return Ok(ReadOnly::Remounted(disk.path().to_path_buf()));
            }
        }
        let bind = Command::new("mount")
            .arg("--bind")
            .arg(dir)
            .arg(dir)
            .status();
        if bind.is_ok_and(|st| st.success()) {
            let ro = Command::new("mount")
                .args(["-o", "remount,bind,ro"])
                .arg(dir)
                .status();
            if ro.is_ok_and(|st| st.success()) {
                eprintln!("read-only: mechanism read-only bind mount");
                return Ok(ReadOnly::BindMount(dir.to_path_buf()));
            }
            let _ = Command::new("umount").arg(dir).status();
        }
        let chattr = Command::new("chattr").arg("+i").arg(dir).status();
        if chattr.is_ok_and(|st| st.success()) {
            eprintln!("read-only: mechanism chattr +i on the directory");
            return Ok(ReadOnly::Immutable(dir.to_path_buf()));
        }
        Err("no read-only remount, bind mount or chattr +i is allowed here".to_string())
    }

    /// What the message must say, lower case.
    fn cause(&self) -> &'static str {
        match self {
            ReadOnly::Remounted(_) | ReadOnly::BindMount(_) => "read-only",
            // An immutable directory refuses new files with EPERM.
            ReadOnly::Immutable(_) => "not permitted",
        }
    }
}

impl Drop for ReadOnly {
    fn drop(&mut self) {
        match self {
            ReadOnly::Remounted(path) => {
                remount(path, "rw");
            }
            ReadOnly::BindMount(dir) => {
                let _ = Command::new("umount").arg(&*dir).status();
            }
            ReadOnly::Immutable(dir) => {
                let _ = Command::new("chattr").arg("-i").arg(&*dir).status();
            }
        }
    }
}

#[test]
fn a_read_only_place_stops_the_run_and_keeps_what_was_there() {
    let (disk, plain) = mechanisms("read-only");
    let base = match &disk {
        Some(d) => d.path().to_path_buf(),
        None => plain.path().to_path_buf(),
    };
    let out = base.join("out");
    assert_ok(
        &solve_obj(&example("cornell_box.obj"), &out, "8", None),
        "earlier solve",
    );
    let before = snapshot(&out);
    // The tmpfs itself, or the output directory alone.
    let ro = match ReadOnly::make(disk.as_ref(), &out) {
        Ok(ro) => ro,
        Err(why) => {
            eprintln!("\n*** read-only: NOT EXERCISED: {why} ***\n");
            return;
        }
    };
    let o = solve_obj(&example("cornell_box.obj"), &out, "12", None);
    assert_write_failure(&o, "solve into a read-only directory", &out, ro.cause());
    assert!(snapshot(&out) == before, "the earlier outputs changed");
    let set = out.join("new.shards");
    let o = shard_tool(
        &[
            "convert",
            &example("cornell_box.obj"),
            "--resolution",
            "8",
            "--out",
            &s(&set),
        ],
        None,
    );
    assert_write_failure(&o, "convert into a read-only directory", &out, ro.cause());
    assert!(!set.exists());
    drop(ro);
    assert_ok(
        &solve_obj(&example("cornell_box.obj"), &out, "12", None),
        "solve once writable",
    );
    eprintln!("read-only: exit 1 naming the path, earlier outputs intact, works once writable");
}

/// The up-front check of the disk is honest about the work files: a solve it admits on a disk of
/// 400 bytes a surfel finishes there, with the direct-light pass, the tail extrapolation and
/// the links files at their defaults. Measured on a building of 7 million surfels, the work
/// set's peak was 405 bytes a surfel until the axis copies shared one radiosity file, the
/// gathered file a pass has read was emptied until the next pass writes it, and the files no
/// longer read were removed before the outputs are written; 260 since (docs/out-of-core.md).
/// The solve's own files add up to 96 bytes a surfel to that, and the links files take only
/// what is left once the work files' growth still to come is set aside: a build that counted
/// neither filled this disk, nor does one with more links asked for (`--links-disk`) than it
/// has. Without a tmpfs (not root, or no mount allowed) it says so loudly and checks nothing.
#[test]
fn the_work_files_fit_the_disk_the_check_admits() {
    let plain = TempDir::new().unwrap();
    let set = plain.path().join("scene.shards");
    let (scene, set_arg) = (example("cornell_box.obj"), s(&set));
    let o = shard_tool(
        &["convert", &scene, "--resolution", "96", "--out", &set_arg],
        None,
    );
    assert_ok(&o, "convert");
    // Shard records are 80 bytes a surfel, beside a small header and index.
    let set_bytes: u64 = std::fs::read_dir(&set)
        .unwrap()
        .map(|e| e.unwrap().metadata().unwrap().len())
        .sum();
    let surfels = set_bytes / 80;
    let per_surfel = 400;
    let disk = match SmallDisk::mount(per_surfel * surfels) {
        Ok(d) => d,
        Err(why) => {
            eprintln!("\n*** work files' peak: NO TMPFS ({why}); nothing checked ***\n");
            return;
        }
    };
    let (set, out, work) = (s(&set), s(&plain.path().join("out")), s(disk.path()));
    let mut args = vec!["solve", &set, "--out", &out, "--work-dir", &work];
    // Three iterations, so that updates and sends to the copies come between passes, and the
    // tail extrapolation keeps the radiosity before each; the Cornell box's lamp calls for the
    // direct-light pass at 49 directions.
    args.extend("--memory 16MiB --directions 49 --iterations 3".split(' '));
    let o = voxrad(&args, None);
    assert_ok(
        &o,
        "out-of-core solve with its work files on a disk of 400 bytes a surfel",
    );
    let report = std::fs::read_to_string(Path::new(&out).join("report.json")).unwrap();
    let report: serde_json::Value = serde_json::from_str(&report).unwrap();
    assert!(
        report["out_of_core"]["direct_light_parts"].as_u64() > Some(0),
        "the direct-light pass did not run: {report}"
    );
    // Links asked for beyond what the disk has left: they keep to what is free beyond the work
    // files' growth (a build that took what was asked filled the disk and failed writing a
    // gathered file), and they change no bit of the answer.
    let asked = s(&plain.path().join("asked"));
    args[3] = &asked;
    args.extend(["--links-disk", "1G"]);
    let o = voxrad(&args, None);
    assert_ok(&o, "the same solve with --links-disk 1G on that disk");
    let answer = |dir: &str| std::fs::read(Path::new(dir).join("surfels.bin")).unwrap();
    assert!(
        answer(&out) == answer(&asked),
        "links on disk changed the answer"
    );
    eprintln!(
        "work files' peak: {surfels} surfels solved with a {} MB disk for the work files",
        per_surfel * surfels / 1_000_000
    );
}

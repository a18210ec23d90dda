//! Running the real binary (or mpirun) as a child that can be killed at a chosen moment, as a
//! batch system or a power cut would: its own process group (so a signal reaches every process
//! it started), its log in a file (a pipe nobody reads would stall it), a seeded random source
//! for the moments.

use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// How long a test waits for a solve before taking it for hung. Only a guard: the tests of one
/// binary run side by side, and on a busy two-core machine an oversubscribed solve that takes
/// seconds alone can take minutes.
pub const HANG_LIMIT: Duration = Duration::from_secs(600);

/// splitmix64: a small seeded generator, so a failing schedule of kills can be replayed.
pub struct Rng(u64);

impl Rng {
    /// Seeded from `VOXRAD_TEST_SEED` if set, else from `default`; prints the seed.
    pub fn seeded(default: u64) -> Self {
        let seed = std::env::var("VOXRAD_TEST_SEED")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(default);
        println!("kill schedule seed {seed} (VOXRAD_TEST_SEED replays it)");
        Rng(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[lo, hi)`.
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// How a child ended.
#[derive(Debug)]
pub enum Ended {
    /// On its own, with this status.
    Exited(ExitStatus),
    /// Killed by the test (SIGKILL to its process group).
    Killed,
}

/// A running child in its own process group, its standard error going to a file.
pub struct Child {
    pub child: std::process::Child,
    pub started: Instant,
    log: std::path::PathBuf,
}

impl Child {
    pub fn spawn(mut command: Command, log: &Path) -> Child {
        let file = std::fs::File::create(log).expect("create log");
        command
            .stdout(Stdio::null())
            .stderr(file)
            .env("NO_COLOR", "1")
            .process_group(0);
        let child = command.spawn().expect("start the child");
        Child {
            child,
            started: Instant::now(),
            log: log.to_path_buf(),
        }
    }

    pub fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    /// Its standard error so far.
    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Sends `signal` to the whole process group.
    pub fn signal_group(&self, signal: i32) {
        // SAFETY: kill(2) with a negative pid signals a process group; no memory is involved.
        unsafe {
            libc::kill(-self.pid(), signal);
        }
    }

    /// Waits until `ready()` holds, the child exits or `timeout` passes; true if ready.
    pub fn wait_for(&mut self, timeout: Duration, mut ready: impl FnMut() -> bool) -> bool {
        let deadline = Instant::now() + timeout;
        while Instant::now() < deadline {
            if ready() {
                return true;
            }
            if self.child.try_wait().expect("poll the child").is_some() {
                return ready();
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        false
    }

    /// Lets the child run until it exits or `delay` (from now) passes, then kills its group.
    pub fn run_or_kill_after(&mut self, delay: Duration) -> Ended {
        let deadline = Instant::now() + delay;
        loop {
            if let Some(status) = self.child.try_wait().expect("poll the child") {
                return Ended::Exited(status);
            }
            if Instant::now() >= deadline {
                self.signal_group(libc::SIGKILL);
                let _ = self.child.wait();
                return Ended::Killed;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    /// Waits for the child to exit, at most `timeout`; kills the group and fails after that.
    pub fn wait_at_most(&mut self, timeout: Duration) -> ExitStatus {
        match self.run_or_kill_after(timeout) {
            Ended::Exited(status) => status,
            Ended::Killed => panic!(
                "still running after {timeout:?}, killed; its log:\n{}",
                self.log()
            ),
        }
    }
}

/// The exit status as a number, or a description of the signal that ended it.
pub fn describe(status: &ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    match (status.code(), status.signal()) {
        (Some(c), _) => format!("exit status {c}"),
        (None, Some(s)) => format!("signal {s}"),
        _ => "unknown".to_string(),
    }
}

/// The processes whose parent is `pid` (from `/proc`).
pub fn children_of(pid: i32) -> Vec<i32> {
    let mut out = Vec::new();
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return out;
    };
    for entry in entries.flatten() {
        let Ok(child) = entry.file_name().to_string_lossy().parse::<i32>() else {
            continue;
        };
        if stat_fields(child).is_some_and(|(_, ppid)| ppid == pid) {
            out.push(child);
        }
    }
    out
}

/// State letter and parent of a process, from `/proc/PID/stat` (the command name, in
/// parentheses, may hold spaces: the fields after its closing parenthesis are read).
fn stat_fields(pid: i32) -> Option<(char, i32)> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let rest = &stat[stat.rfind(')')? + 2..];
    let mut fields = rest.split_whitespace();
    let state = fields.next()?.chars().next()?;
    let ppid = fields.next()?.parse().ok()?;
    Some((state, ppid))
}

/// Whether `pid` is still running (a zombie counts as gone).
pub fn alive(pid: i32) -> bool {
    stat_fields(pid).is_some_and(|(state, _)| state != 'Z' && state != 'X')
}

/// The value of `key` in the environment of process `pid`.
pub fn env_of(pid: i32, key: &str) -> Option<String> {
    let bytes = std::fs::read(format!("/proc/{pid}/environ")).ok()?;
    bytes.split(|&b| b == 0).find_map(|entry| {
        let text = String::from_utf8_lossy(entry);
        let (k, v) = text.split_once('=')?;
        (k == key).then(|| v.to_string())
    })
}

/// Sends SIGKILL to each of `pids` and waits (at most 30 s) until none runs.
pub fn kill_and_reap(pids: &[i32]) {
    for &p in pids {
        // SAFETY: kill(2) on processes this test started (through mpirun).
        unsafe {
            libc::kill(p, libc::SIGKILL);
        }
    }
    let deadline = Instant::now() + Duration::from_secs(30);
    while pids.iter().any(|&p| alive(p)) {
        assert!(
            Instant::now() < deadline,
            "processes {pids:?} survive SIGKILL"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// What a resumed run's log says when it continues inside an iteration.
pub const CONTINUED_INSIDE: &str = "continuing inside an iteration";

/// Reads the log of one run of a kill schedule, which must not have panicked: whether it resumed
/// from a checkpoint, and whether it continued inside an iteration.
pub fn resumed_and_inside(text: &str) -> (bool, bool) {
    assert!(!text.contains("panicked"), "{text}");
    (
        text.contains("resumed from a checkpoint"),
        text.contains(CONTINUED_INSIDE),
    )
}

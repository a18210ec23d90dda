//! SIGTERM and SIGINT as a request to stop: the handler only records the signal in an atomic,
//! and the iteration loops ask [`requested`] between directions, save what they have done (the
//! directions of the iteration in progress where they keep mid-iteration checkpoints, else the
//! last completed iteration) and return (`solve::jacobi` and `outcore::solver`); the command
//! then exits with status 3 (see `docs/checkpoints.md`).
//!
//! Before the iterations start (reading, voxelizing, converting, making the out-of-core work
//! files: work a resumed run does again anyway, and that can take minutes on a large scene, longer
//! than a batch system waits after its signal) there is nothing new to save: a watchdog thread
//! ([`watch_setup`]) ends the process at once with status 3. The iteration loops take over with
//! [`start_iterating`], and from the end of the iterations on a signal is left unanswered so that
//! the outputs are finished.
//!
//! The handler is installed with `SA_RESETHAND`: the first signal asks politely, a second one
//! (a user pressing Ctrl-C again, or a batch system that gave up waiting) gets the default
//! action and ends the process at once. The only thing done inside the handler is an atomic
//! store, which is async-signal-safe.

use std::sync::atomic::{AtomicI32, AtomicU8, Ordering};
use std::time::Duration;

/// The signal received, 0 while none was.
static RECEIVED: AtomicI32 = AtomicI32::new(0);

/// Who answers a signal: the watchdog (before the iterations), the loops, or the watchdog is
/// ending the process.
static PHASE: AtomicU8 = AtomicU8::new(SETUP);
const SETUP: u8 = 0;
const ITERATING: u8 = 1;
const EXITING: u8 = 2;

extern "C" fn record(signal: libc::c_int) {
    RECEIVED.store(signal, Ordering::SeqCst);
}

/// Installs the handler for SIGTERM and SIGINT (for the rest of the process).
pub fn install() -> std::io::Result<()> {
    for signal in [libc::SIGTERM, libc::SIGINT] {
        // SAFETY: `action` is fully initialised (zeroed, then the fields sigaction reads are
        // set); the handler only performs an atomic store.
        let result = unsafe {
            let mut action: libc::sigaction = std::mem::zeroed();
            action.sa_sigaction = record as extern "C" fn(libc::c_int) as libc::sighandler_t;
            action.sa_flags = libc::SA_RESETHAND | libc::SA_RESTART;
            libc::sigemptyset(&mut action.sa_mask);
            libc::sigaction(signal, &action, std::ptr::null_mut())
        };
        if result != 0 {
            return Err(std::io::Error::last_os_error());
        }
    }
    Ok(())
}

/// The stop signal received so far, if any.
pub fn requested() -> Option<i32> {
    match RECEIVED.load(Ordering::Relaxed) {
        0 => None,
        s => Some(s),
    }
}

/// Starts the watchdog thread: a stop signal that comes before [`start_iterating`] ends the
/// process with exit status 3, printing `interrupted by SIGTERM before the iterations started;
/// {advice}`.
pub fn watch_setup(advice: String) {
    let spawned = std::thread::Builder::new()
        .name("voxrad-signals".into())
        .spawn(move || loop {
            std::thread::sleep(Duration::from_millis(20));
            if let Some(signal) = requested() {
                // Only if the loops have not taken over (they then write the checkpoint).
                if PHASE
                    .compare_exchange(SETUP, EXITING, Ordering::SeqCst, Ordering::SeqCst)
                    .is_ok()
                {
                    eprintln!(
                        "error: interrupted by {} before the iterations started; {advice}",
                        name(signal)
                    );
                    std::process::exit(3);
                }
                return;
            }
            if PHASE.load(Ordering::SeqCst) != SETUP {
                return;
            }
        });
    if let Err(e) = spawned {
        tracing::warn!("cannot watch for stop signals before the iterations ({e})");
    }
}

/// Called by an iteration loop before its first iteration: from here it answers stop signals
/// itself (between directions). If the watchdog is already ending the process, waits for that.
pub fn start_iterating() {
    if PHASE
        .compare_exchange(SETUP, ITERATING, Ordering::SeqCst, Ordering::SeqCst)
        .is_err()
        && PHASE.load(Ordering::SeqCst) == EXITING
    {
        loop {
            std::thread::park();
        }
    }
}

/// The conventional name of a signal number, for messages.
pub fn name(signal: i32) -> String {
    match signal {
        libc::SIGTERM => "SIGTERM".to_string(),
        libc::SIGINT => "SIGINT".to_string(),
        other => format!("signal {other}"),
    }
}

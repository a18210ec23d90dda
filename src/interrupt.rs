//! SIGTERM and SIGINT as a request to stop: the handler only records the signal in an atomic,
//! and the iteration loops ask [`requested`] between directions, abandon the iteration they are
//! in, keep the checkpoint of the last completed one and return (`solve::jacobi` and
//! `outcore::solver`); the command then exits with status 3 (see the README, "Checkpoints and
//! signals").
//!
//! The handler is installed with `SA_RESETHAND`: the first signal asks politely, a second one
//! (a user pressing Ctrl-C again, or a batch system that gave up waiting) gets the default
//! action and ends the process at once. The only thing done inside the handler is an atomic
//! store, which is async-signal-safe.

use std::sync::atomic::{AtomicI32, Ordering};

/// The signal received, 0 while none was.
static RECEIVED: AtomicI32 = AtomicI32::new(0);

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

/// The conventional name of a signal number, for messages.
pub fn name(signal: i32) -> String {
    match signal {
        libc::SIGTERM => "SIGTERM".to_string(),
        libc::SIGINT => "SIGINT".to_string(),
        other => format!("signal {other}"),
    }
}

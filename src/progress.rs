//! What the binaries tell the user while they work: progress bars for steps that can take more
//! than a couple of seconds, and the log on standard error.
//!
//! Bars draw on standard error only when it is a terminal (indicatif hides them otherwise), so
//! batch logs and tests stay clean; so do colours in the log.

use indicatif::{ProgressBar, ProgressStyle};

/// A bar over `len` items with a short message.
pub fn bar(len: u64, message: &str) -> ProgressBar {
    let bar = ProgressBar::new(len);
    let style = ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} ({eta} left)")
        .map(|s| s.progress_chars("=> "))
        .unwrap_or_else(|_| ProgressStyle::default_bar());
    bar.set_style(style);
    bar.set_message(message.to_string());
    bar
}

/// Sets up the log on standard error: `-v` for info from every crate, `-vv` for debug; by
/// default warnings, plus voxrad's own info lines. `RUST_LOG` overrides.
pub fn init_logging(verbose: u8) {
    let default = match verbose {
        0 => "warn,voxrad=info",
        1 => "info",
        _ => "debug",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_target(false)
        .init();
}

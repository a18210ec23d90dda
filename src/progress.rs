//! Progress bars for steps that can take more than a couple of seconds.
//!
//! Bars draw on standard error only when it is a terminal (indicatif hides them otherwise), so
//! batch logs and tests stay clean.

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

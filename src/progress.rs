//! What the binaries tell the user while they work: progress bars for steps that can take more
//! than a couple of seconds, and the log on standard error.
//!
//! Bars draw on standard error when it is a terminal. In a batch job (standard error a file) a
//! bar instead writes its state as a log line once every [`BATCH_INTERVAL`] (`iteration 3:
//! 57/193 (29 %), 9m 12s in, about 23m left`), so that a night-long solve says where it is
//! between its checkpoints; a step shorter than that writes nothing, so short runs' logs and the
//! tests' stay clean. Colours in the log only on a terminal too.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle, TermLike};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// How often a bar writes a log line in a batch job (and how long a step runs before its
/// first).
pub const BATCH_INTERVAL: Duration = Duration::from_secs(60);

/// A bar over `len` items with a short message.
pub fn bar(len: u64, message: &str) -> ProgressBar {
    let bar = ProgressBar::new(len);
    if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        let style = ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} ({eta} left)")
            .map(|s| s.progress_chars("=> "))
            .unwrap_or_else(|_| ProgressStyle::default_bar());
        bar.set_style(style);
    } else {
        bar.set_style(batch_style());
        // Drawn at most once a second; the lines themselves are spaced further apart.
        let lines = LogLines::new(BATCH_INTERVAL, Box::new(|line| tracing::info!("{line}")));
        bar.set_draw_target(ProgressDrawTarget::term_like_with_hz(Box::new(lines), 1));
    }
    bar.set_message(message.to_string());
    bar
}

/// A bar's state as one line of a log.
fn batch_style() -> ProgressStyle {
    ProgressStyle::with_template("{msg}: {pos}/{len} ({percent} %), {elapsed} in, about {eta} left")
        .unwrap_or_else(|_| ProgressStyle::default_bar())
}

/// A bar's drawing turned into lines handed to `emit`, at most one every `interval`, the first
/// an `interval` after the bar began.
struct LogLines {
    interval: Duration,
    state: Mutex<LogLinesState>,
    emit: Box<dyn Fn(&str) + Send + Sync>,
}

impl std::fmt::Debug for LogLines {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LogLines")
            .field("interval", &self.interval)
            .finish_non_exhaustive()
    }
}

#[derive(Debug)]
struct LogLinesState {
    /// When the last line was written (at first, when the bar began).
    last: Instant,
    /// The text drawn since the last flush.
    text: String,
}

impl LogLines {
    fn new(interval: Duration, emit: Box<dyn Fn(&str) + Send + Sync>) -> Self {
        LogLines {
            interval,
            state: Mutex::new(LogLinesState {
                last: Instant::now(),
                text: String::new(),
            }),
            emit,
        }
    }

    /// Takes what was drawn; returns it if a line is due.
    fn due(&self) -> Option<String> {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let text = std::mem::take(&mut state.text);
        let text = text.trim();
        if text.is_empty() || state.last.elapsed() < self.interval {
            return None;
        }
        state.last = Instant::now();
        Some(text.to_string())
    }

    fn add(&self, s: &str) {
        let mut state = self.state.lock().unwrap_or_else(|e| e.into_inner());
        state.text.push_str(s);
    }
}

impl TermLike for LogLines {
    fn width(&self) -> u16 {
        // Wide enough that no line is cut.
        u16::MAX
    }
    fn move_cursor_up(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_down(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_right(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_left(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn write_line(&self, s: &str) -> std::io::Result<()> {
        self.add(s);
        Ok(())
    }
    fn write_str(&self, s: &str) -> std::io::Result<()> {
        self.add(s);
        Ok(())
    }
    fn clear_line(&self) -> std::io::Result<()> {
        Ok(())
    }
    fn flush(&self) -> std::io::Result<()> {
        if let Some(line) = self.due() {
            (self.emit)(&line);
        }
        Ok(())
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    /// In a batch job a bar writes its state once an interval has passed, not before, and
    /// not more often.
    #[test]
    fn a_batch_bar_writes_a_line_once_an_interval_has_passed() {
        let lines = Arc::new(Mutex::new(Vec::<String>::new()));
        let sink = lines.clone();
        let emit = Box::new(move |line: &str| sink.lock().unwrap().push(line.to_string()));
        let interval = Duration::from_millis(300);
        let target =
            ProgressDrawTarget::term_like_with_hz(Box::new(LogLines::new(interval, emit)), 100);
        let bar = ProgressBar::with_draw_target(Some(10), target);
        bar.set_style(batch_style());
        bar.set_message("iteration 2");
        bar.inc(1);
        std::thread::sleep(Duration::from_millis(30));
        bar.inc(1);
        assert!(
            lines.lock().unwrap().is_empty(),
            "a line before the interval"
        );
        std::thread::sleep(interval);
        bar.inc(1);
        std::thread::sleep(Duration::from_millis(30));
        bar.inc(1);
        let got = lines.lock().unwrap().clone();
        assert_eq!(got.len(), 1, "{got:?}");
        assert!(got[0].starts_with("iteration 2: 3/10 (30 %),"), "{got:?}");
        assert!(got[0].contains(" left"), "{got:?}");
    }
}

//! A solve stopped by a signal: what it saved and how to go on, in words for the user.

use super::*;

/// A solve stopped by SIGTERM or SIGINT (exit status 3).
#[derive(Clone, Debug)]
pub struct Interruption {
    pub signal: i32,
    /// Iterations completed when it stopped.
    pub completed: usize,
    /// Directions of the next iteration gathered when it stopped (and saved), if it stopped
    /// inside an iteration and kept that.
    pub within: Option<u64>,
    /// The checkpoint to resume from, its iteration and its mid-iteration position.
    pub checkpoint: Option<(PathBuf, u64, Option<u64>)>,
    /// Why the checkpoint of the last completed iteration could not be written.
    pub failure: Option<String>,
    /// Whether this process wrote the checkpoints (rank 0).
    pub writer: bool,
}

impl Interruption {
    /// A stop with no checkpoint to point to (the solve keeps none); `writer` is whether this
    /// process speaks for the run (rank 0).
    pub fn without_checkpoint(signal: i32, completed: usize, writer: bool) -> Self {
        Interruption {
            signal,
            completed,
            within: None,
            checkpoint: None,
            failure: None,
            writer,
        }
    }
}

impl std::fmt::Display for Interruption {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let signal = crate::interrupt::name(self.signal);
        let when = match self.within {
            Some(done) => format!(
                "after iteration {} and {done} directions of the next",
                self.completed
            ),
            None => format!("after iteration {}", self.completed),
        };
        if !self.writer {
            return write!(
                f,
                "interrupted by {signal} {when}; rank 0 wrote the checkpoint"
            );
        }
        write!(f, "interrupted by {signal} {when}; ")?;
        if let Some(e) = &self.failure {
            write!(f, "its checkpoint could not be written ({e}); ")?;
        }
        match &self.checkpoint {
            Some((path, iteration, within)) => {
                write!(f, "checkpoint at {} (iteration {iteration}", path.display())?;
                if let Some(done) = within {
                    write!(f, ", {done} directions into the next")?;
                }
                write!(f, "); rerun with --resume to continue")
            }
            None => write!(f, "no checkpoint; rerun to start again"),
        }
    }
}

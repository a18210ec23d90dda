//! The outputs of one run, written together: every file goes into a hidden staging directory
//! inside the output directory, and only when all of them are complete are they moved into place.
//!
//! Each writer already writes atomically (`atomic`), so no single file is ever half-written; but a
//! solve writes four files, and a disk that fills up after the first left the new `surfels.bin`
//! beside the old `report.json`, `surfels.ply` and `render.png`: a mixed result that looks
//! finished. Staged, a failure anywhere leaves the earlier outputs exactly as they were (the
//! staging directory is removed when the [`Staging`] is dropped), and publishing is a series of
//! renames inside one file system, which need no free space. A crash in the middle of
//! publishing (a few renames) can still mix, as any multi-file update without a journal can, and
//! a killed run leaves its hidden staging directory behind (never a file under a real name).

use super::OutputError;
use std::path::{Path, PathBuf};

/// A staging directory inside an output directory (see the module header).
pub struct Staging {
    out: PathBuf,
    dir: tempfile::TempDir,
}

impl Staging {
    /// Creates the output directory if needed and a staging directory inside it.
    pub fn new(out: &Path) -> Result<Staging, OutputError> {
        std::fs::create_dir_all(out).map_err(|e| OutputError::io(out, e))?;
        let dir = tempfile::Builder::new()
            .prefix(".voxrad-new-")
            .tempdir_in(out)
            .map_err(|e| OutputError::io(out, e))?;
        Ok(Staging {
            out: out.to_path_buf(),
            dir,
        })
    }

    /// The output directory the files go to.
    pub fn out(&self) -> &Path {
        &self.out
    }

    /// Where the run's outputs are written, under their final names.
    pub fn path(&self) -> &Path {
        self.dir.path()
    }

    /// Moves every staged file into the output directory, replacing earlier ones of the same
    /// names; returns their final paths.
    pub fn publish(self) -> Result<Vec<PathBuf>, OutputError> {
        let staged = self.dir.path();
        let mut names = Vec::new();
        for entry in std::fs::read_dir(staged).map_err(|e| OutputError::io(staged, e))? {
            let entry = entry.map_err(|e| OutputError::io(staged, e))?;
            names.push(entry.file_name());
        }
        // A fixed order, so a run publishes the same way every time.
        names.sort();
        let mut published = Vec::with_capacity(names.len());
        for name in names {
            let to = self.out.join(&name);
            std::fs::rename(staged.join(&name), &to).map_err(|e| OutputError::io(&to, e))?;
            published.push(to);
        }
        // Best effort, as in `atomic::commit`: the renames themselves survive a power loss.
        if let Ok(dir) = std::fs::File::open(&self.out) {
            let _ = dir.sync_all();
        }
        Ok(published)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::atomic::write_atomically;

    #[test]
    fn nothing_changes_until_publish_and_a_failed_run_leaves_nothing() {
        let tmp = tempfile::TempDir::new().unwrap();
        let out = tmp.path().join("out");
        std::fs::create_dir(&out).unwrap();
        std::fs::write(out.join("a.txt"), b"old a").unwrap();
        std::fs::write(out.join("b.txt"), b"old b").unwrap();

        // A run that fails after its first file: the earlier outputs stay, nothing is left.
        {
            let staging = Staging::new(&out).unwrap();
            write_atomically(&staging.path().join("a.txt"), |w| w.write_all(b"new a")).unwrap();
            assert_eq!(std::fs::read(out.join("a.txt")).unwrap(), b"old a");
        }
        let mut names: Vec<_> = std::fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        names.sort();
        assert_eq!(names, ["a.txt", "b.txt"]);

        // A run that finishes: both replaced together.
        let staging = Staging::new(&out).unwrap();
        for (name, text) in [("a.txt", "new a"), ("b.txt", "new b")] {
            write_atomically(&staging.path().join(name), |w| w.write_all(text.as_bytes())).unwrap();
        }
        let published = staging.publish().unwrap();
        assert_eq!(published, [out.join("a.txt"), out.join("b.txt")]);
        assert_eq!(std::fs::read(out.join("a.txt")).unwrap(), b"new a");
        assert_eq!(std::fs::read(out.join("b.txt")).unwrap(), b"new b");
        assert_eq!(std::fs::read_dir(&out).unwrap().count(), 2);
    }
}

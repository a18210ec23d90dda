//! Crash-safe file writing: write to a temporary file beside the target, sync it, rename it.
//!
//! Every output of a solve can take minutes or hours to produce, and a crash, a kill or a full
//! disk in the middle must not leave a truncated file under the real name (a reader would take it
//! for a finished result, or it would replace a good file from an earlier run). The temporary file
//! is created in the target's own directory so the final rename stays on one file system and is
//! atomic; if anything fails before the rename, dropping the `NamedTempFile` deletes it.

use super::OutputError;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;
use tempfile::NamedTempFile;

/// The directory a file will be written into ("." for a bare file name).
pub fn parent_dir(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// Creates a temporary file in the directory of `path`, readable by all like an ordinary new file
/// (tempfile makes it owner-only, which would stay so after the rename: results of a cluster job
/// are usually read by other users and programs).
pub fn temp_beside(path: &Path) -> Result<NamedTempFile, OutputError> {
    let tmp = NamedTempFile::new_in(parent_dir(path)).map_err(|e| OutputError::io(path, e))?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        tmp.as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o644))
            .map_err(|e| OutputError::io(path, e))?;
    }
    Ok(tmp)
}

/// Syncs `tmp` to disk and renames it to `path`, then syncs the directory so the rename itself
/// survives a power loss.
pub fn commit(tmp: NamedTempFile, path: &Path) -> Result<(), OutputError> {
    tmp.as_file()
        .sync_all()
        .map_err(|e| OutputError::io(path, e))?;
    tmp.persist(path)
        .map_err(|e| OutputError::io(path, e.error))?;
    // Best effort: not every platform or file system lets a directory be opened and synced, and
    // the data itself is already durable.
    if let Ok(dir) = File::open(parent_dir(path)) {
        let _ = dir.sync_all();
    }
    Ok(())
}

/// Writes a whole file through `fill`, atomically (see the module header).
pub fn write_atomically<F>(path: &Path, fill: F) -> Result<(), OutputError>
where
    F: FnOnce(&mut dyn Write) -> std::io::Result<()>,
{
    let mut tmp = temp_beside(path)?;
    {
        let mut out = BufWriter::with_capacity(1 << 20, tmp.as_file_mut());
        fill(&mut out).map_err(|e| OutputError::io(path, e))?;
        out.flush().map_err(|e| OutputError::io(path, e))?;
    }
    commit(tmp, path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failed_write_leaves_nothing_under_the_real_name() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("out.txt");
        let err = write_atomically(&path, |w| {
            w.write_all(b"half")?;
            Err(std::io::Error::other("disk full"))
        })
        .unwrap_err();
        assert!(err.to_string().contains("out.txt"), "{err}");
        assert!(!path.exists());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        write_atomically(&path, |w| w.write_all(b"whole")).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"whole");
    }
}

//! Memory maps in bounded windows: the only place in voxrad that maps files, and the only
//! `unsafe` in `storage`.
//!
//! A solve reads every shard once per streaming pass. Mapping a whole shard would make the
//! process's address space (what `prlimit --as` limits) as large as the data, so a
//! [`WindowedFile`] maps at most `window_bytes` of a file at a time, starting on a page boundary,
//! and moves the window forward as reads advance; the previous window is unmapped before the next
//! one is mapped, so at most one window per reader is ever mapped. Records (80 bytes) do not
//! divide pages (4096 bytes), so a record that straddles a window's end is copied in two pieces.
//! [`WindowedRecords`] iterates a shard's records this way and checks the checksum as it goes,
//! like the buffered reader of `shard`.
//!
//! The safety argument, in one place: mapping a file is only sound while no one modifies or
//! truncates it (a write would change memory Rust considers immutable; a truncation would make
//! reads fault with SIGBUS). Shard files are immutable once renamed into place (`shard` writes
//! under a temporary name and never reopens a finished file for writing), and voxrad only maps
//! files that went through [`super::shard::ShardReader::open_lazy`], i.e. finished shards. Another
//! process altering a shard set while it is being read is outside the contract, as for any
//! memory-mapped database.

use super::record::{self, RECORD_LEN};
use super::shard::{ShardReader, HEADER_LEN};
use super::StorageError;
use crate::voxel::Surfel;
use memmap2::{Advice, Mmap, MmapOptions};
use std::fs::File;
use std::path::{Path, PathBuf};

/// The size of a virtual-memory page, to which window offsets are aligned.
pub fn page_size() -> u64 {
    // SAFETY: `sysconf` reads a system constant; it takes no pointers and has no preconditions.
    let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
    if page > 0 {
        page as u64
    } else {
        4096
    }
}

/// A read-only file read through one memory-mapped window of bounded size.
pub struct WindowedFile {
    path: PathBuf,
    file: File,
    len: u64,
    window_bytes: u64,
    page_bytes: u64,
    /// The current window and the file offset of its first byte.
    map: Option<(u64, Mmap)>,
    maps: u64,
}

impl WindowedFile {
    /// Opens `path` for windows of `window_bytes`, rounded up to a whole number of pages (at
    /// least one). The file must be a finished shard (see the module header).
    pub fn open(path: &Path, window_bytes: u64) -> Result<Self, StorageError> {
        let file = File::open(path).map_err(|e| StorageError::io(path, "read", e))?;
        let len = file
            .metadata()
            .map_err(|e| StorageError::io(path, "read", e))?
            .len();
        let page_bytes = page_size();
        let pages = window_bytes.div_ceil(page_bytes).max(1);
        Ok(WindowedFile {
            path: path.to_path_buf(),
            file,
            len,
            window_bytes: pages * page_bytes,
            page_bytes,
            map: None,
            maps: 0,
        })
    }

    /// The window size actually used (a whole number of pages).
    pub fn window_bytes(&self) -> u64 {
        self.window_bytes
    }

    /// Length of the file in bytes.
    pub fn len(&self) -> u64 {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// How many windows have been mapped so far.
    pub fn maps(&self) -> u64 {
        self.maps
    }

    /// Maps the window holding `offset`, replacing the current one.
    fn move_to(&mut self, offset: u64) -> Result<(), StorageError> {
        if offset >= self.len {
            return Err(StorageError::io(
                &self.path,
                "map",
                std::io::Error::new(
                    std::io::ErrorKind::UnexpectedEof,
                    format!("offset {offset} is past the end ({} bytes)", self.len),
                ),
            ));
        }
        // Unmap first: at most one window is mapped at any time.
        self.map = None;
        let start = offset / self.page_bytes * self.page_bytes;
        let len = self.window_bytes.min(self.len - start) as usize;
        // SAFETY: the mapping is read-only and the file is a finished shard, which nobody
        // modifies or truncates while it is mapped (module header). `start + len` lies inside the
        // file, checked above against its length, and `start` is page-aligned as mmap requires.
        let map = unsafe { MmapOptions::new().offset(start).len(len).map(&self.file) }
            .map_err(|e| StorageError::io(&self.path, "map", e))?;
        // A hint only: readahead helps a sequential pass, and failing to set it changes nothing.
        let _ = map.advise(Advice::Sequential);
        self.map = Some((start, map));
        self.maps += 1;
        Ok(())
    }

    /// Copies `buf.len()` bytes starting at `offset`, moving the window as needed.
    pub fn read_exact_at(&mut self, offset: u64, buf: &mut [u8]) -> Result<(), StorageError> {
        let mut done = 0;
        while done < buf.len() {
            let at = offset + done as u64;
            let inside = matches!(&self.map, Some((start, m)) if at >= *start && at < *start + m.len() as u64);
            if !inside {
                self.move_to(at)?;
            }
            if let Some((start, m)) = &self.map {
                let from = (at - start) as usize;
                let n = (buf.len() - done).min(m.len() - from);
                buf[done..done + n].copy_from_slice(&m[from..from + n]);
                done += n;
            }
        }
        Ok(())
    }
}

/// Iterates a shard's records through a [`WindowedFile`]. Yields an error and stops on a
/// mapping failure; after the last record, yields a [`StorageError::ChecksumMismatch`] if the
/// bytes read do not match the footer (so everything taken from the iterator is unreliable if
/// its last item is an error).
pub struct WindowedRecords {
    reader: ShardReader,
    file: WindowedFile,
    hasher: crc32fast::Hasher,
    next: u64,
    done: bool,
}

impl WindowedRecords {
    /// Iterates the shard opened as `reader` with windows of at most `window_bytes` (rounded up
    /// to whole pages).
    pub fn new(reader: &ShardReader, window_bytes: u64) -> Result<Self, StorageError> {
        let file = WindowedFile::open(reader.path(), window_bytes)?;
        if file.len() != reader.info().bytes {
            return Err(StorageError::BadLength {
                path: reader.path().to_path_buf(),
                what: format!(
                    "{} bytes when opened, {} now: the file changed while in use",
                    reader.info().bytes,
                    file.len()
                ),
            });
        }
        let mut hasher = crc32fast::Hasher::new();
        hasher.update(reader.header_bytes());
        Ok(WindowedRecords {
            reader: reader.clone(),
            file,
            hasher,
            next: 0,
            done: false,
        })
    }

    /// The windowed file underneath (for its window size and map count).
    pub fn file(&self) -> &WindowedFile {
        &self.file
    }
}

impl Iterator for WindowedRecords {
    type Item = Result<Surfel, StorageError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        if self.next == self.reader.info().count {
            self.done = true;
            let computed = self.hasher.clone().finalize();
            return self.reader.compare_checksum(computed).err().map(Err);
        }
        let mut buf = [0u8; RECORD_LEN];
        let offset = HEADER_LEN + self.next * RECORD_LEN as u64;
        if let Err(e) = self.file.read_exact_at(offset, &mut buf) {
            self.done = true;
            return Some(Err(e));
        }
        self.hasher.update(&buf);
        self.next += 1;
        Some(Ok(record::decode(&buf)))
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = (self.reader.info().count - self.next) as usize;
        (left, Some(left + 1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::shard::tests::{sorted_surfels, write_shard};

    fn windowed(reader: &ShardReader, window_bytes: u64) -> (Vec<Surfel>, u64) {
        let mut it = WindowedRecords::new(reader, window_bytes).unwrap();
        let records: Vec<Surfel> = it.by_ref().collect::<Result<_, _>>().unwrap();
        (records, it.file().maps())
    }

    #[test]
    fn every_window_size_reads_the_same_records() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("s.vxs");
        // About 39 KiB: ten pages, with records straddling most page boundaries.
        let surfels = sorted_surfels(500, 1, 5);
        let info = write_shard(&path, 1, &surfels);
        let reader = ShardReader::open(&path).unwrap();
        let page = page_size();

        let (one_page, maps) = windowed(&reader, page);
        assert_eq!(one_page, surfels);
        let records_end = HEADER_LEN + surfels.len() as u64 * RECORD_LEN as u64;
        assert_eq!(maps, records_end.div_ceil(page), "one map per page touched");

        let (few_records, maps) = windowed(&reader, 3 * RECORD_LEN as u64);
        assert_eq!(few_records, surfels);
        assert!(maps > 1);

        let (whole, maps) = windowed(&reader, info.bytes);
        assert_eq!(whole, surfels);
        assert_eq!(maps, 1);
    }

    #[test]
    fn window_is_page_aligned_and_bounded() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("s.vxs");
        write_shard(&path, 0, &sorted_surfels(200, 0, 9));
        let page = page_size();
        let mut f = WindowedFile::open(&path, 1).unwrap();
        assert_eq!(f.window_bytes(), page);
        // A read across a page boundary is stitched from two windows.
        let mut buf = [0u8; 16];
        f.read_exact_at(page - 8, &mut buf).unwrap();
        assert_eq!(f.maps(), 2);
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(buf[..], bytes[page as usize - 8..page as usize + 8]);
        let e = f.read_exact_at(f.len() - 4, &mut buf).unwrap_err();
        assert!(e.to_string().contains("s.vxs"), "{e}");
    }

    #[test]
    fn corruption_is_reported_at_the_end() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("s.vxs");
        write_shard(&path, 3, &sorted_surfels(60, 3, 2));
        let reader = ShardReader::open_lazy(&path).unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[HEADER_LEN as usize + 59 * RECORD_LEN + 3] ^= 1;
        std::fs::write(&path, bytes).unwrap();
        let items: Vec<_> = WindowedRecords::new(&reader, 4096).unwrap().collect();
        assert_eq!(items.len(), 61);
        assert!(matches!(
            items.last(),
            Some(Err(StorageError::ChecksumMismatch { .. }))
        ));
    }
}

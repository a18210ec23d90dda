//! Work files of `u32` indexes read and written in order, compressed: a copy's canonical ids (the
//! canonical index of each of its records, in its order) and the canonical surfels' places in a
//! copy (`super::workset`). The permutations that bring light and radiosity between a copy's
//! order and the canonical one read them from start to end, never at a position.
//!
//! ```text
//! frame after frame, FRAME_VALUES values each (the last may hold fewer):
//!   count   u32 LE   values in the frame
//!   packed  u32 LE   bytes of the LZ4 block that follows
//!   block            LZ4 block of the frame's differences as 4 byte planes (byte 0 of every
//!                    difference, then byte 1, ...); a difference is the value less the one
//!                    before it (wrapping; the frame's first value less 0)
//! ```
//!
//! Why: at 4 bytes a surfel each, the ids and places of the three copies took 24 bytes a surfel
//! of the work files' peak. Consecutive records of a copy are neighbours along its rows, and
//! their canonical indexes (an order of voxels that keeps neighbours close) differ by small
//! amounts that repeat; as differences in byte planes they compress 3.6 to 87 times (on a
//! generated building of 6,964,850 surfels, about 3.2 bytes a surfel for the six files together
//! instead of 24).

use super::files::IoCounters;
use super::OocError;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

/// Values a frame holds (the last one of a file may hold fewer).
pub const FRAME_VALUES: usize = 1024;

const FRAME_BYTES: usize = 4 * FRAME_VALUES;

fn damaged(path: &Path, what: &str) -> OocError {
    OocError::io(
        path,
        "read",
        std::io::Error::new(std::io::ErrorKind::InvalidData, what.to_string()),
    )
}

/// Writes indexes, in order, into frames.
pub struct IndexWriter {
    path: PathBuf,
    out: BufWriter<File>,
    values: Vec<u32>,
    planes: Vec<u8>,
    packed: Vec<u8>,
    written: u64,
}

impl IndexWriter {
    /// A writer to `path`, through a buffer of `buffer_bytes`.
    pub fn create(path: &Path, buffer_bytes: usize) -> Result<Self, OocError> {
        let file = File::create(path).map_err(|e| OocError::io(path, "create", e))?;
        let bound = lz4::block::compress_bound(FRAME_BYTES).expect("a frame is small");
        Ok(IndexWriter {
            path: path.to_path_buf(),
            out: BufWriter::with_capacity(buffer_bytes.max(64), file),
            values: Vec::with_capacity(FRAME_VALUES),
            planes: vec![0; FRAME_BYTES],
            packed: vec![0; bound],
            written: 0,
        })
    }

    pub fn push(&mut self, value: u32) -> Result<(), OocError> {
        self.values.push(value);
        if self.values.len() == FRAME_VALUES {
            self.flush_frame()?;
        }
        Ok(())
    }

    fn flush_frame(&mut self) -> Result<(), OocError> {
        let n = self.values.len();
        let planes = &mut self.planes[..4 * n];
        let mut before = 0u32;
        for (k, &value) in self.values.iter().enumerate() {
            let bytes = value.wrapping_sub(before).to_le_bytes();
            for (b, &byte) in bytes.iter().enumerate() {
                planes[b * n + k] = byte;
            }
            before = value;
        }
        let fail = |e| OocError::io(&self.path, "compress", e);
        let len =
            lz4::block::compress_to_buffer(planes, None, false, &mut self.packed).map_err(fail)?;
        let mut write = |bytes: &[u8]| {
            self.written += bytes.len() as u64;
            self.out
                .write_all(bytes)
                .map_err(|e| OocError::io(&self.path, "write", e))
        };
        write(&(n as u32).to_le_bytes())?;
        write(&(len as u32).to_le_bytes())?;
        write(&self.packed[..len])?;
        self.values.clear();
        Ok(())
    }

    /// Writes the last frame, flushes and closes; returns the bytes written.
    pub fn finish(mut self) -> Result<u64, OocError> {
        if !self.values.is_empty() {
            self.flush_frame()?;
        }
        self.out
            .flush()
            .map_err(|e| OocError::io(&self.path, "write", e))?;
        Ok(self.written)
    }
}

/// Reads the indexes of a file written by [`IndexWriter`], in order.
pub struct IndexReader {
    path: PathBuf,
    input: BufReader<File>,
    values: Vec<u32>,
    next: usize,
    planes: Vec<u8>,
    packed: Vec<u8>,
    /// Bytes read from the file so far.
    read: u64,
}

impl IndexReader {
    /// Opens `path`, reading through a buffer of `buffer_bytes`.
    pub fn open(path: &Path, buffer_bytes: usize) -> Result<Self, OocError> {
        let file = File::open(path).map_err(|e| OocError::io(path, "open", e))?;
        Ok(IndexReader {
            path: path.to_path_buf(),
            input: BufReader::with_capacity(buffer_bytes.max(64), file),
            values: Vec::with_capacity(FRAME_VALUES),
            next: 0,
            planes: vec![0; FRAME_BYTES],
            packed: Vec::new(),
            read: 0,
        })
    }

    /// The next index, or `None` at the end of the file.
    pub fn next_value(&mut self) -> Result<Option<u32>, OocError> {
        if self.next == self.values.len() && !self.next_frame()? {
            return Ok(None);
        }
        self.next += 1;
        Ok(Some(self.values[self.next - 1]))
    }

    /// The next index, which must exist.
    pub fn expect_value(&mut self) -> Result<u32, OocError> {
        self.next_value()?
            .ok_or_else(|| damaged(&self.path, "work file ended early"))
    }

    /// Adds the bytes read from the file so far to `io` (once, when done with it).
    pub fn count_into(&self, io: &mut IoCounters) {
        io.read += self.read;
    }

    /// Decodes the next frame; `false` at the end of the file.
    fn next_frame(&mut self) -> Result<bool, OocError> {
        let mut header = [0u8; 8];
        // The file's end is where a frame would begin; a signal may interrupt the read.
        loop {
            match self.input.read(&mut header[..1]) {
                Ok(0) => return Ok(false),
                Ok(_) => break,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(OocError::io(&self.path, "read", e)),
            }
        }
        let fail = |e| OocError::io(&self.path, "read", e);
        self.input.read_exact(&mut header[1..]).map_err(fail)?;
        let word = |k: usize| u32::from_le_bytes(header[4 * k..4 * k + 4].try_into().expect("4"));
        let (n, len) = (word(0) as usize, word(1) as usize);
        let bound = lz4::block::compress_bound(FRAME_BYTES).expect("a frame is small");
        if n == 0 || n > FRAME_VALUES || len > bound {
            return Err(damaged(&self.path, "a frame of indexes has a wrong header"));
        }
        self.packed.resize(len, 0);
        self.input.read_exact(&mut self.packed).map_err(fail)?;
        self.read += (8 + len) as u64;
        let planes = &mut self.planes[..4 * n];
        let got = lz4::block::decompress_to_buffer(&self.packed, Some(4 * n as i32), planes)
            .map_err(|_| damaged(&self.path, "a frame of indexes does not decompress"))?;
        if got != 4 * n {
            return Err(damaged(&self.path, "a frame of indexes is short"));
        }
        self.values.clear();
        let mut value = 0u32;
        for k in 0..n {
            let difference = u32::from_le_bytes([
                planes[k],
                planes[n + k],
                planes[2 * n + k],
                planes[3 * n + k],
            ]);
            value = value.wrapping_add(difference);
            self.values.push(value);
        }
        self.next = 0;
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn indexes_come_back_in_order_and_compress() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ids.bin");
        // Frames full and one short; runs of steps, jumps both ways, the extremes.
        let count = 3 * FRAME_VALUES + 17;
        let value = |k: usize| match k % 500 {
            0 => u32::MAX,
            1 => 0,
            _ => (k as u32 / 3).wrapping_mul(7) ^ (k as u32 % 5),
        };
        let mut w = IndexWriter::create(&path, 4096).unwrap();
        for k in 0..count {
            w.push(value(k)).unwrap();
        }
        let written = w.finish().unwrap();
        assert_eq!(written, std::fs::metadata(&path).unwrap().len());
        assert!(written * 2 < 4 * count as u64, "{written} bytes");
        let mut r = IndexReader::open(&path, 100).unwrap();
        for k in 0..count {
            assert_eq!(r.expect_value().unwrap(), value(k), "{k}");
        }
        assert_eq!(r.next_value().unwrap(), None);
        assert!(r.expect_value().is_err());
        let mut io = IoCounters::default();
        r.count_into(&mut io);
        assert_eq!(io.read, written);
    }

    #[test]
    fn an_empty_file_holds_no_index_and_a_damaged_one_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ids.bin");
        IndexWriter::create(&path, 64).unwrap().finish().unwrap();
        assert_eq!(
            IndexReader::open(&path, 64).unwrap().next_value().unwrap(),
            None
        );
        let mut w = IndexWriter::create(&path, 64).unwrap();
        for k in 0..2 * FRAME_VALUES as u32 {
            w.push(k * k).unwrap();
        }
        w.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        // Cut short, and a header naming more values than a frame holds.
        std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
        let mut r = IndexReader::open(&path, 64).unwrap();
        let all: Result<Vec<_>, _> = (0..2 * FRAME_VALUES).map(|_| r.expect_value()).collect();
        assert!(all.is_err());
        let mut wrong = bytes.clone();
        wrong[..4].copy_from_slice(&(FRAME_VALUES as u32 + 1).to_le_bytes());
        std::fs::write(&path, &wrong).unwrap();
        assert!(IndexReader::open(&path, 64).unwrap().next_value().is_err());
    }
}

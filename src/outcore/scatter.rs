//! Permuting values that do not fit in memory: every value comes with the index it must land
//! at, and the permutation is done in two streaming passes.
//!
//! Pass one appends each `(target, value)` pair to the bucket file of its target's *chunk* (a
//! range of `chunk` consecutive targets); pass two hands each chunk's pairs to the caller, who
//! places them in an array of `chunk` entries and writes it out in order. Memory: one write
//! buffer per bucket during pass one, one chunk array (the caller's) and one read buffer during
//! pass two. The solver uses it to bring the light gathered in the three axis-sorted copies back
//! to canonical order and to send new radiosity to the copies, once per iteration.

use super::files::SeqWriter;
use super::OocError;
use std::path::{Path, PathBuf};

/// A permutation in progress of values of `W` bytes over `count` targets.
pub struct Scatter<const W: usize> {
    chunk: u64,
    count: u64,
    buckets: Vec<SeqWriter>,
    buffer_bytes: usize,
}

impl<const W: usize> Scatter<W> {
    /// A scatter over `count` targets in chunks of `chunk` targets, with bucket files named
    /// after `name` in `dir` and write buffers of `buffer_bytes` each.
    pub fn new(
        dir: &Path,
        name: &str,
        count: u64,
        chunk: u64,
        buffer_bytes: usize,
    ) -> Result<Self, OocError> {
        let chunk = chunk.max(1);
        let chunks = count.div_ceil(chunk);
        let mut buckets = Vec::with_capacity(chunks as usize);
        for c in 0..chunks {
            buckets.push(SeqWriter::create(
                &dir.join(format!("{name}-{c}.tmp")),
                buffer_bytes,
            )?);
        }
        Ok(Scatter {
            chunk,
            count,
            buckets,
            buffer_bytes,
        })
    }

    /// Number of chunks.
    pub fn chunks(&self) -> u64 {
        self.buckets.len() as u64
    }

    pub fn push(&mut self, target: u64, value: &[u8; W]) -> Result<(), OocError> {
        debug_assert!(target < self.count);
        let bucket = &mut self.buckets[(target / self.chunk) as usize];
        bucket.write(&target.to_le_bytes())?;
        bucket.write(value)
    }

    /// Ends pass one; the returned reader hands out the pairs chunk by chunk.
    pub fn into_chunks(self) -> Result<ChunkReader<W>, OocError> {
        let mut paths = Vec::with_capacity(self.buckets.len());
        let mut written = 0;
        for bucket in self.buckets {
            paths.push(bucket.path().to_path_buf());
            written += bucket.finish()?;
        }
        Ok(ChunkReader {
            paths,
            next: 0,
            chunk: self.chunk,
            count: self.count,
            buffer_bytes: self.buffer_bytes,
            written,
            read: 0,
        })
    }
}

/// Pass two of a [`Scatter`].
pub struct ChunkReader<const W: usize> {
    paths: Vec<PathBuf>,
    next: usize,
    chunk: u64,
    count: u64,
    buffer_bytes: usize,
    /// Bytes written to and read from the bucket files.
    pub written: u64,
    pub read: u64,
}

impl<const W: usize> ChunkReader<W> {
    /// Calls `place(offset_in_chunk, value)` for every pair of the next chunk and returns the
    /// chunk's `(start, len)`, or `None` after the last chunk.
    pub fn next_chunk<P>(&mut self, mut place: P) -> Result<Option<(u64, u64)>, OocError>
    where
        P: FnMut(usize, &[u8; W]),
    {
        let Some(path) = self.paths.get(self.next) else {
            return Ok(None);
        };
        let start = self.next as u64 * self.chunk;
        let len = self.chunk.min(self.count - start);
        self.read += read_pairs::<W, _>(path, self.buffer_bytes, |target, value| {
            if target < start || target >= start + len {
                return Err(OocError::io(
                    path,
                    "read",
                    std::io::Error::new(
                        std::io::ErrorKind::InvalidData,
                        "a work file holds a target outside its chunk",
                    ),
                ));
            }
            place((target - start) as usize, value);
            Ok(())
        })?;
        std::fs::remove_file(path).map_err(|e| OocError::io(path, "remove", e))?;
        self.next += 1;
        Ok(Some((start, len)))
    }
}

/// Reads a bucket file of `(u64 target, [u8; W])` pairs.
fn read_pairs<const W: usize, F>(
    path: &Path,
    buffer_bytes: usize,
    mut f: F,
) -> Result<u64, OocError>
where
    F: FnMut(u64, &[u8; W]) -> Result<(), OocError>,
{
    let mut read = 0;
    let len = std::fs::metadata(path)
        .map_err(|e| OocError::io(path, "read", e))?
        .len();
    let pairs = len / (8 + W as u64);
    let mut reader = PairReader::<W>::open(path, buffer_bytes)?;
    for _ in 0..pairs {
        let (target, value) = reader.next()?;
        f(target, &value)?;
        read += 8 + W as u64;
    }
    Ok(read)
}

/// Sequential reader of `(u64, [u8; W])` pairs.
struct PairReader<const W: usize> {
    path: PathBuf,
    input: std::io::BufReader<std::fs::File>,
}

impl<const W: usize> PairReader<W> {
    fn open(path: &Path, buffer_bytes: usize) -> Result<Self, OocError> {
        let file = std::fs::File::open(path).map_err(|e| OocError::io(path, "open", e))?;
        Ok(PairReader {
            path: path.to_path_buf(),
            input: std::io::BufReader::with_capacity(buffer_bytes.max(8 + W), file),
        })
    }

    fn next(&mut self) -> Result<(u64, [u8; W]), OocError> {
        use std::io::Read;
        let mut t = [0u8; 8];
        let mut v = [0u8; W];
        self.input
            .read_exact(&mut t)
            .and_then(|_| self.input.read_exact(&mut v))
            .map_err(|e| OocError::io(&self.path, "read", e))?;
        Ok((u64::from_le_bytes(t), v))
    }
}

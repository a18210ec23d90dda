//! A shard file: fixed-size surfel records sorted in one lexicographic order, between a header
//! and a footer.
//!
//! ```text
//! header (32 bytes)
//!   0  magic         8 bytes  "VXRSHRD\0"
//!   8  version       u32      1 (this build reads MIN_VERSION..=VERSION)
//!  12  order         u32      index (0..4) of the lexicographic order, see geometry::order
//!  16  record_len    u32      80 (storage::record::RECORD_LEN)
//!  20  reserved      u32      0
//!  24  count         u64      number of records
//! records (count x 80 bytes, layout in storage::record), sorted by order::sort_key(order, voxel),
//!   non-decreasing; surfels of one voxel are adjacent, in the order they were written
//! footer (20 bytes)
//!   0  count         u64      the header's count again
//!   8  crc32         u32      CRC-32 (IEEE) of every byte before the footer (header included)
//!  12  end magic     8 bytes  "VXRSEND\0"
//! ```
//!
//! Writing ([`ShardWriter`]): records stream into a temporary file beside the target; only
//! [`ShardWriter::finish`] (never `Drop`) writes the footer, patches the count into the header,
//! syncs and renames the file into place. So a file under a shard name is always complete, and
//! once there it is never modified: readers (and the memory maps of `window`) rely on that.
//! The writer refuses records out of order, so a shard cannot be written unsorted.
//!
//! Reading ([`ShardReader`]): `open` checks, in this order, the magic, the version against the
//! supported range, the lengths (file size against the header's count, the footer's count and end
//! marker) and the checksum; [`verify`] also checks that the records are sorted. Each failure is a
//! [`StorageError`] naming the file. `open_lazy` skips the checksum pass for a caller that will
//! stream every record once anyway: the record iterators hash what they read and report a
//! mismatch as their last item.

use super::record::{self, RECORD_LEN};
use super::StorageError;
use crate::geometry::order;
use crate::output::atomic;
use crate::output::results::read_up_to;
use crate::voxel::Surfel;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use tempfile::NamedTempFile;

pub const MAGIC: [u8; 8] = *b"VXRSHRD\0";
pub const END_MAGIC: [u8; 8] = *b"VXRSEND\0";
/// The version this build writes.
pub const VERSION: u32 = 1;
/// The oldest version this build reads.
pub const MIN_VERSION: u32 = 1;
pub const HEADER_LEN: u64 = 32;
pub const FOOTER_LEN: u64 = 20;
/// Number of lexicographic orders (see `geometry::order`).
pub const ORDERS: usize = 4;

const KIND: &str = "shard file";

/// A temporary file beside `path` (see `output::atomic`) that others may read once renamed into
/// place. `tempfile` creates files readable by their owner only, which is right for secrets but
/// wrong for a shard set that other users, or ranks running under another account, must read.
pub(crate) fn temp_beside_shared(path: &Path) -> Result<NamedTempFile, StorageError> {
    // `atomic::temp_beside` already makes the file readable by all.
    Ok(atomic::temp_beside(path)?)
}

/// Byte offset of record `index` in a shard file.
pub fn record_offset(index: u64) -> u64 {
    HEADER_LEN + index * RECORD_LEN as u64
}

/// Total size in bytes of a shard file holding `count` records, or `None` if it cannot exist.
pub fn file_len(count: u64) -> Option<u64> {
    count
        .checked_mul(RECORD_LEN as u64)
        .and_then(|r| r.checked_add(HEADER_LEN + FOOTER_LEN))
}

/// The key shard records are sorted by.
#[inline]
pub fn key(order: usize, s: &Surfel) -> (i64, i64, i64) {
    order::sort_key(order, s.voxel)
}

/// The decoded header of a shard file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ShardHeader {
    pub version: u32,
    pub order: usize,
    pub count: u64,
}

impl ShardHeader {
    fn encode(&self) -> [u8; HEADER_LEN as usize] {
        let mut h = [0u8; HEADER_LEN as usize];
        h[0..8].copy_from_slice(&MAGIC);
        h[8..12].copy_from_slice(&self.version.to_le_bytes());
        h[12..16].copy_from_slice(&(self.order as u32).to_le_bytes());
        h[16..20].copy_from_slice(&(RECORD_LEN as u32).to_le_bytes());
        // 20..24 reserved, zero.
        h[24..32].copy_from_slice(&self.count.to_le_bytes());
        h
    }
}

/// What a finished or opened shard file holds: enough to list it in a manifest.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ShardInfo {
    pub path: PathBuf,
    pub order: usize,
    pub count: u64,
    /// Size of the whole file in bytes.
    pub bytes: u64,
    /// The footer's checksum: CRC-32 of every byte before the footer.
    pub crc32: u32,
}

/// How a [`ShardWriter`] writes.
#[derive(Clone, Copy, Debug)]
pub struct WriteOptions {
    /// Size of the write buffer: the writer's whole memory use.
    pub buffer_bytes: usize,
    /// Sync the file (and its directory) before the rename. Off only for scratch files whose
    /// loss in a crash does not matter, such as the runs of an external sort.
    pub sync: bool,
}

impl Default for WriteOptions {
    fn default() -> Self {
        WriteOptions {
            buffer_bytes: 1 << 20,
            sync: true,
        }
    }
}

/// Streams sorted records into a new shard file (see the module header). Dropping it before
/// [`ShardWriter::finish`] deletes the temporary file and leaves nothing under the real name.
pub struct ShardWriter {
    path: PathBuf,
    order: usize,
    sync: bool,
    out: BufWriter<NamedTempFile>,
    /// CRC of the records only: the header's count is not known until `finish`, so the header's
    /// CRC is computed then and combined in front.
    body_hasher: crc32fast::Hasher,
    count: u64,
    last: Option<[i32; 3]>,
}

impl ShardWriter {
    /// Starts a shard of order `order` (0..4) that will appear at `path` on `finish`.
    pub fn create(path: &Path, order: usize) -> Result<Self, StorageError> {
        Self::create_with(path, order, WriteOptions::default())
    }

    pub fn create_with(
        path: &Path,
        order: usize,
        options: WriteOptions,
    ) -> Result<Self, StorageError> {
        if order >= ORDERS {
            return Err(StorageError::invalid(
                path,
                format!("order {order} does not exist (there are {ORDERS})"),
            ));
        }
        let tmp = temp_beside_shared(path)?;
        let mut out = BufWriter::with_capacity(options.buffer_bytes.max(1), tmp);
        // A placeholder header, patched in `finish`; an unfinished file has count 0 and no footer,
        // so it can never pass for a valid shard.
        let placeholder = ShardHeader {
            version: VERSION,
            order,
            count: 0,
        };
        out.write_all(&placeholder.encode())
            .map_err(|e| StorageError::io(path, "write", e))?;
        Ok(ShardWriter {
            path: path.to_path_buf(),
            order,
            sync: options.sync,
            out,
            body_hasher: crc32fast::Hasher::new(),
            count: 0,
            last: None,
        })
    }

    /// Appends one record; it must not sort before the previous one.
    pub fn push(&mut self, s: &Surfel) -> Result<(), StorageError> {
        if let Some(previous) = self.last {
            if order::sort_key(self.order, previous) > key(self.order, s) {
                return Err(StorageError::Unsorted {
                    path: self.path.clone(),
                    order: self.order as u32,
                    index: self.count,
                    voxel: s.voxel,
                    previous,
                });
            }
        }
        let bytes = record::encode(s);
        self.body_hasher.update(&bytes);
        self.out
            .write_all(&bytes)
            .map_err(|e| StorageError::io(&self.path, "write", e))?;
        self.count += 1;
        self.last = Some(s.voxel);
        Ok(())
    }

    /// Number of records pushed so far.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Writes the footer and the final header, syncs, and renames the file into place.
    pub fn finish(self) -> Result<ShardInfo, StorageError> {
        let ShardWriter {
            path,
            order,
            sync,
            mut out,
            body_hasher,
            count,
            ..
        } = self;
        let io = |e| StorageError::io(&path, "write", e);
        let header = ShardHeader {
            version: VERSION,
            order,
            count,
        }
        .encode();
        let mut hasher = crc32fast::Hasher::new();
        hasher.update(&header);
        hasher.combine(&body_hasher);
        let crc32 = hasher.finalize();
        let mut footer = [0u8; FOOTER_LEN as usize];
        footer[0..8].copy_from_slice(&count.to_le_bytes());
        footer[8..12].copy_from_slice(&crc32.to_le_bytes());
        footer[12..20].copy_from_slice(&END_MAGIC);
        out.write_all(&footer).map_err(io)?;
        let mut tmp = out.into_inner().map_err(|e| io(e.into_error()))?;
        tmp.seek(SeekFrom::Start(0)).map_err(io)?;
        tmp.write_all(&header).map_err(io)?;
        if sync {
            atomic::commit(tmp, &path)?;
        } else {
            tmp.persist(&path).map_err(|e| io(e.error))?;
        }
        Ok(ShardInfo {
            path,
            order,
            count,
            bytes: file_len(count).unwrap_or(u64::MAX),
            crc32,
        })
    }
}

/// An opened shard file whose structure has been checked (see the module header).
#[derive(Clone, Debug)]
pub struct ShardReader {
    info: ShardInfo,
    header: ShardHeader,
    header_bytes: [u8; HEADER_LEN as usize],
}

impl ShardReader {
    /// Opens `path` and checks magic, version, lengths and checksum, in that order.
    pub fn open(path: &Path) -> Result<Self, StorageError> {
        let reader = Self::open_lazy(path)?;
        reader.check_checksum()?;
        Ok(reader)
    }

    /// Opens `path` and checks magic, version and lengths, but not the checksum: for callers that
    /// stream every record once and so get the checksum checked at the end (see [`ShardRecords`]).
    pub fn open_lazy(path: &Path) -> Result<Self, StorageError> {
        let io = |e| StorageError::io(path, "read", e);
        let bad_length = |what: String| StorageError::BadLength {
            path: path.to_path_buf(),
            what,
        };
        let mut file = File::open(path).map_err(io)?;
        let len = file.metadata().map_err(io)?.len();

        // Read as much of the header as exists, so a short file still gets its magic checked first.
        let mut h = [0u8; HEADER_LEN as usize];
        let got = read_up_to(&mut file, &mut h).map_err(io)?;
        if got < MAGIC.len() || h[..8] != MAGIC {
            return Err(StorageError::BadMagic {
                path: path.to_path_buf(),
                kind: KIND,
                found: h[..got.min(8)].to_vec(),
                expected: MAGIC.to_vec(),
            });
        }
        if got < 12 {
            return Err(bad_length(format!(
                "{len} bytes, shorter than the {HEADER_LEN}-byte header"
            )));
        }
        let version = u32_at(&h, 8);
        if !(MIN_VERSION..=VERSION).contains(&version) {
            return Err(StorageError::UnsupportedVersion {
                path: path.to_path_buf(),
                kind: KIND,
                found: version,
                min: MIN_VERSION,
                max: VERSION,
            });
        }
        if got < HEADER_LEN as usize {
            return Err(bad_length(format!(
                "{len} bytes, shorter than the {HEADER_LEN}-byte header"
            )));
        }
        let order = u32_at(&h, 12);
        let record_len = u32_at(&h, 16);
        let bad_header = |what: String| StorageError::BadHeader {
            path: path.to_path_buf(),
            what,
        };
        if order as usize >= ORDERS {
            return Err(bad_header(format!(
                "order {order}, but only 0 to {} exist",
                ORDERS - 1
            )));
        }
        if record_len as usize != RECORD_LEN {
            return Err(bad_header(format!(
                "record length {record_len}, expected {RECORD_LEN}"
            )));
        }
        let count = u64_at(&h, 24);
        let expected = file_len(count);
        if expected != Some(len) {
            return Err(bad_length(format!(
                "the header announces {count} records ({} bytes in all) but the file has {len} \
                 bytes",
                expected.map_or_else(|| "an impossible number of".to_string(), |e| e.to_string())
            )));
        }
        file.seek(SeekFrom::Start(len - FOOTER_LEN)).map_err(io)?;
        let mut footer = [0u8; FOOTER_LEN as usize];
        file.read_exact(&mut footer).map_err(io)?;
        if footer[12..] != END_MAGIC {
            return Err(bad_length(
                "the footer's end marker is missing (the file was not finished)".to_string(),
            ));
        }
        let footer_count = u64_at(&footer, 0);
        if footer_count != count {
            return Err(bad_length(format!(
                "the header announces {count} records but the footer {footer_count}"
            )));
        }
        let header = ShardHeader {
            version,
            order: order as usize,
            count,
        };
        Ok(ShardReader {
            info: ShardInfo {
                path: path.to_path_buf(),
                order: order as usize,
                count,
                bytes: len,
                crc32: u32_at(&footer, 8),
            },
            header,
            header_bytes: h,
        })
    }

    pub fn info(&self) -> &ShardInfo {
        &self.info
    }

    pub fn header(&self) -> &ShardHeader {
        &self.header
    }

    pub fn path(&self) -> &Path {
        &self.info.path
    }

    /// The raw header bytes, where the checksum starts.
    pub(crate) fn header_bytes(&self) -> &[u8; HEADER_LEN as usize] {
        &self.header_bytes
    }

    /// Reads the whole file once (through a 64 KiB buffer) and compares its checksum with the
    /// footer's.
    pub fn check_checksum(&self) -> Result<(), StorageError> {
        let path = self.path();
        let io = |e| StorageError::io(path, "read", e);
        let mut file = File::open(path).map_err(io)?;
        let mut remaining = self.info.bytes - FOOTER_LEN;
        let mut hasher = crc32fast::Hasher::new();
        let mut buf = vec![0u8; 64 << 10];
        while remaining > 0 {
            let n = remaining.min(buf.len() as u64) as usize;
            file.read_exact(&mut buf[..n]).map_err(io)?;
            hasher.update(&buf[..n]);
            remaining -= n as u64;
        }
        self.compare_checksum(hasher.finalize())
    }

    pub(crate) fn compare_checksum(&self, computed: u32) -> Result<(), StorageError> {
        if computed == self.info.crc32 {
            Ok(())
        } else {
            Err(StorageError::ChecksumMismatch {
                path: self.info.path.clone(),
                stored: self.info.crc32,
                computed,
            })
        }
    }

    /// The records in file order through a read buffer of `buffer_bytes` (at least one record),
    /// the checksum checked at the end.
    pub fn records(&self, buffer_bytes: usize) -> Result<ShardRecords, StorageError> {
        let path = self.path();
        let mut file = File::open(path).map_err(|e| StorageError::io(path, "read", e))?;
        file.seek(SeekFrom::Start(HEADER_LEN))
            .map_err(|e| StorageError::io(path, "read", e))?;
        let mut hasher = crc32fast::Hasher::new();
        hasher.update(&self.header_bytes);
        Ok(ShardRecords {
            reader: self.clone(),
            file: BufReader::with_capacity(buffer_bytes.max(RECORD_LEN), file),
            hasher,
            next: 0,
            done: false,
        })
    }
}

/// Iterator over a shard's records by buffered reads (see [`ShardReader::records`]). Yields an
/// error and stops on a read failure; after the last record, yields a
/// [`StorageError::ChecksumMismatch`] if the bytes read do not match the footer, so a consumer
/// must treat everything it took from the iterator as unreliable if the last item is an error.
pub struct ShardRecords {
    reader: ShardReader,
    file: BufReader<File>,
    hasher: crc32fast::Hasher,
    next: u64,
    done: bool,
}

impl Iterator for ShardRecords {
    type Item = Result<Surfel, StorageError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        if self.next == self.reader.info.count {
            self.done = true;
            let computed = self.hasher.clone().finalize();
            return self.reader.compare_checksum(computed).err().map(Err);
        }
        let mut buf = [0u8; RECORD_LEN];
        if let Err(e) = self.file.read_exact(&mut buf) {
            self.done = true;
            return Some(Err(StorageError::io(self.reader.path(), "read", e)));
        }
        self.hasher.update(&buf);
        self.next += 1;
        Some(Ok(record::decode(&buf)))
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = (self.reader.info.count - self.next) as usize;
        (left, Some(left + 1))
    }
}

/// Checks a whole shard file: magic, version, lengths, checksum, then that its records are
/// sorted in its order. Reads the file once.
pub fn verify(path: &Path) -> Result<ShardInfo, StorageError> {
    let reader = ShardReader::open_lazy(path)?;
    let order = reader.header.order;
    // Remember the first unsorted pair but keep reading: a checksum failure is the more basic
    // fault and is reported first.
    let mut unsorted = None;
    let mut previous: Option<[i32; 3]> = None;
    for (index, s) in reader.records(256 << 10)?.enumerate() {
        let s = s?;
        if let Some(p) = previous {
            if unsorted.is_none() && order::sort_key(order, p) > key(order, &s) {
                unsorted = Some(StorageError::Unsorted {
                    path: path.to_path_buf(),
                    order: order as u32,
                    index: index as u64,
                    voxel: s.voxel,
                    previous: p,
                });
            }
        }
        previous = Some(s.voxel);
    }
    match unsorted {
        Some(e) => Err(e),
        None => Ok(reader.info),
    }
}

fn u32_at(b: &[u8], i: usize) -> u32 {
    u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]])
}

fn u64_at(b: &[u8], i: usize) -> u64 {
    let mut w = [0u8; 8];
    w.copy_from_slice(&b[i..i + 8]);
    u64::from_le_bytes(w)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::storage::record::tests::{random_surfel, SplitMix};

    /// `n` seeded random surfels sorted in `order` (stable, so equal voxels keep their order).
    pub(crate) fn sorted_surfels(n: usize, order: usize, seed: u64) -> Vec<Surfel> {
        let mut rng = SplitMix(seed);
        let mut v: Vec<Surfel> = (0..n).map(|_| random_surfel(&mut rng, 6)).collect();
        v.sort_by_key(|s| key(order, s));
        v
    }

    pub(crate) fn write_shard(path: &Path, order: usize, surfels: &[Surfel]) -> ShardInfo {
        let mut w = ShardWriter::create(path, order).unwrap();
        for s in surfels {
            w.push(s).unwrap();
        }
        w.finish().unwrap()
    }

    fn written(n: usize) -> (tempfile::TempDir, PathBuf, Vec<Surfel>) {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("shard-0.vxs");
        let surfels = sorted_surfels(n, 2, 11);
        write_shard(&path, 2, &surfels);
        (dir, path, surfels)
    }

    fn read_all(path: &Path) -> Result<Vec<Surfel>, StorageError> {
        ShardReader::open(path)?.records(1000)?.collect()
    }

    fn corrupt(path: &Path, f: impl FnOnce(&mut Vec<u8>)) {
        let mut bytes = std::fs::read(path).unwrap();
        f(&mut bytes);
        std::fs::write(path, bytes).unwrap();
    }

    fn names_file(e: &StorageError, path: &Path) {
        assert_eq!(e.path(), Some(path));
        assert!(e.to_string().contains(&path.display().to_string()), "{e}");
    }

    #[test]
    fn round_trip() {
        let (dir, path, surfels) = written(100);
        let info = verify(&path).unwrap();
        assert_eq!(info.count, 100);
        assert_eq!(info.order, 2);
        assert_eq!(info.bytes, HEADER_LEN + 100 * 80 + FOOTER_LEN);
        assert_eq!(std::fs::metadata(&path).unwrap().len(), info.bytes);
        assert_eq!(read_all(&path).unwrap(), surfels);
        // Only the finished file is left: no temporary beside it.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(&path).unwrap().permissions().mode();
            assert_eq!(mode & 0o777, 0o644, "readable by all, like any data file");
        }
    }

    #[test]
    fn empty_shard_is_valid() {
        let (_dir, path, _) = written(0);
        assert_eq!(verify(&path).unwrap().count, 0);
        assert!(read_all(&path).unwrap().is_empty());
    }

    #[test]
    fn flipped_byte_is_a_checksum_error() {
        let (_dir, path, _) = written(50);
        // In a record's float, so the structure stays valid and only the checksum can tell.
        corrupt(&path, |b| b[HEADER_LEN as usize + 7 * 80 + 14] ^= 0x10);
        for e in [
            ShardReader::open(&path).unwrap_err(),
            verify(&path).unwrap_err(),
            read_all(&path).unwrap_err(),
        ] {
            assert!(matches!(e, StorageError::ChecksumMismatch { .. }), "{e}");
            names_file(&e, &path);
        }
        // The lazy open does not read the records; the iterator reports it at the end.
        let items: Vec<_> = ShardReader::open_lazy(&path)
            .unwrap()
            .records(80)
            .unwrap()
            .collect();
        assert_eq!(items.len(), 51);
        assert!(matches!(
            items.last(),
            Some(Err(StorageError::ChecksumMismatch { .. }))
        ));
    }

    #[test]
    fn truncation_is_a_length_error() {
        let (_dir, path, _) = written(50);
        corrupt(&path, |b| b.truncate(b.len() - 30));
        let e = ShardReader::open(&path).unwrap_err();
        assert!(matches!(e, StorageError::BadLength { .. }), "{e}");
        names_file(&e, &path);
        // A truncation that happens to remove whole records plus the footer.
        let (_dir, path, _) = written(50);
        corrupt(&path, |b| b.truncate(HEADER_LEN as usize + 10 * 80));
        let e = ShardReader::open(&path).unwrap_err();
        assert!(matches!(e, StorageError::BadLength { .. }), "{e}");
        // Cut inside the header.
        corrupt(&path, |b| b.truncate(20));
        let e = verify(&path).unwrap_err();
        assert!(matches!(e, StorageError::BadLength { .. }), "{e}");
    }

    #[test]
    fn wrong_magic_is_reported_first() {
        let (_dir, path, _) = written(5);
        corrupt(&path, |b| {
            b[1] = b'Y';
            b[8] = 99; // a bad version too: the magic is checked first
            b.truncate(100); // and a bad length
        });
        let e = verify(&path).unwrap_err();
        assert!(matches!(e, StorageError::BadMagic { .. }), "{e}");
        names_file(&e, &path);
        std::fs::write(&path, b"VX").unwrap();
        let e = ShardReader::open(&path).unwrap_err();
        assert!(matches!(e, StorageError::BadMagic { .. }), "{e}");
    }

    #[test]
    fn future_version_is_reported_before_lengths_and_checksum() {
        let (_dir, path, _) = written(5);
        corrupt(&path, |b| {
            b[8..12].copy_from_slice(&(VERSION + 1).to_le_bytes());
            b.truncate(b.len() - 1);
        });
        let e = verify(&path).unwrap_err();
        match &e {
            StorageError::UnsupportedVersion { found, .. } => assert_eq!(*found, VERSION + 1),
            other => panic!("{other}"),
        }
        names_file(&e, &path);
        assert!(e.to_string().contains("versions 1 to 1"), "{e}");
    }

    /// Swaps two records whose keys differ and repairs the checksum, so that only the order is
    /// wrong: what a buggy writer elsewhere would produce.
    #[test]
    fn unsorted_records_are_found_by_verify() {
        let (_dir, path, surfels) = written(40);
        let (i, j) = (3, 30);
        assert_ne!(key(2, &surfels[i]), key(2, &surfels[j]));
        corrupt(&path, |b| {
            let at = |k: usize| HEADER_LEN as usize + k * RECORD_LEN;
            let ri = b[at(i)..at(i + 1)].to_vec();
            let rj = b[at(j)..at(j + 1)].to_vec();
            b[at(i)..at(i + 1)].copy_from_slice(&rj);
            b[at(j)..at(j + 1)].copy_from_slice(&ri);
            let body = b.len() - FOOTER_LEN as usize;
            let crc = crc32fast::hash(&b[..body]);
            b[body + 8..body + 12].copy_from_slice(&crc.to_le_bytes());
        });
        // Structurally sound: open (which does not check order) accepts it.
        ShardReader::open(&path).unwrap();
        let e = verify(&path).unwrap_err();
        match &e {
            StorageError::Unsorted { index, .. } => assert!(*index <= j as u64, "{e}"),
            other => panic!("{other}"),
        }
        names_file(&e, &path);
    }

    #[test]
    fn writer_refuses_unsorted_records_and_leaves_nothing() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("s.vxs");
        let surfels = sorted_surfels(10, 0, 3);
        let (lo, hi) = (surfels[0], surfels[9]);
        assert!(key(0, &lo) < key(0, &hi));
        let mut w = ShardWriter::create(&path, 0).unwrap();
        w.push(&hi).unwrap();
        let e = w.push(&lo).unwrap_err();
        assert!(matches!(e, StorageError::Unsorted { .. }), "{e}");
        drop(w);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        assert!(ShardWriter::create(&path, 4).is_err());
    }

    #[test]
    fn missing_file_names_it() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("absent.vxs");
        let e = ShardReader::open(&path).unwrap_err();
        assert!(matches!(e, StorageError::Io { .. }));
        names_file(&e, &path);
    }
}

//! The per-voxel results file, `surfels.bin`: every surfel with its radiosity on both sides and
//! the materials of its sides, so that a reader can tell the light arriving (irradiance) from the
//! light leaving.
//!
//! Binary, little-endian, fixed-size records so a reader can check the length from the header
//! alone and seek to record `k` at `HEADER_LEN + k * RECORD_LEN`.
//!
//! ```text
//! header (72 bytes)
//!   0  magic         8 bytes  "VXRSURF\0"
//!   8  version       u32      2 (1: records of 64 bytes without materials, still read)
//!  12  record_len    u32      96
//!  16  count         u64      number of records
//!  24  grid.origin   f64 x 3  world position of voxel (0,0,0)'s low corner
//!  48  grid.voxel_size f64
//!  56  grid.dims     u32 x 3
//!  68  materials     u32      number of entries of the material table (version 1: 0)
//! records (count x 96 bytes), in the solver's surfel order
//!   0  voxel         i32 x 3  integer voxel coordinates
//!  12  point         f32 x 3  surface point inside the voxel, voxel units in [0, 1]
//!                             (world = origin + (voxel + point) * voxel_size; kept relative so
//!                             huge scenes do not lose precision to f32)
//!  24  normal        f32 x 3  unit normal of the front side
//!  36  area          f32      surface area inside the voxel, in voxel_size^2 (0: only touched)
//!  40  B front       f32 x 3  radiosity of side 0 (facing along normal), RGB, units of Ke
//!  52  B back        f32 x 3  radiosity of side 1 (facing along -normal)
//!  64  material      u32 x 2  entry of the material table of the front and the back side
//!  72  extent        f32 x 6  bounding box of the surface piece inside the voxel (low corner,
//!                             high corner; voxel units relative to the voxel's low corner)
//! material table (materials x 48 bytes)
//!   0  reflectance   f64 x 3  rho, RGB (MTL Kd)
//!  24  emission      f64 x 3  E, RGB (MTL Ke), leaving the side that has this material
//! footer (20 bytes)
//!   0  count         u64      the header's count again
//!   8  crc32         u32      CRC-32 (IEEE) of every byte before the footer
//!  12  end magic     8 bytes  "VXREND\0\0"
//! ```
//!
//! A file is written to a temporary name and renamed only by [`ResultsWriter::finish`], after
//! the footer is written and synced, so a file under the real name is always complete. The reader
//! checks, in order: magic, version (and record length), file length against the header's count
//! and material count (and the footer), checksum, and that every record names a material of the
//! table; each error names the file and what is wrong.

use super::{atomic, check_pair, OutputError};
use crate::solve::Solution;
use crate::voxel::{Grid, Surfel, SurfelSet, BACK, FRONT};
use glam::DVec3;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use tempfile::NamedTempFile;

pub const MAGIC: [u8; 8] = *b"VXRSURF\0";
pub const END_MAGIC: [u8; 8] = *b"VXREND\0\0";
pub const VERSION: u32 = 2;
pub const HEADER_LEN: u64 = 72;
pub const RECORD_LEN: u64 = 96;
pub const FOOTER_LEN: u64 = 20;
/// Records of version 1 files (no materials).
pub const RECORD_LEN_V1: u64 = 64;
/// Bytes of one entry of the material table.
pub const MATERIAL_LEN: u64 = 48;
/// Material index of a record read from a version 1 file (no table).
pub const NO_MATERIAL: u32 = u32::MAX;

/// What the results file keeps of a material: enough to tell irradiance from radiosity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SideMaterial {
    /// `rho` per channel.
    pub reflectance: [f64; 3],
    /// `E` per channel.
    pub emission: [f64; 3],
}

impl SideMaterial {
    pub fn of(m: &crate::scene::Material) -> Self {
        SideMaterial {
            reflectance: m.reflectance,
            emission: m.emission,
        }
    }
}

/// One surfel and its radiosity, as stored.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Record {
    pub voxel: [i32; 3],
    pub point: [f32; 3],
    pub normal: [f32; 3],
    pub area: f32,
    /// `radiosity[side][channel]`, side `FRONT` or `BACK`.
    pub radiosity: [[f32; 3]; 2],
    /// Index into [`Results::materials`] of each side's material ([`NO_MATERIAL`] when read from
    /// a version 1 file).
    pub material: [u32; 2],
    /// Bounding box of the surface piece in its voxel (see `Surfel::extent`; the whole voxel
    /// when read from a version 1 file).
    pub extent: [[f32; 3]; 2],
}

impl Record {
    pub fn from_surfel(s: &Surfel, radiosity: [[f32; 3]; 2]) -> Self {
        Record {
            voxel: s.voxel,
            point: s.point,
            normal: s.normal,
            area: s.area,
            radiosity,
            material: s.material,
            extent: s.extent,
        }
    }

    /// Surface point in voxel units (absolute).
    pub fn position(&self) -> DVec3 {
        crate::voxel::absolute_position(self.voxel, self.point)
    }

    /// Unit normal of side `side` (`FRONT` or `BACK`).
    pub fn side_normal(&self, side: usize) -> DVec3 {
        crate::voxel::oriented_normal(self.normal, side)
    }

    /// Whether side `side` is worth exporting: it has surface, or it carries light.
    pub fn side_is_present(&self, side: usize) -> bool {
        self.area > 0.0 || self.radiosity[side].iter().any(|&b| b != 0.0)
    }

    fn encode(&self) -> [u8; RECORD_LEN as usize] {
        let mut b = [0u8; RECORD_LEN as usize];
        let mut at = 0;
        let mut put = |bytes: [u8; 4]| {
            b[at..at + 4].copy_from_slice(&bytes);
            at += 4;
        };
        self.voxel.iter().for_each(|v| put(v.to_le_bytes()));
        self.point.iter().for_each(|v| put(v.to_le_bytes()));
        self.normal.iter().for_each(|v| put(v.to_le_bytes()));
        put(self.area.to_le_bytes());
        self.radiosity
            .iter()
            .flatten()
            .for_each(|v| put(v.to_le_bytes()));
        self.material.iter().for_each(|v| put(v.to_le_bytes()));
        self.extent
            .iter()
            .flatten()
            .for_each(|v| put(v.to_le_bytes()));
        b
    }

    /// A record of `b`, which holds 96 bytes (version 2) or 64 (version 1, no materials).
    fn decode(b: &[u8]) -> Self {
        let word = |i: usize| [b[4 * i], b[4 * i + 1], b[4 * i + 2], b[4 * i + 3]];
        let f = |i: usize| f32::from_le_bytes(word(i));
        Record {
            voxel: [0, 1, 2].map(|i| i32::from_le_bytes(word(i))),
            point: [f(3), f(4), f(5)],
            normal: [f(6), f(7), f(8)],
            area: f(9),
            radiosity: [[f(10), f(11), f(12)], [f(13), f(14), f(15)]],
            material: if b.len() >= RECORD_LEN as usize {
                [16, 17].map(|i| u32::from_le_bytes(word(i)))
            } else {
                [NO_MATERIAL; 2]
            },
            extent: if b.len() >= RECORD_LEN as usize {
                [[f(18), f(19), f(20)], [f(21), f(22), f(23)]]
            } else {
                [[0.0; 3], [1.0; 3]]
            },
        }
    }

    /// The irradiance `H` arriving on side `side` (the light it reflects is `rho H`, so
    /// `H = (B - E) / rho`), by channel, from the side's material in `materials`; `None` for a
    /// channel whose reflectance is 0 (nothing tells what arrives there) and for a record without
    /// materials.
    pub fn irradiance(&self, side: usize, materials: &[SideMaterial]) -> [Option<f64>; 3] {
        let Some(m) = materials.get(self.material[side] as usize) else {
            return [None; 3];
        };
        std::array::from_fn(|ch| {
            let rho = m.reflectance[ch];
            // `E` as the solver stored it (f32), so that a surface lit by nothing reads 0.
            let e = m.emission[ch] as f32 as f64;
            (rho > 0.0).then(|| (self.radiosity[side][ch] as f64 - e) / rho)
        })
    }
}

/// A whole results file in memory.
#[derive(Clone, Debug, PartialEq)]
pub struct Results {
    pub grid: Grid,
    pub records: Vec<Record>,
    /// The materials the records' sides name (empty for a version 1 file).
    pub materials: Vec<SideMaterial>,
}

impl Results {
    /// The records of a solve, without going through a file.
    pub fn from_solution(set: &SurfelSet, solution: &Solution) -> Result<Results, OutputError> {
        check_pair(Path::new("<results>"), set, solution)?;
        Ok(Results {
            grid: set.grid,
            records: set
                .surfels
                .iter()
                .zip(&solution.radiosity)
                .map(|(s, b)| Record::from_surfel(s, *b))
                .collect(),
            materials: set.materials.iter().map(SideMaterial::of).collect(),
        })
    }

    /// World position of record `r`'s surface point.
    pub fn world_position(&self, r: &Record) -> DVec3 {
        self.grid.to_world(r.position())
    }
}

fn encode_header(grid: &Grid, count: u64, materials: u32) -> [u8; HEADER_LEN as usize] {
    let mut h = Vec::with_capacity(HEADER_LEN as usize);
    h.extend_from_slice(&MAGIC);
    h.extend_from_slice(&VERSION.to_le_bytes());
    h.extend_from_slice(&(RECORD_LEN as u32).to_le_bytes());
    h.extend_from_slice(&count.to_le_bytes());
    grid.origin
        .iter()
        .for_each(|v| h.extend_from_slice(&v.to_le_bytes()));
    h.extend_from_slice(&grid.voxel_size.to_le_bytes());
    grid.dims
        .iter()
        .for_each(|v| h.extend_from_slice(&v.to_le_bytes()));
    h.extend_from_slice(&materials.to_le_bytes());
    let mut out = [0u8; HEADER_LEN as usize];
    out.copy_from_slice(&h);
    out
}

/// Streams records into a results file. Nothing appears under the real name until
/// [`ResultsWriter::finish`] succeeds; dropping the writer earlier deletes the temporary file.
pub struct ResultsWriter {
    path: PathBuf,
    out: BufWriter<NamedTempFile>,
    hasher: crc32fast::Hasher,
    declared: u64,
    written: u64,
    materials: Vec<SideMaterial>,
}

impl ResultsWriter {
    /// Starts a file that will hold exactly `count` records whose sides name entries of
    /// `materials`.
    pub fn create(
        path: &Path,
        grid: &Grid,
        count: u64,
        materials: &[crate::scene::Material],
    ) -> Result<Self, OutputError> {
        let table_len = u32::try_from(materials.len()).map_err(|_| {
            OutputError::invalid(path, format!("{} materials is too many", materials.len()))
        })?;
        let tmp = atomic::temp_beside(path)?;
        let mut w = ResultsWriter {
            path: path.to_path_buf(),
            out: BufWriter::with_capacity(1 << 20, tmp),
            hasher: crc32fast::Hasher::new(),
            declared: count,
            written: 0,
            materials: materials.iter().map(SideMaterial::of).collect(),
        };
        w.put(&encode_header(grid, count, table_len))?;
        Ok(w)
    }

    fn put(&mut self, bytes: &[u8]) -> Result<(), OutputError> {
        self.hasher.update(bytes);
        self.out
            .write_all(bytes)
            .map_err(|e| OutputError::io(&self.path, e))
    }

    pub fn push(&mut self, record: &Record) -> Result<(), OutputError> {
        if self.written == self.declared {
            return Err(OutputError::invalid(
                &self.path,
                format!("more records than the {} declared", self.declared),
            ));
        }
        if let Some(&m) = record
            .material
            .iter()
            .find(|&&m| m as usize >= self.materials.len())
        {
            return Err(OutputError::invalid(
                &self.path,
                format!("a surfel names material {m} of {}", self.materials.len()),
            ));
        }
        self.put(&record.encode())?;
        self.written += 1;
        Ok(())
    }

    /// Writes the footer, syncs and renames the file into place.
    pub fn finish(mut self) -> Result<(), OutputError> {
        if self.written != self.declared {
            return Err(OutputError::invalid(
                &self.path,
                format!(
                    "{} records declared but only {} written",
                    self.declared, self.written
                ),
            ));
        }
        let table = encode_materials(&self.materials);
        self.put(&table)?;
        let crc = self.hasher.clone().finalize();
        let mut footer = Vec::with_capacity(FOOTER_LEN as usize);
        footer.extend_from_slice(&self.written.to_le_bytes());
        footer.extend_from_slice(&crc.to_le_bytes());
        footer.extend_from_slice(&END_MAGIC);
        let path = self.path;
        self.out
            .write_all(&footer)
            .map_err(|e| OutputError::io(&path, e))?;
        let tmp = self
            .out
            .into_inner()
            .map_err(|e| OutputError::io(&path, e.into_error()))?;
        atomic::commit(tmp, &path)
    }
}

fn encode_materials(materials: &[SideMaterial]) -> Vec<u8> {
    let mut table = Vec::with_capacity(materials.len() * MATERIAL_LEN as usize);
    for m in materials {
        for v in m.reflectance.iter().chain(&m.emission) {
            table.extend_from_slice(&v.to_le_bytes());
        }
    }
    table
}

fn decode_materials(bytes: &[u8]) -> Vec<SideMaterial> {
    let f = |at: usize| {
        let mut w = [0u8; 8];
        w.copy_from_slice(&bytes[at..at + 8]);
        f64::from_le_bytes(w)
    };
    (0..bytes.len() / MATERIAL_LEN as usize)
        .map(|i| {
            let at = i * MATERIAL_LEN as usize;
            SideMaterial {
                reflectance: [0, 1, 2].map(|c| f(at + 8 * c)),
                emission: [3, 4, 5].map(|c| f(at + 8 * c)),
            }
        })
        .collect()
}

/// Writes the results of a solve to `path` and returns the number of records.
pub fn write_results(
    path: &Path,
    set: &SurfelSet,
    solution: &Solution,
) -> Result<u64, OutputError> {
    check_pair(path, set, solution)?;
    let count = set.surfels.len() as u64;
    let mut w = ResultsWriter::create(path, &set.grid, count, &set.materials)?;
    for (s, b) in set.surfels.iter().zip(&solution.radiosity) {
        w.push(&Record::from_surfel(s, *b))?;
    }
    w.finish()?;
    Ok(count)
}

/// Why a results file cannot be read. Every case names the file.
#[derive(Debug, thiserror::Error)]
pub enum ResultsError {
    #[error("cannot read {}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{} is not a voxrad results file: it starts with {found:?}, expected {expected:?}",
        path.display()
    )]
    BadMagic {
        path: PathBuf,
        found: Vec<u8>,
        expected: Vec<u8>,
    },
    #[error(
        "{} has results format version {found}; this build reads versions 1 to {expected}",
        path.display()
    )]
    UnsupportedVersion {
        path: PathBuf,
        found: u32,
        expected: u32,
    },
    #[error("{} has an invalid header: {what}", path.display())]
    BadHeader { path: PathBuf, what: String },
    #[error("{} is truncated or has extra bytes: {what}", path.display())]
    BadLength { path: PathBuf, what: String },
    #[error("{} has an invalid record {index}: {what}", path.display())]
    BadRecord {
        path: PathBuf,
        index: u64,
        what: String,
    },
    #[error(
        "{} is corrupted: checksum {computed:#010x} of its contents does not match the stored \
         {stored:#010x}",
        path.display()
    )]
    ChecksumMismatch {
        path: PathBuf,
        stored: u32,
        computed: u32,
    },
}

impl ResultsError {
    /// The file the error is about.
    pub fn path(&self) -> &Path {
        match self {
            ResultsError::Io { path, .. }
            | ResultsError::BadMagic { path, .. }
            | ResultsError::UnsupportedVersion { path, .. }
            | ResultsError::BadHeader { path, .. }
            | ResultsError::BadLength { path, .. }
            | ResultsError::BadRecord { path, .. }
            | ResultsError::ChecksumMismatch { path, .. } => path,
        }
    }
}

/// Reads and verifies a whole results file (see the module header for the checks and order).
pub fn read_results(path: &Path) -> Result<Results, ResultsError> {
    let reader = ResultsReader::open(path)?;
    // The count is checked against the real file length by `open`, so the collection is bounded
    // by the file size; the last item of the iterator is the checksum's verdict.
    let records = reader.records(1 << 20)?.collect::<Result<Vec<_>, _>>()?;
    Ok(Results {
        grid: reader.grid,
        records,
        materials: reader.materials.clone(),
    })
}

/// A results file whose header, length and footer have been checked, read as a stream: for
/// files too large to hold. The checksum is checked by [`ResultsReader::check_checksum`] (a pass
/// over the file) and again at the end of every [`ResultsReader::records`] pass, so a caller that
/// must not act on unverified data checks first, then streams.
#[derive(Clone, Debug)]
pub struct ResultsReader {
    path: PathBuf,
    grid: Grid,
    count: u64,
    stored: u32,
    header: [u8; HEADER_LEN as usize],
    /// Bytes of one record: [`RECORD_LEN`], or [`RECORD_LEN_V1`] in a version 1 file.
    record_len: u64,
    /// The material table as stored (hashed after the records) and decoded.
    table: Vec<u8>,
    materials: Vec<SideMaterial>,
}

impl ResultsReader {
    /// Opens `path` and checks, in order, magic, version, record length, file length against the
    /// header's count, and the footer.
    pub fn open(path: &Path) -> Result<Self, ResultsError> {
        let io = |source| ResultsError::Io {
            path: path.to_path_buf(),
            source,
        };
        let bad_length = |what: String| ResultsError::BadLength {
            path: path.to_path_buf(),
            what,
        };
        let mut file = File::open(path).map_err(io)?;
        let len = file.metadata().map_err(io)?.len();

        // Read as much of the header as exists, so a short file still gets its magic checked
        // first.
        let mut header = [0u8; HEADER_LEN as usize];
        let got = read_up_to(&mut file, &mut header).map_err(io)?;
        if got < MAGIC.len() || header[..8] != MAGIC {
            return Err(ResultsError::BadMagic {
                path: path.to_path_buf(),
                found: header[..got.min(8)].to_vec(),
                expected: MAGIC.to_vec(),
            });
        }
        if got < 12 {
            return Err(bad_length(format!(
                "{len} bytes, shorter than the {HEADER_LEN}-byte header"
            )));
        }
        let u32_at = |b: &[u8], i: usize| u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        let bytes8 = |b: &[u8], i: usize| {
            let mut w = [0u8; 8];
            w.copy_from_slice(&b[i..i + 8]);
            w
        };
        let u64_at = |b: &[u8], i: usize| u64::from_le_bytes(bytes8(b, i));
        let f64_at = |b: &[u8], i: usize| f64::from_le_bytes(bytes8(b, i));
        let version = u32_at(&header, 8);
        if version != VERSION && version != 1 {
            return Err(ResultsError::UnsupportedVersion {
                path: path.to_path_buf(),
                found: version,
                expected: VERSION,
            });
        }
        if got < HEADER_LEN as usize {
            return Err(bad_length(format!(
                "{len} bytes, shorter than the {HEADER_LEN}-byte header"
            )));
        }
        let record_len = u32_at(&header, 12);
        let expected_record = if version == 1 {
            RECORD_LEN_V1
        } else {
            RECORD_LEN
        };
        if record_len as u64 != expected_record {
            return Err(ResultsError::BadHeader {
                path: path.to_path_buf(),
                what: format!("record length {record_len}, expected {expected_record}"),
            });
        }
        let count = u64_at(&header, 16);
        let material_count = if version == 1 {
            0
        } else {
            u32_at(&header, 68) as u64
        };
        let table_len = material_count * MATERIAL_LEN;
        let expected = count
            .checked_mul(expected_record)
            .and_then(|r| r.checked_add(HEADER_LEN + FOOTER_LEN + table_len));
        if expected != Some(len) {
            return Err(bad_length(format!(
                "the header announces {count} records and {material_count} materials ({} \
                 bytes in all) but the file has {len} bytes",
                expected.map_or_else(|| "an impossible number of".to_string(), |e| e.to_string())
            )));
        }
        let body_len = len - FOOTER_LEN;
        // The table is small (48 bytes a material) and its length was checked above.
        let mut table = vec![0u8; table_len as usize];
        file.seek(SeekFrom::Start(body_len - table_len))
            .map_err(io)?;
        file.read_exact(&mut table).map_err(io)?;
        let mut footer = [0u8; FOOTER_LEN as usize];
        file.read_exact(&mut footer).map_err(io)?;
        let footer_count = u64_at(&footer, 0);
        let stored = u32_at(&footer, 8);
        if footer[12..] != END_MAGIC {
            return Err(bad_length(
                "the footer's end marker is missing (the file was not finished)".to_string(),
            ));
        }
        if footer_count != count {
            return Err(bad_length(format!(
                "the header announces {count} records but the footer {footer_count}"
            )));
        }
        let grid = Grid {
            origin: [0, 1, 2].map(|i| f64_at(&header, 24 + 8 * i)),
            voxel_size: f64_at(&header, 48),
            dims: [0, 1, 2].map(|i| u32_at(&header, 56 + 4 * i)),
        };
        Ok(ResultsReader {
            path: path.to_path_buf(),
            grid,
            count,
            stored,
            header,
            record_len: expected_record,
            materials: decode_materials(&table),
            table,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// Number of records.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// The material table (empty for a version 1 file).
    pub fn materials(&self) -> &[SideMaterial] {
        &self.materials
    }

    /// The records in file order through a buffer of `buffer_bytes`. After the last record,
    /// yields a [`ResultsError::ChecksumMismatch`] if the bytes read do not match the footer.
    pub fn records(&self, buffer_bytes: usize) -> Result<ResultsRecords, ResultsError> {
        let io = |source| ResultsError::Io {
            path: self.path.clone(),
            source,
        };
        let mut file = File::open(&self.path).map_err(io)?;
        file.seek(SeekFrom::Start(HEADER_LEN)).map_err(io)?;
        let mut hasher = crc32fast::Hasher::new();
        hasher.update(&self.header);
        Ok(ResultsRecords {
            reader: self.clone(),
            file: BufReader::with_capacity(buffer_bytes.max(self.record_len as usize), file),
            hasher,
            left: self.count,
            done: false,
        })
    }

    /// Reads the whole file once and compares its checksum with the footer's.
    pub fn check_checksum(&self) -> Result<(), ResultsError> {
        for r in self.records(1 << 20)? {
            r?;
        }
        Ok(())
    }
}

/// Iterator over a results file's records (see [`ResultsReader::records`]).
pub struct ResultsRecords {
    reader: ResultsReader,
    file: BufReader<File>,
    hasher: crc32fast::Hasher,
    left: u64,
    done: bool,
}

impl Iterator for ResultsRecords {
    type Item = Result<Record, ResultsError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        if self.left == 0 {
            self.done = true;
            self.hasher.update(&self.reader.table);
            let computed = self.hasher.clone().finalize();
            return (computed != self.reader.stored).then(|| {
                Err(ResultsError::ChecksumMismatch {
                    path: self.reader.path.clone(),
                    stored: self.reader.stored,
                    computed,
                })
            });
        }
        let mut buf = [0u8; RECORD_LEN as usize];
        let buf = &mut buf[..self.reader.record_len as usize];
        if let Err(source) = self.file.read_exact(buf) {
            self.done = true;
            return Some(Err(ResultsError::Io {
                path: self.reader.path.clone(),
                source,
            }));
        }
        self.hasher.update(buf);
        let index = self.reader.count - self.left;
        self.left -= 1;
        let record = Record::decode(buf);
        let table = self.reader.materials.len();
        let named = (self.reader.record_len == RECORD_LEN)
            .then(|| record.material.iter().find(|&&m| m as usize >= table))
            .flatten();
        if let Some(&m) = named {
            self.done = true;
            return Some(Err(ResultsError::BadRecord {
                path: self.reader.path.clone(),
                index,
                what: format!("its material {m} is not in the table of {table}"),
            }));
        }
        Some(Ok(record))
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = self.left as usize;
        (left, Some(left + 1))
    }
}

/// Fills `buf` as far as the reader allows; returns how many bytes were read. (A short read is
/// not an error here: readers of checked files report short files as length errors.)
pub(crate) fn read_up_to(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

/// The first line of a CSV export.
pub const CSV_HEADER: &str = "x,y,z,nx,ny,nz,B_r,B_g,B_b";

/// Writes the CSV rows of one record (one per present side, see [`write_csv`]); returns how many.
pub fn write_csv_record(w: &mut dyn Write, grid: &Grid, r: &Record) -> std::io::Result<u64> {
    let p = grid.to_world(r.position());
    let mut rows = 0;
    for side in [FRONT, BACK] {
        if !r.side_is_present(side) {
            continue;
        }
        let n = r.side_normal(side);
        let b = r.radiosity[side];
        writeln!(
            w,
            "{},{},{},{},{},{},{},{},{}",
            p.x, p.y, p.z, n.x as f32, n.y as f32, n.z as f32, b[0], b[1], b[2]
        )?;
        rows += 1;
    }
    Ok(rows)
}

/// Writes one CSV row per present surfel side (area > 0 or any radiosity): world position, the
/// side's unit normal and its radiosity, `x,y,z,nx,ny,nz,B_r,B_g,B_b`, after a header line.
/// Meant for small scenes (`voxrad-shard export` streams large ones); returns the number of rows.
pub fn write_csv(path: &Path, results: &Results) -> Result<u64, OutputError> {
    let mut rows = 0u64;
    atomic::write_atomically(path, |w| {
        writeln!(w, "{CSV_HEADER}")?;
        for r in &results.records {
            rows += write_csv_record(w, &results.grid, r)?;
        }
        Ok(())
    })?;
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::testutil;

    fn written() -> (tempfile::TempDir, PathBuf, Results) {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("surfels.bin");
        let (set, solution) = testutil::lit_square(5);
        assert_eq!(write_results(&path, &set, &solution).unwrap(), 25);
        let expected = Results::from_solution(&set, &solution).unwrap();
        (dir, path, expected)
    }

    #[test]
    fn round_trip() {
        let (dir, path, expected) = written();
        let back = read_results(&path).unwrap();
        assert_eq!(back, expected);
        let len = std::fs::metadata(&path).unwrap().len();
        assert_eq!(
            len,
            HEADER_LEN + 25 * RECORD_LEN + MATERIAL_LEN + FOOTER_LEN
        );
        // Only the finished file is left: no temporary beside it.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    fn corrupt(path: &Path, f: impl FnOnce(&mut Vec<u8>)) {
        let mut bytes = std::fs::read(path).unwrap();
        f(&mut bytes);
        std::fs::write(path, bytes).unwrap();
    }

    fn names_file(e: &ResultsError, path: &Path) {
        assert_eq!(e.path(), path);
        assert!(e.to_string().contains(&path.display().to_string()), "{e}");
    }

    #[test]
    fn flipped_byte_is_a_checksum_error() {
        let (_dir, path, _) = written();
        corrupt(&path, |b| {
            let mid = b.len() / 2;
            b[mid] ^= 0x40;
        });
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::ChecksumMismatch { .. }), "{e}");
        names_file(&e, &path);
    }

    #[test]
    fn truncation_is_a_length_error() {
        let (_dir, path, _) = written();
        corrupt(&path, |b| b.truncate(b.len() - 30));
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::BadLength { .. }), "{e}");
        names_file(&e, &path);
        // Cut inside the header too.
        corrupt(&path, |b| b.truncate(40));
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::BadLength { .. }), "{e}");
    }

    #[test]
    fn wrong_magic_is_reported_first() {
        let (_dir, path, _) = written();
        corrupt(&path, |b| {
            b[0] = b'X';
            b[8] = 99; // a bad version too: the magic is checked first
        });
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::BadMagic { .. }), "{e}");
        names_file(&e, &path);
        std::fs::write(&path, b"VX").unwrap();
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::BadMagic { .. }), "{e}");
    }

    #[test]
    fn wrong_version_is_reported_before_the_checksum() {
        let (_dir, path, _) = written();
        corrupt(&path, |b| b[8..12].copy_from_slice(&7u32.to_le_bytes()));
        let e = read_results(&path).unwrap_err();
        match &e {
            ResultsError::UnsupportedVersion { found, .. } => assert_eq!(*found, 7),
            other => panic!("{other}"),
        }
        names_file(&e, &path);
    }

    #[test]
    fn missing_file_names_it() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("absent.bin");
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::Io { .. }));
        names_file(&e, &path);
    }

    /// A version 1 file (64-byte records, no material table), as solves before materials were
    /// stored wrote it: read, with the irradiance unknown.
    #[test]
    fn version_1_files_are_read_without_materials() {
        let (_dir, path, expected) = written();
        let mut v1 = Vec::new();
        let mut header = encode_header(&expected.grid, 25, 0);
        header[8..12].copy_from_slice(&1u32.to_le_bytes());
        header[12..16].copy_from_slice(&(RECORD_LEN_V1 as u32).to_le_bytes());
        v1.extend_from_slice(&header);
        for r in &expected.records {
            v1.extend_from_slice(&r.encode()[..RECORD_LEN_V1 as usize]);
        }
        let crc = crc32fast::hash(&v1);
        v1.extend_from_slice(&25u64.to_le_bytes());
        v1.extend_from_slice(&crc.to_le_bytes());
        v1.extend_from_slice(&END_MAGIC);
        std::fs::write(&path, v1).unwrap();
        let back = read_results(&path).unwrap();
        assert!(back.materials.is_empty());
        assert_eq!(back.records.len(), 25);
        for (b, e) in back.records.iter().zip(&expected.records) {
            assert_eq!((b.voxel, b.radiosity), (e.voxel, e.radiosity));
            assert_eq!(b.material, [NO_MATERIAL; 2]);
            assert_eq!(b.irradiance(FRONT, &back.materials), [None; 3]);
        }
    }

    /// A record naming a material the table does not hold is refused, naming the record.
    #[test]
    fn a_material_outside_the_table_is_refused() {
        let (_dir, path, _) = written();
        corrupt(&path, |b| {
            let at = (HEADER_LEN + 3 * RECORD_LEN + 68) as usize;
            b[at..at + 4].copy_from_slice(&7u32.to_le_bytes());
            // Keep the checksum right, so that the record check is what fails.
            let body = b.len() - FOOTER_LEN as usize;
            let crc = crc32fast::hash(&b[..body]);
            b[body + 8..body + 12].copy_from_slice(&crc.to_le_bytes());
        });
        let e = read_results(&path).unwrap_err();
        assert!(matches!(e, ResultsError::BadRecord { index: 3, .. }), "{e}");
        names_file(&e, &path);
    }

    /// `H = (B - E) / rho` by channel; unknown where the reflectance is 0.
    #[test]
    fn irradiance_is_what_the_side_reflects_over_its_reflectance() {
        let materials = [
            SideMaterial {
                reflectance: [0.5, 0.25, 0.0],
                emission: [0.0; 3],
            },
            SideMaterial {
                reflectance: [0.5; 3],
                emission: [1.0, 2.0, 0.0],
            },
        ];
        let mut r = Record::from_surfel(
            &testutil::surfel([0; 3], [0.5; 3], [0.0, 0.0, 1.0], 1.0),
            [[1.0, 1.0, 1.0], [3.0, 3.0, 3.0]],
        );
        r.material = [0, 1];
        assert_eq!(
            r.irradiance(FRONT, &materials),
            [Some(2.0), Some(4.0), None]
        );
        assert_eq!(
            r.irradiance(BACK, &materials),
            [Some(4.0), Some(2.0), Some(6.0)]
        );
    }

    #[test]
    fn unfinished_writer_leaves_nothing() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("surfels.bin");
        let (set, solution) = testutil::lit_square(2);
        let mut w = ResultsWriter::create(&path, &set.grid, 4, &set.materials).unwrap();
        w.push(&Record::from_surfel(&set.surfels[0], solution.radiosity[0]))
            .unwrap();
        let e = w.finish().unwrap_err();
        assert!(e.to_string().contains("surfels.bin"), "{e}");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn csv_has_present_sides_in_world_units() {
        let dir = tempfile::TempDir::new().unwrap();
        let path = dir.path().join("surfels.csv");
        let mut surfels = vec![
            testutil::surfel([1, 2, 3], [0.5, 0.5, 0.5], [0.0, 0.0, 1.0], 0.0),
            testutil::surfel([0, 0, 0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], 0.0),
        ];
        surfels[1].area = 0.0;
        let set = testutil::set_of(surfels, 0.5);
        let solution = Solution {
            radiosity: vec![[[1.0, 2.0, 3.0], [0.0; 3]], [[0.0; 3]; 2]],
            stats: Default::default(),
        };
        let results = Results::from_solution(&set, &solution).unwrap();
        assert_eq!(write_csv(&path, &results).unwrap(), 1);
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "x,y,z,nx,ny,nz,B_r,B_g,B_b");
        // origin (-1, 2, 0.5) + (1.5, 2.5, 3.5) * 0.5
        assert_eq!(lines[1], "-0.25,3.25,2.25,0,0,1,1,2,3");
        assert_eq!(lines.len(), 2);
    }
}

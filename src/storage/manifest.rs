//! The shard-set manifest, `manifest.json`: what a shard set is, beside the shard files it lists.
//!
//! A shard set is a directory holding this manifest and shard files (see `shard`). JSON, because
//! it is small (it grows with the number of materials, normals and shards, not with the voxels)
//! and people read it when inspecting a set. Fields:
//!
//! ```text
//! format          "voxrad-shardset"   (what the file is; the JSON equivalent of a magic number)
//! format_version  2                   (this build reads MIN_VERSION..=VERSION)
//! grid            { origin: [f64; 3], voxel_size: f64, dims: [u32; 3] }  scene bounds in world units
//! materials       [{ name, reflectance: [f64; 3] in [0, 1), emission: [f64; 3] >= 0,
//!                 inside: true (only on the material of back sides inside closed solids,
//!                 voxel::enclosed; absent means false) }] indexed by a record's `material`
//! normals         [[f32; 3]] unit normals, indexed by a record's `normal_id`
//! order           0..4, the lexicographic order every shard is sorted in (geometry::order)
//! shards          [{ file, records, bytes, crc32 }] in rank order: a plain file name inside the
//!                 set's directory, its record count, its size in bytes, and its footer checksum
//!                 (CRC-32 of everything before the shard's footer), so a shard can be matched to
//!                 the manifest by reading its footer only
//! manifest_crc32  (version 2) CRC-32 (IEEE) of every byte of the file before the key
//!                 "manifest_crc32", which is the last field
//! ```
//!
//! The manifest's own checksum (version 2) exists because the manifest decides the answer as much
//! as the shards do: a flipped digit in a reflectance or in the grid would otherwise give a wrong
//! radiosity with exit status 0. It covers the raw bytes, so any change before it is caught
//! (whitespace included); a version 1 manifest (no checksum) is still read, unchecked, and a
//! checksum present in any version is always checked, so one flipped byte cannot both turn a
//! version 2 manifest into a version 1 and change a value.
//!
//! Written atomically (temporary file, sync, rename; `output::atomic`), readable by all like the
//! shards, and written last when a
//! set is made, so a directory with a manifest has all its shards. [`Manifest::read`] checks, in
//! order, the `format` marker, the version, the JSON structure, then every value (finite, in
//! range, unique file names that stay inside the directory, sizes that agree with counts); every
//! error names the file. [`Manifest::check_shards`] matches the listed shard files to the entries.

use super::shard::{self, ShardInfo, ShardReader};
use super::StorageError;
use crate::output::atomic;
use crate::scene::Material;
use crate::voxel::Grid;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::io::Write;
use std::path::{Path, PathBuf};

pub const MANIFEST_FILE: &str = "manifest.json";
pub const FORMAT: &str = "voxrad-shardset";
/// The version this build writes (2: the manifest carries its own checksum).
pub const VERSION: u32 = 2;
/// The key of the manifest's own checksum, the last field of the file.
pub const CHECKSUM_KEY: &str = "manifest_crc32";
/// The oldest version this build reads.
pub const MIN_VERSION: u32 = 1;

const KIND: &str = "shard-set manifest";

/// A material as stored in the manifest (the scene's [`Material`], serialisable).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaterialEntry {
    pub name: String,
    pub reflectance: [f64; 3],
    pub emission: [f64; 3],
    /// The back sides inside closed solids (`scene::Material::inside`); written only when true,
    /// so that shard sets without such sides read and write as before.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub inside: bool,
}

impl From<&Material> for MaterialEntry {
    fn from(m: &Material) -> Self {
        MaterialEntry {
            name: m.name.clone(),
            reflectance: m.reflectance,
            emission: m.emission,
            inside: m.inside,
        }
    }
}

impl From<&MaterialEntry> for Material {
    fn from(m: &MaterialEntry) -> Self {
        Material {
            inside: m.inside,
            ..Material::new(&m.name, m.reflectance, m.emission)
        }
    }
}

/// One shard file of the set.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ShardEntry {
    /// File name inside the set's directory.
    pub file: String,
    pub records: u64,
    pub bytes: u64,
    /// The shard's footer checksum.
    pub crc32: u32,
}

impl ShardEntry {
    /// The entry for a finished shard, listed under its file name.
    pub fn from_info(info: &ShardInfo) -> Result<Self, StorageError> {
        let file = info
            .path
            .file_name()
            .and_then(|n| n.to_str())
            .ok_or_else(|| {
                StorageError::invalid(&info.path, "a shard's file name must be valid UTF-8")
            })?;
        Ok(ShardEntry {
            file: file.to_string(),
            records: info.count,
            bytes: info.bytes,
            crc32: info.crc32,
        })
    }

    /// How the shard file described by `info` differs from this entry of a manifest of order
    /// `order` (order, record count and size, checksum), or `None` if it is the listed file.
    pub fn mismatch(&self, info: &ShardInfo, order: usize) -> Option<String> {
        if info.order != order {
            Some(format!("order {}, the manifest {order}", info.order))
        } else if info.count != self.records || info.bytes != self.bytes {
            Some(format!(
                "{} records in {} bytes, the manifest {} in {}",
                info.count, info.bytes, self.records, self.bytes
            ))
        } else if info.crc32 != self.crc32 {
            Some(format!(
                "checksum {:#010x}, the manifest {:#010x}",
                info.crc32, self.crc32
            ))
        } else {
            None
        }
    }
}

/// The manifest of a shard set (see the module header).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub format_version: u32,
    pub grid: Grid,
    pub materials: Vec<MaterialEntry>,
    pub normals: Vec<[f32; 3]>,
    pub order: usize,
    pub shards: Vec<ShardEntry>,
    /// Every shard begins at a voxel boundary of the canonical stream (no voxel's surfels are
    /// split over two shards), as `voxrad-shard convert` and `reshard` cut them: a rank of the
    /// data mode out of core whose slice is one shard then reads that shard alone. Written only
    /// when true, so that other sets read and write as before.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub voxel_aligned: bool,
}

/// Only the fields that say what a file is, read before trusting the rest of its structure.
#[derive(Deserialize)]
struct Probe {
    format: Option<String>,
    format_version: Option<u32>,
    manifest_crc32: Option<u32>,
}

/// The bytes of a manifest file for the JSON `json` (an object, as `serde_json` writes it): the
/// object with the checksum of everything before its key appended as its last field.
fn with_checksum(mut json: Vec<u8>) -> Vec<u8> {
    // Pretty JSON of a struct ends with "\n}"; reopen the object after its last field.
    while json.last().is_some_and(|b| b.is_ascii_whitespace()) {
        json.pop();
    }
    debug_assert_eq!(json.last(), Some(&b'}'));
    json.pop();
    while json.last().is_some_and(|b| b.is_ascii_whitespace()) {
        json.pop();
    }
    json.extend_from_slice(b",\n  ");
    let crc = crc32fast::hash(&json);
    json.extend_from_slice(format!("\"{CHECKSUM_KEY}\": {crc}\n}}\n").as_bytes());
    json
}

/// Where the checksum's key starts in a manifest file: its last occurrence (the checksum is the
/// last field; a key spelled the same inside an earlier string would come before it).
fn checksum_key_at(text: &[u8]) -> Option<usize> {
    let key = format!("\"{CHECKSUM_KEY}\"");
    let key = key.as_bytes();
    text.windows(key.len()).rposition(|w| w == key)
}

impl Manifest {
    /// A manifest of the current version.
    pub fn new(
        grid: Grid,
        materials: &[Material],
        normals: Vec<[f32; 3]>,
        order: usize,
        shards: Vec<ShardEntry>,
    ) -> Self {
        Manifest {
            format: FORMAT.to_string(),
            format_version: VERSION,
            grid,
            materials: materials.iter().map(MaterialEntry::from).collect(),
            normals,
            order,
            shards,
            voxel_aligned: false,
        }
    }

    /// The path of the manifest in the shard set `dir`.
    pub fn path_in(dir: &Path) -> PathBuf {
        dir.join(MANIFEST_FILE)
    }

    /// World-space bounds of the grid: low and high corner.
    pub fn bounds(&self) -> [[f64; 3]; 2] {
        let g = &self.grid;
        let high = [0, 1, 2].map(|i| g.origin[i] + g.dims[i] as f64 * g.voxel_size);
        [g.origin, high]
    }

    /// Total number of records over all shards.
    pub fn records(&self) -> u64 {
        self.shards.iter().map(|s| s.records).sum()
    }

    /// The scene's materials.
    pub fn materials(&self) -> Vec<Material> {
        self.materials.iter().map(Material::from).collect()
    }

    /// Writes the manifest into the shard set `dir` atomically, after validating it (a manifest
    /// that would not read back is never written). Returns its path.
    pub fn write(&self, dir: &Path) -> Result<PathBuf, StorageError> {
        let path = Self::path_in(dir);
        self.validate(&path)?;
        let json = serde_json::to_vec_pretty(self)
            .map_err(|e| StorageError::invalid(&path, format!("cannot encode it: {e}")))?;
        let json = with_checksum(json);
        let mut tmp = shard::temp_beside_shared(&path)?;
        tmp.write_all(&json)
            .map_err(|e| StorageError::io(&path, "write", e))?;
        atomic::commit(tmp, &path)?;
        Ok(path)
    }

    /// Reads and validates the manifest of the shard set `dir`.
    pub fn read_dir(dir: &Path) -> Result<Self, StorageError> {
        Self::read(&Self::path_in(dir))
    }

    /// Reads and validates the manifest file at `path` (see the module header for the order of
    /// the checks).
    pub fn read(path: &Path) -> Result<Self, StorageError> {
        let text = std::fs::read(path).map_err(|e| StorageError::io(path, "read", e))?;
        Self::parse(path, &text)
    }

    /// Parses and validates the bytes of a manifest file; `path` only names it in errors (for
    /// manifests that did not come from a file of their own, such as one inside a pack).
    pub fn parse(path: &Path, text: &[u8]) -> Result<Self, StorageError> {
        let json = |source| StorageError::Json {
            path: path.to_path_buf(),
            source,
        };
        let probe: Probe = serde_json::from_slice(text).map_err(json)?;
        if probe.format.as_deref() != Some(FORMAT) {
            return Err(StorageError::BadMagic {
                path: path.to_path_buf(),
                kind: KIND,
                found: probe.format.unwrap_or_default().into_bytes(),
                expected: FORMAT.as_bytes().to_vec(),
            });
        }
        let version = probe.format_version.unwrap_or(0);
        if !(MIN_VERSION..=VERSION).contains(&version) {
            return Err(StorageError::UnsupportedVersion {
                path: path.to_path_buf(),
                kind: KIND,
                found: version,
                min: MIN_VERSION,
                max: VERSION,
            });
        }
        match probe.manifest_crc32 {
            Some(stored) => {
                // The key was found by the JSON parser, so it is in the text.
                let at = checksum_key_at(text).unwrap_or(text.len());
                let computed = crc32fast::hash(&text[..at]);
                if computed != stored {
                    return Err(StorageError::ChecksumMismatch {
                        path: path.to_path_buf(),
                        stored,
                        computed,
                    });
                }
            }
            None if version >= 2 => {
                return Err(StorageError::BadHeader {
                    path: path.to_path_buf(),
                    what: format!(
                        "format version {version} but no \"{CHECKSUM_KEY}\" field (the file was \
                         edited or cut short)"
                    ),
                });
            }
            None => {}
        }
        let manifest: Manifest = serde_json::from_slice(text).map_err(json)?;
        manifest.validate(path)?;
        Ok(manifest)
    }

    /// Checks every value (see the module header); `path` names the manifest in errors.
    pub fn validate(&self, path: &Path) -> Result<(), StorageError> {
        let bad = |what: String| Err(StorageError::invalid(path, what));
        let g = &self.grid;
        if !g.origin.iter().all(|v| v.is_finite()) {
            return bad(format!("grid origin {:?} is not finite", g.origin));
        }
        if !(g.voxel_size.is_finite() && g.voxel_size > 0.0) {
            return bad(format!(
                "voxel size {} is not a positive number",
                g.voxel_size
            ));
        }
        if g.dims.contains(&0) {
            return bad(format!("grid dimensions {:?} include a zero", g.dims));
        }
        for (i, m) in self.materials.iter().enumerate() {
            if !m.reflectance.iter().all(|r| (0.0..1.0).contains(r)) {
                return bad(format!(
                    "material {i} ({:?}) has reflectance {:?}, outside [0, 1)",
                    m.name, m.reflectance
                ));
            }
            if !m.emission.iter().all(|e| e.is_finite() && *e >= 0.0) {
                return bad(format!(
                    "material {i} ({:?}) has emission {:?}, not finite and non-negative",
                    m.name, m.emission
                ));
            }
            // The sides inside solids gather nothing and send nothing: such a material can only
            // be black and dark, or the answer would silently lose its light.
            let lit = m.reflectance.iter().chain(&m.emission).any(|&v| v != 0.0);
            if m.inside && lit {
                return bad(format!(
                    "material {i} ({:?}) is marked inside a solid but reflects or emits \
                     (reflectance {:?}, emission {:?})",
                    m.name, m.reflectance, m.emission
                ));
            }
        }
        for (i, n) in self.normals.iter().enumerate() {
            let len = n.iter().map(|c| (*c as f64).powi(2)).sum::<f64>().sqrt();
            // f32 components of a unit vector: anything far from 1 is not a rounding error.
            if !len.is_finite() || (len - 1.0).abs() > 1e-4 {
                return bad(format!("normal {i} {n:?} is not a unit vector"));
            }
        }
        if self.order >= shard::ORDERS {
            return bad(format!(
                "order {}, but only 0 to {} exist",
                self.order,
                shard::ORDERS - 1
            ));
        }
        let mut names = HashSet::new();
        let mut total: u64 = 0;
        for (i, s) in self.shards.iter().enumerate() {
            let plain = !s.file.is_empty()
                && s.file != "."
                && s.file != ".."
                && !s.file.contains(['/', '\\'])
                && s.file != MANIFEST_FILE;
            if !plain {
                return bad(format!(
                    "shard {i} has file name {:?}; it must be a plain file name inside the set's \
                     directory",
                    s.file
                ));
            }
            if !names.insert(s.file.as_str()) {
                return bad(format!("shard file {:?} is listed twice", s.file));
            }
            if shard::file_len(s.records) != Some(s.bytes) {
                return bad(format!(
                    "shard {:?} is listed with {} records but {} bytes, which cannot both hold",
                    s.file, s.records, s.bytes
                ));
            }
            total = match total.checked_add(s.records) {
                Some(t) => t,
                None => return bad("the shards' record counts overflow".to_string()),
            };
        }
        Ok(())
    }

    /// The path of shard `entry` in the shard set `dir`.
    pub fn shard_path(dir: &Path, entry: &ShardEntry) -> PathBuf {
        dir.join(&entry.file)
    }

    /// Opens every listed shard of the set `dir` (checking magic, version and lengths, not
    /// checksums) and checks that it is the file the manifest lists: same order, record count,
    /// size and footer checksum. Cheap: reads each shard's header and footer only.
    pub fn check_shards(&self, dir: &Path) -> Result<Vec<ShardReader>, StorageError> {
        self.check_present_shards(dir, false)?
            .into_iter()
            .map(|reader| Ok(reader.expect("every shard is required")))
            .collect()
    }

    /// As [`Manifest::check_shards`], but with `allow_missing` a shard whose file is not in
    /// `dir` is `None` rather than an error (a node that holds only the shards its rank reads).
    pub fn check_present_shards(
        &self,
        dir: &Path,
        allow_missing: bool,
    ) -> Result<Vec<Option<ShardReader>>, StorageError> {
        self.shards
            .iter()
            .map(|entry| {
                let path = Self::shard_path(dir, entry);
                if allow_missing && !path.exists() {
                    return Ok(None);
                }
                let reader = ShardReader::open_lazy(&path)?;
                let info = reader.info();
                let mismatch = entry.mismatch(info, self.order);
                match mismatch {
                    Some(what) => Err(StorageError::invalid(
                        &path,
                        format!(
                            "it does not match {}: it has {what}; the shard set is mixed up, \
                             make it again",
                            Self::path_in(dir).display()
                        ),
                    )),
                    None => Ok(Some(reader)),
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::shard::tests::{sorted_surfels, write_shard};

    fn sample(dir: &Path) -> Manifest {
        let order = 1;
        let shards = (0..2)
            .map(|k| {
                let path = dir.join(format!("shard-{k:05}.vxs"));
                let info = write_shard(&path, order, &sorted_surfels(10 + k, order, k as u64));
                ShardEntry::from_info(&info).unwrap()
            })
            .collect();
        Manifest::new(
            Grid {
                origin: [-1.0, 0.0, 2.5],
                voxel_size: 0.25,
                dims: [8, 4, 2],
            },
            &[
                Material::new("wall", [0.5, 0.6, 0.7], [0.0; 3]),
                Material::new("lamp", [0.0; 3], [10.0, 9.0, 8.0]),
                Material::inside_of_solids(),
            ],
            vec![[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]],
            order,
            shards,
        )
    }

    #[test]
    fn round_trip_and_shards_match() {
        let dir = tempfile::TempDir::new().unwrap();
        let m = sample(dir.path());
        let path = m.write(dir.path()).unwrap();
        assert_eq!(path, dir.path().join(MANIFEST_FILE));
        let back = Manifest::read_dir(dir.path()).unwrap();
        assert_eq!(back, m);
        assert_eq!(back.records(), 21);
        assert_eq!(back.bounds(), [[-1.0, 0.0, 2.5], [1.0, 1.0, 3.0]]);
        assert_eq!(back.materials()[1].emission, [10.0, 9.0, 8.0]);
        // The flag is written only where it is set, and read back.
        let text = std::fs::read_to_string(&path).unwrap();
        assert_eq!(text.matches("\"inside\"").count(), 1, "{text}");
        let inside: Vec<bool> = back.materials().iter().map(|m| m.inside).collect();
        assert_eq!(inside, [false, false, true]);
        assert_eq!(back.check_shards(dir.path()).unwrap().len(), 2);
    }

    fn write_json(dir: &Path, f: impl FnOnce(&mut serde_json::Value)) -> PathBuf {
        let mut v = serde_json::to_value(sample(dir)).unwrap();
        f(&mut v);
        let path = Manifest::path_in(dir);
        std::fs::write(&path, with_checksum(serde_json::to_vec(&v).unwrap())).unwrap();
        path
    }

    fn read_err(dir: &Path, f: impl FnOnce(&mut serde_json::Value)) -> StorageError {
        let path = write_json(dir, f);
        let e = Manifest::read(&path).unwrap_err();
        assert_eq!(e.path(), Some(path.as_path()));
        assert!(e.to_string().contains(MANIFEST_FILE), "{e}");
        e
    }

    #[test]
    fn every_bad_manifest_is_named_with_what_is_wrong() {
        let dir = tempfile::TempDir::new().unwrap();
        let d = dir.path();
        let e = read_err(d, |v| v["format"] = "something-else".into());
        assert!(matches!(e, StorageError::BadMagic { .. }), "{e}");
        let e = read_err(d, |v| v["format_version"] = 3.into());
        assert!(
            matches!(e, StorageError::UnsupportedVersion { found: 3, .. }),
            "{e}"
        );
        let e = read_err(d, |v| v["order"] = "x".into());
        assert!(matches!(e, StorageError::Json { .. }), "{e}");
        let e = read_err(d, |v| v["order"] = 4.into());
        assert!(e.to_string().contains("order 4"), "{e}");
        let e = read_err(d, |v| v["grid"]["voxel_size"] = (-1.0).into());
        assert!(e.to_string().contains("voxel size"), "{e}");
        let e = read_err(d, |v| v["materials"][0]["reflectance"][1] = 1.0.into());
        assert!(e.to_string().contains("reflectance"), "{e}");
        let e = read_err(d, |v| v["materials"][0]["inside"] = true.into());
        assert!(e.to_string().contains("inside a solid"), "{e}");
        let e = read_err(d, |v| v["normals"][1][0] = 0.7.into());
        assert!(e.to_string().contains("unit vector"), "{e}");
        let e = read_err(d, |v| v["shards"][0]["file"] = "../escape.vxs".into());
        assert!(e.to_string().contains("plain file name"), "{e}");
        let e = read_err(d, |v| {
            v["shards"][1]["file"] = v["shards"][0]["file"].clone()
        });
        assert!(e.to_string().contains("twice"), "{e}");
        let e = read_err(d, |v| v["shards"][0]["bytes"] = 1000.into());
        assert!(e.to_string().contains("cannot both hold"), "{e}");
        std::fs::write(Manifest::path_in(d), b"{ truncated").unwrap();
        let e = Manifest::read_dir(d).unwrap_err();
        assert!(matches!(e, StorageError::Json { .. }), "{e}");
        let missing = tempfile::TempDir::new().unwrap();
        let e = Manifest::read_dir(missing.path()).unwrap_err();
        assert!(matches!(e, StorageError::Io { .. }), "{e}");
    }

    #[test]
    fn the_manifest_checksum_catches_every_edit() {
        let dir = tempfile::TempDir::new().unwrap();
        let m = sample(dir.path());
        let path = m.write(dir.path()).unwrap();
        let good = std::fs::read(&path).unwrap();
        let text = String::from_utf8(good.clone()).unwrap();
        assert!(text.trim_end().ends_with('}'), "{text}");
        assert_eq!(checksum_key_at(&good), text.rfind("\"manifest_crc32\""));
        // A value changed to another valid value: only the checksum can tell.
        let edited = text.replacen("0.25", "0.5", 1);
        assert_ne!(edited, text);
        std::fs::write(&path, &edited).unwrap();
        let e = Manifest::read(&path).unwrap_err();
        assert!(matches!(e, StorageError::ChecksumMismatch { .. }), "{e}");
        assert!(e.to_string().contains(MANIFEST_FILE), "{e}");
        // The checksum removed: a version 2 manifest must have one.
        let cut = text.rfind(",\n  \"manifest_crc32\"").unwrap();
        std::fs::write(&path, format!("{}\n}}\n", &text[..cut])).unwrap();
        let e = Manifest::read(&path).unwrap_err();
        assert!(e.to_string().contains("manifest_crc32"), "{e}");
        // Downgraded to version 1 with the checksum still there: still checked.
        std::fs::write(
            &path,
            text.replace("\"format_version\": 2", "\"format_version\": 1"),
        )
        .unwrap();
        let e = Manifest::read(&path).unwrap_err();
        assert!(matches!(e, StorageError::ChecksumMismatch { .. }), "{e}");
        // Untouched, it reads.
        std::fs::write(&path, &good).unwrap();
        assert_eq!(Manifest::read(&path).unwrap(), m);
    }

    #[test]
    fn a_shard_that_is_not_the_listed_one_is_named() {
        let dir = tempfile::TempDir::new().unwrap();
        let mut m = sample(dir.path());
        m.shards[1].crc32 ^= 1;
        m.write(dir.path()).unwrap();
        let e = Manifest::read_dir(dir.path())
            .unwrap()
            .check_shards(dir.path())
            .unwrap_err();
        assert!(e.to_string().contains("shard-00001.vxs"), "{e}");
        assert!(e.to_string().contains("checksum"), "{e}");
    }

    #[test]
    fn an_invalid_manifest_is_not_written() {
        let dir = tempfile::TempDir::new().unwrap();
        let mut m = sample(dir.path());
        m.grid.voxel_size = f64::NAN;
        assert!(m.write(dir.path()).is_err());
        assert!(!Manifest::path_in(dir.path()).exists());
    }
}

//! Whole shard sets: writing one safely, splitting a sorted stream into equal-count shards,
//! verifying every file of one, describing one.
//!
//! A set is built in a staging directory beside the target ([`Staging`]), and appears under its
//! real name only once all its shards and its manifest are complete and synced: a crash leaves
//! either the old set or the new one, never a mix (plus, at worst, a hidden staging directory).
//! Replacing an existing set swaps the directories by two renames, then deletes the old one.
//!
//! [`verify_set`] reads every byte once: each shard's magic, version, lengths and checksum (by
//! `storage::shard`), its match with the manifest's entry (count, size, checksum, order), the
//! order of its records, and the order across shards (a shard's first record must not sort before
//! the previous shard's last). Every problem is reported, one line per file.

use super::ConvertError;
use crate::geometry::order;
use crate::storage::record::{self, RECORD_LEN};
use crate::storage::shard::{self, ShardInfo, ShardReader, ShardWriter, WriteOptions};
use crate::storage::{Manifest, StorageError, MANIFEST_FILE};
use crate::voxel::Surfel;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The file name of shard `rank`.
pub fn shard_file_name(rank: usize) -> String {
    format!("shard-{rank:05}.vxs")
}

fn bad(path: &Path, what: impl std::fmt::Display) -> ConvertError {
    ConvertError::BadInput(format!("{}: {what}", path.display()))
}

fn failed(path: &Path, what: impl std::fmt::Display) -> ConvertError {
    ConvertError::Failure(format!("{}: {what}", path.display()))
}

/// A shard set being built beside its final place (see the module header).
pub struct Staging {
    target: PathBuf,
    dir: tempfile::TempDir,
}

impl Staging {
    /// Checks that `target` can receive a shard set (absent, an empty directory, or an existing
    /// shard set, which will be replaced) and creates the staging directory beside it.
    pub fn new(target: &Path) -> Result<Self, ConvertError> {
        if target.exists() {
            if !target.is_dir() {
                return Err(bad(
                    target,
                    "exists and is not a directory; give a new directory for the shard set",
                ));
            }
            let empty = std::fs::read_dir(target)
                .map_err(|e| bad(target, format!("cannot be read: {e}")))?
                .next()
                .is_none();
            if !empty && Manifest::read_dir(target).is_err() {
                return Err(bad(
                    target,
                    format!(
                        "exists, is not empty and is not a shard set (no valid {MANIFEST_FILE}); \
                         refusing to replace it: give a new or empty directory"
                    ),
                ));
            }
        }
        let parent = crate::output::atomic::parent_dir(target);
        if !parent.is_dir() {
            return Err(bad(
                target,
                format!("its parent directory {} does not exist", parent.display()),
            ));
        }
        let dir = tempfile::Builder::new()
            .prefix(".voxrad-shard-staging-")
            .tempdir_in(parent)
            .map_err(|e| failed(parent, format!("cannot create a staging directory: {e}")))?;
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            // Readable by all once in place, like every shard (tempfile makes it owner-only).
            std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755))
                .map_err(|e| failed(dir.path(), e))?;
        }
        Ok(Staging {
            target: target.to_path_buf(),
            dir,
        })
    }

    pub fn path(&self) -> &Path {
        self.dir.path()
    }

    /// Moves the finished set into place (see the module header).
    pub fn commit(self) -> Result<(), ConvertError> {
        let staging = self.dir.keep();
        let target = &self.target;
        let parent = crate::output::atomic::parent_dir(target).to_path_buf();
        let old = if target.exists() {
            let old = tempfile::Builder::new()
                .prefix(".voxrad-shard-old-")
                .tempdir_in(&parent)
                .map_err(|e| failed(&parent, format!("cannot create a directory: {e}")))?
                .keep();
            // Renaming a directory onto an empty one replaces it.
            std::fs::rename(target, &old)
                .map_err(|e| failed(target, format!("cannot move: {e}")))?;
            Some(old)
        } else {
            None
        };
        std::fs::rename(&staging, target).map_err(|e| {
            failed(
                target,
                format!(
                    "cannot move the new set {} into place: {e}",
                    staging.display()
                ),
            )
        })?;
        if let Ok(dir) = std::fs::File::open(&parent) {
            let _ = dir.sync_all();
        }
        if let Some(old) = old {
            std::fs::remove_dir_all(&old)
                .map_err(|e| failed(&old, format!("cannot remove the replaced set: {e}")))?;
        }
        Ok(())
    }
}

/// Writes `total` sorted records into `ranks` shards in `dir`: shard `k` begins at the first
/// voxel boundary at or after record `k * total / ranks` (so no voxel's surfels are split over
/// two shards, and a shard may be empty where one voxel spans a whole share), the rule by which
/// the data mode out of core slices the stream over its ranks. Holds one write buffer of
/// `buffer_bytes`.
pub fn write_split(
    records: impl Iterator<Item = Result<Surfel, ConvertError>>,
    total: u64,
    ranks: usize,
    dir: &Path,
    order: usize,
    buffer_bytes: usize,
) -> Result<Vec<ShardInfo>, ConvertError> {
    let bound = |k: usize| (total as u128 * k as u128 / ranks as u128) as u64;
    let options = WriteOptions {
        buffer_bytes,
        sync: true,
    };
    let mut records = records.peekable();
    let mut infos = Vec::with_capacity(ranks);
    let (mut index, mut last_voxel) = (0u64, None);
    for k in 0..ranks {
        let path = dir.join(shard_file_name(k));
        let mut w = ShardWriter::create_with(&path, order, options)?;
        // The first voxel boundary at or after the next shard's nominal start ends this one;
        // the last shard ends with the records announced.
        let end = bound(k + 1);
        while let Some(peeked) = records.peek() {
            let stop = match peeked {
                Ok(s) => index >= end && (k + 1 == ranks || Some(s.voxel) != last_voxel),
                Err(_) => false,
            };
            if stop {
                break;
            }
            let s = records.next().expect("a record was peeked")?;
            last_voxel = Some(s.voxel);
            w.push(&s)?;
            index += 1;
        }
        if index < end {
            return Err(failed(
                &path,
                format!("the input ended before the {total} records it announced"),
            ));
        }
        infos.push(w.finish()?);
    }
    if let Some(extra) = records.next() {
        extra?;
        return Err(failed(
            dir,
            format!("the input has more than the {total} records it announced"),
        ));
    }
    Ok(infos)
}

/// A CRC-32 over the encoded records of a sequence: equal digests and counts mean (but for a
/// 2^-32 chance) the same records in the same order.
#[derive(Clone, Default)]
pub struct Digest {
    hasher: crc32fast::Hasher,
    pub count: u64,
}

impl Digest {
    pub fn add(&mut self, s: &Surfel) {
        let mut b = [0u8; RECORD_LEN];
        record::encode_into(s, &mut b);
        self.hasher.update(&b);
        self.count += 1;
    }

    pub fn value(&self) -> (u64, u32) {
        (self.count, self.hasher.clone().finalize())
    }
}

/// The records of a set's shards in rank order, each shard's checksum checked as its last
/// record is read.
pub fn records_of(
    readers: &[ShardReader],
    buffer_bytes: usize,
) -> Result<impl Iterator<Item = Result<Surfel, ConvertError>>, ConvertError> {
    let iters = readers
        .iter()
        .map(|r| r.records(buffer_bytes))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(iters
        .into_iter()
        .flatten()
        .map(|r| r.map_err(ConvertError::from)))
}

/// The outcome of [`verify_set`].
#[derive(Debug, Default)]
pub struct Verification {
    /// Shards that passed every check.
    pub good: Vec<ShardInfo>,
    /// One line per problem, each naming its file.
    pub problems: Vec<String>,
    /// Files in the directory that the manifest does not list (not part of the set, so not a
    /// problem, but worth knowing: a leftover of another set, or a shard the manifest lost).
    pub unlisted: Vec<String>,
}

/// Checks every file of the shard set `dir` (see the module header). An unreadable manifest is
/// an error: nothing else can be checked without it.
pub fn verify_set(dir: &Path) -> Result<(Manifest, Verification), ConvertError> {
    if !dir.is_dir() {
        return Err(bad(dir, "is not a directory (a shard set is a directory)"));
    }
    let manifest = Manifest::read_dir(dir)?;
    let mut v = Verification::default();
    if let Ok(entries) = std::fs::read_dir(dir) {
        let listed: std::collections::HashSet<&str> =
            manifest.shards.iter().map(|s| s.file.as_str()).collect();
        v.unlisted = entries
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n != MANIFEST_FILE && !listed.contains(n.as_str()))
            .collect();
        v.unlisted.sort();
    }
    // The last voxel of the previous shard that could be read, for the order across shards.
    let mut previous: Option<(PathBuf, [i32; 3])> = None;
    for entry in &manifest.shards {
        let path = Manifest::shard_path(dir, entry);
        let mut first_last: Option<([i32; 3], [i32; 3])> = None;
        let checked = (|| -> Result<ShardInfo, StorageError> {
            let info = shard::verify(&path)?;
            let mismatch = entry.mismatch(&info, manifest.order);
            if let Some(what) = mismatch {
                return Err(StorageError::Invalid {
                    path: path.clone(),
                    what: format!(
                        "it is not the shard {MANIFEST_FILE} lists: it has {what} (a shard \
                         replaced, swapped or from another set)"
                    ),
                });
            }
            if info.count > 0 {
                let reader = ShardReader::open_lazy(&path)?;
                let first = read_at(&reader, 0)?;
                let last = read_at(&reader, info.count - 1)?;
                first_last = Some((first.voxel, last.voxel));
            }
            Ok(info)
        })();
        match checked {
            Ok(info) => {
                if let Some((first, last)) = first_last {
                    if let Some((prev_path, prev)) = &previous {
                        if order::sort_key(manifest.order, *prev)
                            > order::sort_key(manifest.order, first)
                        {
                            v.problems.push(format!(
                                "{}: its first voxel {first:?} sorts before the last voxel \
                                 {prev:?} of {} in order {}: the shards are out of order",
                                path.display(),
                                prev_path.display(),
                                manifest.order
                            ));
                        } else if manifest.voxel_aligned && *prev == first {
                            // The data mode out of core would slice a voxel's surfels apart.
                            v.problems.push(format!(
                                "{}: its first voxel {first:?} is also the last voxel of {},                                  but the manifest says no voxel is split over two shards",
                                path.display(),
                                prev_path.display(),
                            ));
                        }
                    }
                    previous = Some((path.clone(), last));
                }
                v.good.push(info);
            }
            Err(e) => v.problems.push(e.to_string()),
        }
    }
    Ok((manifest, v))
}

/// Record `index` of a shard already checked, read by seeking.
fn read_at(reader: &ShardReader, index: u64) -> Result<Surfel, StorageError> {
    use std::io::{Read, Seek, SeekFrom};
    let path = reader.path();
    let io = |e| StorageError::io(path, "read", e);
    let mut f = std::fs::File::open(path).map_err(io)?;
    f.seek(SeekFrom::Start(shard::record_offset(index)))
        .map_err(io)?;
    let mut b = [0u8; RECORD_LEN];
    f.read_exact(&mut b).map_err(io)?;
    Ok(record::decode(&b))
}

/// A summary of a set's manifest for people.
pub fn describe(dir: &Path, m: &Manifest) -> String {
    let mut t = String::new();
    let g = &m.grid;
    let [lo, hi] = m.bounds();
    let _ = writeln!(t, "shard set     {}", dir.display());
    let _ = writeln!(t, "format        {} version {}", m.format, m.format_version);
    let _ = writeln!(
        t,
        "grid          {} x {} x {} voxels of {} scene units",
        g.dims[0], g.dims[1], g.dims[2], g.voxel_size
    );
    let _ = writeln!(t, "voxel size    {}", g.voxel_size);
    let _ = writeln!(t, "origin        {:?}", g.origin);
    let _ = writeln!(t, "bounds        {lo:?} to {hi:?}");
    let _ = writeln!(
        t,
        "order         {} (axis signs {:?})",
        m.order,
        crate::geometry::order::signs(m.order)
    );
    let _ = writeln!(t, "normals       {}", m.normals.len());
    let _ = writeln!(t, "materials     {}", m.materials.len());
    for (i, mat) in m.materials.iter().enumerate() {
        let _ = writeln!(
            t,
            "  {i:>3}  {:<24} reflectance {:?} emission {:?}",
            mat.name, mat.reflectance, mat.emission
        );
    }
    let cut = if m.voxel_aligned {
        "at voxel boundaries"
    } else {
        "by count"
    };
    let _ = writeln!(t, "shards        {} (cut {cut})", m.shards.len());
    for (k, s) in m.shards.iter().enumerate() {
        let _ = writeln!(
            t,
            "  {k:>3}  {:<18} {:>12} records {:>14} bytes  crc32 {:#010x}",
            s.file, s.records, s.bytes, s.crc32
        );
    }
    let bytes: u64 = m.shards.iter().map(|s| s.bytes).sum();
    let _ = writeln!(
        t,
        "total         {} records, {} bytes ({})",
        m.records(),
        bytes,
        crate::outcore::budget::format_bytes(bytes)
    );
    let _ = writeln!(
        t,
        "(from {MANIFEST_FILE} alone; `voxrad-shard verify` checks the files)"
    );
    t
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::ShardEntry;
    use crate::voxel::Grid;

    fn surfels(n: i32) -> Vec<Surfel> {
        (0..n)
            .map(|k| Surfel {
                voxel: [k % 3, k / 3, 0],
                point: [0.5; 3],
                normal: [0.0, 0.0, 1.0],
                normal_id: 0,
                group: k as u32,
                area: 1.0,
                material: [0, 0],
                extent: [[0.0; 3], [1.0; 3]],
            })
            .collect::<Vec<_>>()
    }

    fn split(n: i32, ranks: usize) -> (tempfile::TempDir, Vec<ShardInfo>, Vec<Surfel>) {
        let mut v = surfels(n);
        v.sort_by_key(|s| shard::key(0, s));
        let (dir, infos) = split_sorted(&v, ranks);
        (dir, infos, v)
    }

    /// `v` (sorted) written into `ranks` shards in a new directory.
    fn split_sorted(v: &[Surfel], ranks: usize) -> (tempfile::TempDir, Vec<ShardInfo>) {
        let dir = tempfile::TempDir::new().unwrap();
        let total = v.len() as u64;
        let infos = write_split(v.iter().map(|s| Ok(*s)), total, ranks, dir.path(), 0, 4096);
        (dir, infos.unwrap())
    }

    #[test]
    fn split_counts_are_equal_to_one_and_contiguous() {
        let (dir, infos, v) = split(10, 3);
        let counts: Vec<u64> = infos.iter().map(|i| i.count).collect();
        assert_eq!(counts, [3, 3, 4]);
        let readers: Vec<ShardReader> = infos
            .iter()
            .map(|i| ShardReader::open(&i.path).unwrap())
            .collect();
        let back: Vec<Surfel> = records_of(&readers, 4096)
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(back, v);
        // More ranks than records: empty shards are valid and verify.
        let (dir2, infos, _) = split(2, 4);
        let counts: Vec<u64> = infos.iter().map(|i| i.count).collect();
        assert_eq!(counts, [0, 1, 0, 1]);
        let entries = infos
            .iter()
            .map(|i| ShardEntry::from_info(i).unwrap())
            .collect();
        let grid = Grid {
            origin: [0.0; 3],
            voxel_size: 1.0,
            dims: [3, 4, 1],
        };
        Manifest::new(grid, &[], vec![[0.0, 0.0, 1.0]], 0, entries)
            .write(dir2.path())
            .unwrap();
        let (_, v) = verify_set(dir2.path()).unwrap();
        assert!(v.problems.is_empty(), "{:?}", v.problems);
        drop(dir);
    }

    /// `n` surfels, `per_voxel` to a voxel, in order; split into `ranks` shards: their counts.
    fn split_counts(n: i32, per_voxel: usize, ranks: usize) -> Vec<u64> {
        let v: Vec<Surfel> = surfels(n)
            .into_iter()
            .enumerate()
            .map(|(k, s)| Surfel {
                voxel: [(k / per_voxel) as i32, 0, 0],
                ..s
            })
            .collect();
        split_sorted(&v, ranks).1.iter().map(|i| i.count).collect()
    }

    #[test]
    fn shards_begin_at_voxel_boundaries() {
        // Four surfels a voxel: the nominal cuts at 4 and 9 of 14 records fall at a boundary
        // and inside a voxel (records 8 to 11).
        assert_eq!(split_counts(14, 4, 3), [4, 8, 2]);
        // One voxel spanning a whole share leaves that share's shard empty.
        assert_eq!(split_counts(6, 5, 3), [5, 0, 1]);
    }

    #[test]
    fn verify_refuses_a_voxel_split_over_shards_where_the_manifest_says_none_is() {
        let v: Vec<Surfel> = surfels(4)
            .into_iter()
            .map(|s| Surfel {
                voxel: [1, 1, 0],
                ..s
            })
            .collect();
        for aligned in [false, true] {
            let dir = tempfile::TempDir::new().unwrap();
            let entries = v
                .chunks(2)
                .enumerate()
                .map(|(k, part)| {
                    let path = dir.path().join(shard_file_name(k));
                    let mut w = ShardWriter::create(&path, 0).unwrap();
                    part.iter().for_each(|s| w.push(s).unwrap());
                    ShardEntry::from_info(&w.finish().unwrap()).unwrap()
                })
                .collect();
            let grid = Grid {
                origin: [0.0; 3],
                voxel_size: 1.0,
                dims: [3, 4, 1],
            };
            let mut m = Manifest::new(grid, &[], vec![[0.0, 0.0, 1.0]], 0, entries);
            m.voxel_aligned = aligned;
            m.write(dir.path()).unwrap();
            let (_, report) = verify_set(dir.path()).unwrap();
            assert_eq!(
                report.problems.len(),
                aligned as usize,
                "{:?}",
                report.problems
            );
            if aligned {
                assert!(
                    report.problems[0].contains("split"),
                    "{:?}",
                    report.problems
                );
            }
        }
    }

    #[test]
    fn a_short_or_long_input_is_refused() {
        let dir = tempfile::TempDir::new().unwrap();
        let v = surfels(5);
        let e = write_split(v.iter().map(|s| Ok(*s)), 6, 2, dir.path(), 0, 4096).unwrap_err();
        assert!(e.to_string().contains("ended before"), "{e}");
        let e = write_split(v.iter().map(|s| Ok(*s)), 4, 2, dir.path(), 0, 4096).unwrap_err();
        assert!(e.to_string().contains("more than"), "{e}");
    }

    #[test]
    fn staging_refuses_what_is_not_a_set_and_replaces_a_set() {
        let tmp = tempfile::TempDir::new().unwrap();
        let file = tmp.path().join("file");
        std::fs::write(&file, "x").unwrap();
        assert!(matches!(
            Staging::new(&file),
            Err(ConvertError::BadInput(_))
        ));
        let deep = tmp.path().join("no/such/parent");
        assert!(matches!(
            Staging::new(&deep),
            Err(ConvertError::BadInput(_))
        ));
        // Replacing: the old directory goes, the new one takes its name.
        let target = tmp.path().join("set");
        for round in 0..2 {
            let staging = Staging::new(&target).unwrap();
            let grid = Grid {
                origin: [0.0; 3],
                voxel_size: 1.0 + round as f64,
                dims: [1, 1, 1],
            };
            Manifest::new(grid, &[], vec![], 0, vec![])
                .write(staging.path())
                .unwrap();
            staging.commit().unwrap();
            assert_eq!(
                Manifest::read_dir(&target).unwrap().grid.voxel_size,
                1.0 + round as f64
            );
        }
        let names: Vec<_> = std::fs::read_dir(tmp.path()).unwrap().collect();
        assert_eq!(names.len(), 2, "the file and the set only: {names:?}");
    }
}

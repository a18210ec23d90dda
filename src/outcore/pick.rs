//! Picking the surfels of given voxels out of a source: what each part of the direct-light pass
//! out of core reads (`outcore::direct`), the surfels on its emitters' lines.
//!
//! A part needs the voxels of a few directions' lines, often a twentieth of the scene or less,
//! and there are hundreds of parts, so what a pick costs is what the pass costs. Two ways:
//!
//! - [`by_stream`]: a pass over the whole stream, each record decoded and its voxel looked up
//!   among the wanted ones. Any source, any order; about 80 ns a record on a building of
//!   7 x 10^6 surfels, most of a part's time (`docs/out-of-core.md`).
//! - [`from_sorted_shards`]: a shard set sorted in the voxels' own order (`z`, then `y`, then
//!   `x`, ascending: order 0, what `voxrad-shard convert` writes) holds each voxel's records
//!   together at a place a search finds. The wanted voxels, sorted, are walked along the
//!   shards: for each, a search by steps that double from where the last one ended, reading
//!   only the voxel of the records it probes, then the voxel's records themselves. Records
//!   between wanted voxels are neither decoded nor, where the gaps are wide, read.
//!
//! Both hand the picked surfels over in canonical order with their canonical indices, and the
//! same surfels: the tests compare them. The searches read the shards without their checksum,
//! which the pass's first stream over the set has checked; each record picked is still checked
//! against the manifest ([`super::source::check_record`]).

use super::source::{check_record, SourceInfo, SurfelStream};
use super::OocError;
use crate::storage::shard::record_offset;
use crate::storage::{record, ShardReader, WindowedFile, RECORD_LEN};
use crate::voxel::Surfel;

/// Takes one picked surfel: its canonical index, the surfel, and the place in the wanted keys
/// of its voxel; `Ok(false)` stops the pick (a part that is full).
pub type Take<'a> = dyn FnMut(u64, Surfel, usize) -> Result<bool, OocError> + 'a;

/// A voxel's key, in the order of the voxels' own sort (`z`, `y`, `x`): the key of the
/// direct pass's voxel table (`solve::direct::VoxelTable::key`).
fn voxel_key(voxel: [i32; 3]) -> u64 {
    crate::solve::direct::VoxelTable::key(voxel)
}

/// The first place at or after `from` in `keys` (sorted) whose key is not below `key`, found by
/// steps that double from `from` and then halve: a few steps when it is near.
pub fn gallop(keys: &[u64], from: usize, key: u64) -> usize {
    let mut step = 1;
    let mut low = from;
    while low + step <= keys.len() && keys[low + step - 1] < key {
        low += step;
        step *= 2;
    }
    let high = (low + step).min(keys.len());
    low + keys[low..high].partition_point(|&k| k < key)
}

/// Picks the surfels of the voxels `keys` (sorted) from a whole stream; returns the bytes read
/// (every record's). A stream in the keys' order (a shard set) walks the keys along with it,
/// by [`gallop`]; where its order goes back (a scene voxelized in memory, in Morton order), a
/// search over all of them.
pub fn by_stream(
    stream: SurfelStream<'_>,
    keys: &[u64],
    take: &mut Take<'_>,
) -> Result<u64, OocError> {
    let (mut at, mut last) = (0, 0);
    let mut records = 0u64;
    for (id, s) in stream.enumerate() {
        let s = s?;
        records += 1;
        let key = voxel_key(s.voxel);
        if key < last {
            at = keys.partition_point(|&k| k < key);
        } else {
            at = gallop(keys, at, key);
        }
        last = key;
        if keys.get(at) == Some(&key) && !take(id as u64, s, at)? {
            break;
        }
    }
    Ok(records * RECORD_LEN as u64)
}

/// One shard as a sorted array of records, read through a window.
struct SortedShard<'a> {
    reader: &'a ShardReader,
    file: WindowedFile,
    count: u64,
    /// Bytes copied out of the file.
    read: u64,
}

impl SortedShard<'_> {
    /// The key of record `i`'s voxel (its first 12 bytes).
    fn key_at(&mut self, i: u64) -> Result<u64, OocError> {
        let mut bytes = [0u8; 12];
        self.file.read_exact_at(record_offset(i), &mut bytes)?;
        self.read += 12;
        let c = |k: usize| i32::from_le_bytes(bytes[4 * k..4 * k + 4].try_into().expect("4"));
        Ok(voxel_key([c(0), c(1), c(2)]))
    }

    /// The first record at or after `from` whose voxel's key is not below `key` (`count` if
    /// none), by steps that double from `from` and then a halving search.
    fn lower_bound(&mut self, from: u64, key: u64) -> Result<u64, OocError> {
        let mut step = 1;
        let mut low = from;
        while low + step <= self.count && self.key_at(low + step - 1)? < key {
            low += step;
            step *= 2;
        }
        let mut high = (low + step).min(self.count);
        // The answer lies in `low..=high`: every record before `low` is below `key`, and
        // record `high` (if any) is not.
        while low < high {
            let middle = low + (high - low) / 2;
            if self.key_at(middle)? < key {
                low = middle + 1;
            } else {
                high = middle;
            }
        }
        Ok(low)
    }

    /// Record `i`, decoded and checked against the set's manifest.
    fn record(&mut self, i: u64, info: &SourceInfo) -> Result<Surfel, OocError> {
        let mut bytes = [0u8; RECORD_LEN];
        self.file.read_exact_at(record_offset(i), &mut bytes)?;
        self.read += RECORD_LEN as u64;
        let s = record::decode(&bytes);
        check_record(info, &s).map_err(|what| OocError::BadData {
            source_name: self.reader.path().display().to_string(),
            what: format!(
                "record {i} {what}: the file is damaged; restore it from a copy or make the \
                 shard set again with `voxrad-shard convert`"
            ),
        })?;
        Ok(s)
    }
}

/// Picks the surfels of the voxels `keys` (sorted) from `shards`, each with its record count,
/// in canonical order, which must be the keys' order throughout (the caller checks the set's
/// order; a voxel may go on from one shard into the next). Returns the bytes read.
pub fn from_sorted_shards<'a>(
    shards: impl Iterator<Item = (&'a ShardReader, u64)>,
    info: &SourceInfo,
    keys: &[u64],
    window_bytes: u64,
    take: &mut Take<'_>,
) -> Result<u64, OocError> {
    let mut wanted = 0;
    let mut first_id = 0u64;
    let mut read = 0;
    for (reader, count) in shards {
        if wanted == keys.len() {
            break;
        }
        let mut shard = SortedShard {
            reader,
            file: WindowedFile::open(reader.path(), window_bytes)?,
            count,
            read: 0,
        };
        let mut at = 0u64;
        let stopped = loop {
            if wanted == keys.len() || at == count {
                break false;
            }
            let key = keys[wanted];
            at = shard.lower_bound(at, key)?;
            if at == count {
                break false;
            }
            let found = shard.key_at(at)?;
            if found != key {
                // No record of this voxel: on to the first wanted voxel from the one found.
                wanted = gallop(keys, wanted, found);
                continue;
            }
            let mut full = false;
            while at < count && shard.key_at(at)? == key {
                let s = shard.record(at, info)?;
                if !take(first_id + at, s, wanted)? {
                    full = true;
                    break;
                }
                at += 1;
            }
            if full {
                break true;
            }
            if at < count {
                wanted += 1;
            }
            // At the shard's end the voxel may go on in the next shard: it is looked for there.
        };
        read += shard.read;
        if stopped {
            break;
        }
        first_id += count;
    }
    Ok(read)
}

/// Whether the non-empty `shards`, each with its record count, follow one another in the
/// voxels' order: each one's first voxel not below the last one's before it (within a shard,
/// its order says so). A set cut otherwise is picked from by [`by_stream`].
pub fn shards_in_key_order(shards: &[(&ShardReader, u64)]) -> Result<bool, OocError> {
    let mut last: Option<u64> = None;
    for &(reader, count) in shards.iter().filter(|s| s.1 > 0) {
        let mut shard = SortedShard {
            reader,
            file: WindowedFile::open(reader.path(), 1)?,
            count,
            read: 0,
        };
        if last.is_some_and(|k| shard.key_at(0).is_ok_and(|first| first < k)) {
            return Ok(false);
        }
        last = Some(shard.key_at(count - 1)?);
    }
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::outcore::{ShardSetSource, SurfelSource};
    use crate::voxel::voxelize::{voxelize, GridSpec};

    /// What a pick handed over: canonical indices, the surfels' bits, the places of their keys.
    type Picked = Vec<(u64, Vec<u32>, usize)>;

    fn picked(
        pick: impl FnOnce(&mut Take<'_>) -> Result<u64, OocError>,
        stop_after: usize,
    ) -> Picked {
        let mut got = Vec::new();
        pick(&mut |id, s: Surfel, at| {
            let bits = [s.point, s.normal]
                .iter()
                .flatten()
                .map(|v| v.to_bits())
                .chain(s.voxel.map(|v| v as u32))
                .chain(s.material)
                .collect();
            got.push((id, bits, at));
            Ok(got.len() < stop_after)
        })
        .unwrap();
        got
    }

    /// A shard set cut into equal counts of records (a voxel may go on into the next shard),
    /// searched for sets of voxels of every density: the stream's surfels, indices and places,
    /// also when the taker stops early. Other orders are streamed.
    #[test]
    fn a_sorted_shard_set_is_searched_for_the_surfels_a_stream_finds() {
        let scene = crate::scene::obj::load_obj(std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/examples/cornell_box.obj"
        )))
        .unwrap();
        let set = voxelize(&scene, GridSpec::Resolution(20)).unwrap();
        let mut all: Vec<u64> = set.surfels.iter().map(|s| voxel_key(s.voxel)).collect();
        all.sort_unstable();
        all.dedup();
        // The sorted keys, record by record: where the cuts between shards fall.
        let mut sorted: Vec<u64> = set.surfels.iter().map(|s| voxel_key(s.voxel)).collect();
        sorted.sort_unstable();
        let mut split_voxels = 0;
        let tmp = tempfile::tempdir().unwrap();
        for (shards, order) in [(1, 0), (7, 0), (97, 0), (7, 1)] {
            let dir = tmp.path().join(format!("set-{shards}-{order}"));
            crate::storage::write_shard_set(&set, &dir, shards, order).unwrap();
            let per = sorted.len().div_ceil(shards);
            if order == 0 {
                split_voxels += (per..sorted.len())
                    .step_by(per)
                    .filter(|&cut| sorted[cut - 1] == sorted[cut])
                    .count();
            }
            let source = ShardSetSource::open(&dir).unwrap();
            let mut searched_any = false;
            for every in [1usize, 2, 3, 17, 400] {
                // Every `every`-th occupied voxel, with keys of empty voxels between them.
                let mut keys: Vec<u64> = all.iter().step_by(every).copied().collect();
                keys.extend(all.iter().step_by(every).map(|k| k + 1));
                keys.sort_unstable();
                keys.dedup();
                for stop_after in [usize::MAX, 5] {
                    let window = 1 << 16;
                    let streamed = picked(
                        |take| by_stream(source.stream(window)?, &keys, take),
                        stop_after,
                    );
                    let got = picked(|take| source.pick_voxels(&keys, window, take), stop_after);
                    assert!(!streamed.is_empty());
                    assert_eq!(
                        got, streamed,
                        "{shards} shards, order {order}, every {every}"
                    );
                    let read = source.pick_voxels(&keys, window, &mut |_, _, _| Ok(true));
                    let whole = set.surfels.len() as u64 * RECORD_LEN as u64;
                    searched_any |= read.unwrap() < whole;
                }
            }
            // Order 0 is searched (reading less than the whole set for sparse voxels); order 1,
            // not in the keys' order, is streamed.
            assert_eq!(searched_any, order == 0, "{shards} shards, order {order}");
        }
        assert!(
            split_voxels > 0,
            "no voxel went on from one shard into the next"
        );
    }

    #[test]
    fn gallop_finds_what_a_search_over_the_rest_finds() {
        let keys: Vec<u64> = (0..200u64).map(|k| k * 7 + k % 5).collect();
        assert!(keys.is_sorted());
        for from in [0, 1, 5, 63, 64, 150, 199, 200] {
            for key in 0..1450 {
                let want = from + keys[from..].partition_point(|&k| k < key);
                assert_eq!(gallop(&keys, from, key), want, "from {from}, key {key}");
            }
        }
    }
}

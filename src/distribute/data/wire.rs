//! How packs of surfels travel between ranks (a flag, the raw length, the bytes, compressed with
//! zstd where that pays) and how the sorted runs that arrive are merged into the octant order.

use crate::geometry::order;
use crate::solve::dispatch::OrderedEntry;
use std::cmp::Ordering;

/// Packs smaller than this are sent as they are.
pub(super) const COMPRESS_FROM: usize = 4096;

/// A pack on the wire: a flag byte (0 raw, 1 zstd), the raw length, the bytes. With `compress`,
/// a pack of at least [`COMPRESS_FROM`] bytes is compressed when that makes it 1/8 smaller.
pub(super) fn seal(raw: Vec<u8>, compress: bool) -> Vec<u8> {
    if raw.is_empty() {
        return raw;
    }
    let packed = if compress && raw.len() >= COMPRESS_FROM {
        zstd::bulk::compress(&raw, 1)
            .ok()
            .filter(|c| c.len() < raw.len() * 7 / 8)
    } else {
        None
    };
    let mut out = Vec::with_capacity(9 + packed.as_ref().map_or(raw.len(), Vec::len));
    out.push(packed.is_some() as u8);
    out.extend_from_slice(&(raw.len() as u64).to_le_bytes());
    out.extend_from_slice(packed.as_deref().unwrap_or(&raw));
    out
}

/// The raw bytes of a pack made by `seal`.
pub(super) fn unseal(sealed: &[u8]) -> Vec<u8> {
    if sealed.is_empty() {
        return Vec::new();
    }
    let mut len = [0u8; 8];
    len.copy_from_slice(&sealed[1..9]);
    let len = u64::from_le_bytes(len) as usize;
    if sealed[0] == 1 {
        zstd::bulk::decompress(&sealed[9..], len)
            .expect("a pack compressed by this program decompresses")
    } else {
        sealed[9..].to_vec()
    }
}

/// The order of the data mode: position in octant order `order`, then surfel id (the
/// single-process solver breaks ties by index, which is the id). The ids, read by place (a random
/// access), are compared only between surfels of one voxel.
#[inline]
pub(super) fn compare(order: usize, ids: &[u32], x: &OrderedEntry, y: &OrderedEntry) -> Ordering {
    order::sort_key(order, x.voxel)
        .cmp(&order::sort_key(order, y.voxel))
        .then_with(|| ids[x.index as usize].cmp(&ids[y.index as usize]))
}

/// Merges two runs sorted by `cmp` into one (ties: `a` first, never met since keys are unique).
pub(super) fn merge_two(
    a: &[OrderedEntry],
    b: &[OrderedEntry],
    cmp: impl Fn(&OrderedEntry, &OrderedEntry) -> Ordering,
) -> Vec<OrderedEntry> {
    let mut out = Vec::with_capacity(a.len() + b.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        if cmp(&b[j], &a[i]) == Ordering::Less {
            out.push(b[j]);
            j += 1;
        } else {
            out.push(a[i]);
            i += 1;
        }
    }
    out.extend_from_slice(&a[i..]);
    out.extend_from_slice(&b[j..]);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn large_packs_are_compressed_and_restored() {
        let raw: Vec<u8> = (0..100_000u32).map(|k| (k / 1000) as u8).collect();
        let sealed = seal(raw.clone(), true);
        assert!(sealed.len() < raw.len() / 4);
        assert_eq!(unseal(&sealed), raw);
        let plain = seal(raw.clone(), false);
        assert_eq!(plain.len(), raw.len() + 9);
        assert_eq!(unseal(&plain), raw);
    }
}

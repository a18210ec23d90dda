//! A hash map for `u64` keys in the solver's hot loops (voxel keys, the bits of a link's factor):
//! one multiply and two shifts per key, where the standard library's SipHash costs several
//! times that and its protection against chosen keys buys nothing for keys the solver makes.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

/// A map from `u64` keys hashed by [`MixHasher`].
pub(crate) type MixMap<V> = HashMap<u64, V, BuildHasherDefault<MixHasher>>;

/// Mixes a `u64` key so that both its high bits (the map's control bytes) and its low bits (the
/// bucket) depend on every bit of the key.
#[derive(Default)]
pub(crate) struct MixHasher(u64);

impl Hasher for MixHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(8) ^ b as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        }
    }

    fn write_u64(&mut self, v: u64) {
        let x = (v ^ (v >> 29)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        self.0 = x ^ (x >> 32);
    }
}

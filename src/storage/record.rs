//! The fixed-size on-disk surfel record: every shard file is a header, then these records, then
//! a footer (see [`super::shard`]).
//!
//! Fixed size so that record `k` of a shard sits at `HEADER_LEN + k * RECORD_LEN`: a reader checks
//! a file's length from its header alone, seeks without an index, and a memory-map window can
//! compute which records it holds. Little-endian on every platform, so a shard set written on one
//! machine is read unchanged on another. Encoding and decoding are plain byte copies through
//! `to_le_bytes`/`from_le_bytes`: no `unsafe`, no dependence on the in-memory layout of
//! [`Surfel`].
//!
//! ```text
//! record (80 bytes)
//!  offset size  field       type      meaning (see crate::voxel::Surfel)
//!   0     12    voxel       i32 x 3   integer voxel coordinates (x, y, z)
//!  12     12    point       f32 x 3   surface point inside the voxel, voxel units in [0, 1]
//!  24     12    normal      f32 x 3   unit normal of the front side
//!  36      4    normal_id   u32       index into the shard set's normal table (manifest)
//!  40      4    group       u32       plane group
//!  44      4    area        f32       surface area inside the voxel, in voxel_size^2
//!  48      8    material    u32 x 2   material index of the front and the back side (manifest)
//!  56     24    extent      f32 x 6   low corner (x, y, z) then high corner of the piece's
//!                                     bounding box, voxel units relative to the voxel
//! ```
//!
//! Floats are stored bit for bit, so a record decodes to exactly the surfel that was encoded
//! (NaN payloads included); validating values is the business of whoever made the surfels.

use crate::voxel::Surfel;

/// Size in bytes of one encoded record.
pub const RECORD_LEN: usize = 80;

/// Writes `s` into `out` in the layout of the module header.
pub fn encode_into(s: &Surfel, out: &mut [u8; RECORD_LEN]) {
    let words = s
        .voxel
        .iter()
        .map(|v| v.to_le_bytes())
        .chain(s.point.iter().map(|v| v.to_le_bytes()))
        .chain(s.normal.iter().map(|v| v.to_le_bytes()))
        .chain([
            s.normal_id.to_le_bytes(),
            s.group.to_le_bytes(),
            s.area.to_le_bytes(),
        ])
        .chain(s.material.iter().map(|v| v.to_le_bytes()))
        .chain(s.extent.iter().flatten().map(|v| v.to_le_bytes()));
    let mut written = 0;
    for (slot, word) in out.chunks_exact_mut(4).zip(words) {
        slot.copy_from_slice(&word);
        written += 4;
    }
    // Twenty 4-byte fields fill the record exactly; a field added to `Surfel` without a place in
    // the layout must not silently produce a short record.
    debug_assert_eq!(written, RECORD_LEN);
}

/// The encoded bytes of `s`.
pub fn encode(s: &Surfel) -> [u8; RECORD_LEN] {
    let mut out = [0u8; RECORD_LEN];
    encode_into(s, &mut out);
    out
}

/// The surfel stored in `bytes` (the inverse of [`encode`]).
pub fn decode(bytes: &[u8; RECORD_LEN]) -> Surfel {
    let word = |i: usize| {
        let at = 4 * i;
        [bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]
    };
    let i = |k: usize| i32::from_le_bytes(word(k));
    let u = |k: usize| u32::from_le_bytes(word(k));
    let f = |k: usize| f32::from_le_bytes(word(k));
    Surfel {
        voxel: [i(0), i(1), i(2)],
        point: [f(3), f(4), f(5)],
        normal: [f(6), f(7), f(8)],
        normal_id: u(9),
        group: u(10),
        area: f(11),
        material: [u(12), u(13)],
        extent: [[f(14), f(15), f(16)], [f(17), f(18), f(19)]],
    }
}

/// Decodes the first record of `bytes`, or `None` if it holds fewer than [`RECORD_LEN`] bytes.
pub fn decode_prefix(bytes: &[u8]) -> Option<Surfel> {
    bytes.first_chunk::<RECORD_LEN>().map(decode)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A deterministic pseudo-random generator (SplitMix64) for test data, so tests need no
    /// extra dependency and every run sees the same records.
    pub(crate) struct SplitMix(pub u64);

    impl SplitMix {
        pub(crate) fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        }

        /// Uniform in `[0, 1)`.
        pub(crate) fn unit(&mut self) -> f32 {
            (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
        }

        /// Uniform in `[lo, hi)`.
        pub(crate) fn range(&mut self, lo: i32, hi: i32) -> i32 {
            lo + (self.next_u64() % (hi - lo) as u64) as i32
        }
    }

    /// A random surfel with voxel coordinates in `[-span, span)`. Small spans give many equal
    /// keys, which is what exercises the tie rules.
    pub(crate) fn random_surfel(rng: &mut SplitMix, span: i32) -> Surfel {
        Surfel {
            voxel: [0; 3].map(|_| rng.range(-span, span)),
            point: [0; 3].map(|_| rng.unit()),
            normal: [0; 3].map(|_| rng.unit() * 2.0 - 1.0),
            normal_id: rng.next_u64() as u32 % 64,
            group: rng.next_u64() as u32,
            area: rng.unit() * 1.7,
            material: [rng.next_u64() as u32 % 8, rng.next_u64() as u32 % 8],
            extent: [
                [0; 3].map(|_| rng.unit() * 0.5),
                [0; 3].map(|_| 0.5 + rng.unit() * 0.5),
            ],
        }
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let mut rng = SplitMix(7);
        for _ in 0..1000 {
            let s = random_surfel(&mut rng, 1 << 30);
            assert_eq!(decode(&encode(&s)), s);
        }
        // Extreme values survive too, bit for bit.
        let mut s = random_surfel(&mut rng, 4);
        s.voxel = [i32::MIN, i32::MAX, -1];
        s.area = f32::NAN;
        s.normal_id = u32::MAX;
        let back = decode(&encode(&s));
        assert_eq!(back.voxel, s.voxel);
        assert_eq!(back.area.to_bits(), s.area.to_bits());
        assert_eq!(back.normal_id, u32::MAX);
    }

    #[test]
    fn layout_matches_the_documented_offsets() {
        let s = Surfel {
            voxel: [1, -2, 3],
            point: [0.25, 0.5, 0.75],
            normal: [0.0, 0.0, 1.0],
            normal_id: 5,
            group: 6,
            area: 1.5,
            material: [7, 8],
            extent: [[0.0, 0.1, 0.2], [0.9, 1.0, 0.3]],
        };
        let b = encode(&s);
        assert_eq!(b[4..8], (-2i32).to_le_bytes());
        assert_eq!(b[16..20], 0.5f32.to_le_bytes());
        assert_eq!(b[32..36], 1.0f32.to_le_bytes());
        assert_eq!(b[36..40], 5u32.to_le_bytes());
        assert_eq!(b[40..44], 6u32.to_le_bytes());
        assert_eq!(b[44..48], 1.5f32.to_le_bytes());
        assert_eq!(b[52..56], 8u32.to_le_bytes());
        assert_eq!(b[68..72], 0.9f32.to_le_bytes());
        assert_eq!(b[76..80], 0.3f32.to_le_bytes());
        assert_eq!(decode_prefix(&b[..79]), None);
        assert_eq!(decode_prefix(&b), Some(s));
    }
}

//! A rank's slice of the input (data mode out of core): about `n / P` surfels of the canonical
//! stream, both ends moved to the next voxel boundary so that voxel-mates (for the coverage)
//! stay together, written as held files with `B = E` (carried by the lines as it is).

use super::held::{self, Held, HeldWriter, WIRE_LEN};
use super::Solver;
use crate::outcore::budget::MemoryPlan;
use crate::outcore::files::{
    encode_radiosity, encode_static, IoCounters, StaticRecord, STATIC_LEN,
};
use crate::outcore::OocError;
use crate::solve::propagate::PropSurfel;
use crate::voxel::Surfel;
use std::path::Path;

/// The rank's slice of the input.
pub(super) struct Slice {
    pub held: Held,
    /// Canonical index of its first surfel.
    pub first: u64,
    pub voxels: u64,
    pub any_light: bool,
    /// Surfels with an emitting side (what the direct pass's decision reads).
    pub emitting: u64,
    /// Some material a surfel side of the slice uses has unequal channels (`solve::effects`).
    pub coloured: bool,
}

impl Solver<'_> {
    /// Reads this rank's slice of the source into held files (canonical order), with `B = E`.
    pub(super) fn read_slice(
        &self,
        plan: &MemoryPlan,
        dir: &Path,
        cosine_sum: &[f64],
        io: &mut IoCounters,
    ) -> Result<Slice, OocError> {
        let info = self.source.info();
        let n = info.count;
        // Every group holds the whole scene, sliced over its ranks.
        let (ranks, me) = (self.group.size() as u64, self.group.rank() as u64);
        // A slice starts at the first voxel boundary at or after its nominal start, and ends
        // where the next one starts: the voxel of the record before the nominal start decides.
        // A shard set cut by that rule into one shard per rank (`voxrad-shard convert --ranks`)
        // gives each rank its shard, read alone: its node needs no other.
        let parts = self.source.voxel_aligned_parts();
        let own_part = parts.filter(|p| p.len() as u64 == ranks + 1);
        let (lo, hi) = match &own_part {
            Some(p) => (p[me as usize], p[me as usize + 1]),
            None => (n * me / ranks, n * (me + 1) / ranks),
        };
        // Its own shard is read whole (its checksum is checked at its end) and no other; else
        // from the record before the nominal start on.
        let (stream, mut index) = match own_part {
            Some(_) => self.source.stream_between(lo, hi, plan.io_bytes as u64)?,
            None => self
                .source
                .stream_from(lo.saturating_sub(1), plan.io_bytes as u64)?,
        };
        // The direct light comes later (`direct::attach_direct`), into new files.
        let mut writer = HeldWriter::create(dir, 0, plan.io_bytes, None, false)?;
        let mut group: Vec<Surfel> = Vec::new();
        let mut first_id = 0u64;
        let mut previous: Option<[i32; 3]> = None;
        let mut inside = false;
        let mut slice = Slice {
            first: 0,
            held: Held::whole(Default::default(), 0, false),
            voxels: 0,
            any_light: false,
            emitting: 0,
            coloured: false,
        };
        for s in stream {
            let s = s?;
            let i = index;
            index += 1;
            io.read += crate::storage::RECORD_LEN as u64;
            let boundary = previous != Some(s.voxel);
            previous = Some(s.voxel);
            if i + 1 < lo {
                continue;
            }
            if boundary && i >= lo {
                if inside || (i >= hi) {
                    self.write_group(&group, first_id, &mut writer, cosine_sum, &mut slice)?;
                    group.clear();
                }
                if i >= hi {
                    break;
                }
                if !inside {
                    slice.first = i;
                }
                inside = true;
                first_id = i;
            }
            if inside {
                group.push(s);
            }
        }
        if inside {
            self.write_group(&group, first_id, &mut writer, cosine_sum, &mut slice)?;
        }
        let (held, _) = writer.finish(io)?;
        if !inside {
            // Empty: it would start at the next rank's start, or at the end.
            slice.first = index.min(n);
        }
        slice.held = held;
        Ok(slice)
    }

    /// Writes the held records of the surfels of one voxel, with canonical ids from `first_id`.
    fn write_group(
        &self,
        group: &[Surfel],
        first_id: u64,
        writer: &mut HeldWriter,
        cosine_sum: &[f64],
        slice: &mut Slice,
    ) -> Result<(), OocError> {
        if group.is_empty() {
            return Ok(());
        }
        let info = self.source.info();
        slice.voxels += 1;
        let props = PropSurfel::of_voxel(group, &info.materials);
        for (k, (s, prop)) in group.iter().zip(props).enumerate() {
            let mut w = [0u8; WIRE_LEN];
            let r = StaticRecord {
                prop,
                id: (first_id + k as u64) as u32,
            };
            let mut statics = [0u8; STATIC_LEN];
            encode_static(&r, &mut statics);
            w[..STATIC_LEN].copy_from_slice(&statics);
            // B = E, computed as the update computes it with no light gathered.
            let norm = cosine_sum[s.normal_id as usize];
            let mut b: [[f32; 3]; 2] = [[0.0; 3]; 2];
            for (side, b_side) in b.iter_mut().enumerate() {
                let m = &info.materials[s.material[side] as usize];
                slice.coloured |= !m.is_grey();
                for (ch, value) in b_side.iter_mut().enumerate() {
                    let e = m.emission[ch] as f32 as f64;
                    *value = (e + m.reflectance[ch] * 0.0 / norm) as f32;
                    slice.any_light |= m.emission[ch] > 0.0;
                }
            }
            // As the one-process out-of-core solver counts them (`solve::direct::emits`).
            let emission = s
                .material
                .map(|m| info.materials[m as usize].emission.map(|e| e as f32));
            slice.emitting += crate::solve::direct::emits(&emission) as u64;
            // The lines carry `B` until the direct pass, if it runs, makes it `B - E`.
            encode_radiosity(&b, &mut w[held::RADIOSITY_AT..]);
            encode_radiosity(&b, &mut w[held::CARRIED_AT..]);
            held::encode_scene_data(s.normal_id, s.area, s.material, &mut w);
            writer.write(&w)?;
        }
        Ok(())
    }
}

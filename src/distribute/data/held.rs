//! The surfels a rank holds in the data mode, in slots that stay put while the surfels stay, and
//! their form on the wire between ranks.

use crate::solve::dispatch::OrderedEntry;
use crate::solve::propagate::PropSurfel;

/// Bytes of one surfel on the wire: id (4), radiosity (24) and gathered light (48). Its
/// propagation data does not travel: every rank of this in-memory mode holds the whole scene's
/// (`DataSolver::surfels`), and finds it by id (it took 68 of 144 bytes).
pub const RECORD_BYTES: usize = 76;

/// The surfels a rank holds. Their data sits in slots that do not move while they stay (a
/// surfel that leaves frees its slot, one that arrives takes a free slot), and `order` lists the
/// live slots sorted along the current octant order: a direction moves and merges 16-byte
/// entries, not whole surfels. Propagation reads `prop` and `radiosity` by slot, as the lines'
/// members name them.
#[derive(Default)]
pub(super) struct Held {
    pub(super) ids: Vec<u32>,
    pub(super) prop: Vec<PropSurfel>,
    pub(super) radiosity: Vec<[[f32; 3]; 2]>,
    pub(super) acc: Vec<[[f64; 3]; 2]>,
    /// Slots of surfels that left.
    pub(super) free: Vec<u32>,
    /// The live slots (with their voxels) in the current order: what dispatch reads.
    pub(super) order: Vec<OrderedEntry>,
}

impl Held {
    pub(super) fn len(&self) -> usize {
        self.order.len()
    }

    /// Stores a surfel in a free slot (or a new one) and returns the slot.
    pub(super) fn store(
        &mut self,
        id: u32,
        prop: PropSurfel,
        radiosity: [[f32; 3]; 2],
        acc: [[f64; 3]; 2],
    ) -> u32 {
        match self.free.pop() {
            Some(slot) => {
                let k = slot as usize;
                self.ids[k] = id;
                self.prop[k] = prop;
                self.radiosity[k] = radiosity;
                self.acc[k] = acc;
                slot
            }
            None => {
                self.ids.push(id);
                self.prop.push(prop);
                self.radiosity.push(radiosity);
                self.acc.push(acc);
                (self.ids.len() - 1) as u32
            }
        }
    }

    /// Appends the surfel in slot `slot` in wire form (little-endian, the layout `decode_all`
    /// reads).
    pub(super) fn encode(&self, slot: u32, out: &mut Vec<u8>) {
        let i = slot as usize;
        out.extend_from_slice(&self.ids[i].to_le_bytes());
        for f in self.radiosity[i].iter().flatten() {
            out.extend_from_slice(&f.to_le_bytes());
        }
        for a in self.acc[i].iter().flatten() {
            out.extend_from_slice(&a.to_le_bytes());
        }
    }

    /// Stores the surfels of a pack made by `encode`, their propagation data taken from `props`
    /// (by id); appends their entries, in pack order, to `entries`.
    pub(super) fn decode_all(
        &mut self,
        bytes: &[u8],
        props: &[PropSurfel],
        entries: &mut Vec<OrderedEntry>,
    ) {
        for r in bytes.chunks_exact(RECORD_BYTES) {
            let u = |k: usize| u32::from_le_bytes([r[k], r[k + 1], r[k + 2], r[k + 3]]);
            let f = |k: usize| f32::from_bits(u(k));
            let d = |k: usize| {
                let mut b = [0u8; 8];
                b.copy_from_slice(&r[k..k + 8]);
                f64::from_le_bytes(b)
            };
            let f3 = |k: usize| [f(k), f(k + 4), f(k + 8)];
            let d3 = |k: usize| [d(k), d(k + 8), d(k + 16)];
            let id = u(0);
            let prop = props[id as usize];
            let slot = self.store(id, prop, [f3(4), f3(16)], [d3(28), d3(52)]);
            entries.push(OrderedEntry {
                voxel: prop.voxel,
                index: slot,
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::distribute::data::wire::{seal, unseal};

    #[test]
    fn records_survive_the_wire() {
        let mut held = Held::default();
        let blank = PropSurfel {
            voxel: [0; 3],
            group: 0,
            point: [0.0; 3],
            normal: [0.0; 3],
            extent: [[0.0; 3]; 2],
            coverage: 0.0,
        };
        let mut props = vec![blank; 29];
        for k in 0..5u32 {
            let f = k as f32 + 0.25;
            let prop = PropSurfel {
                voxel: [k as i32, -(k as i32), 3],
                group: k + 100,
                point: [f, f * 2.0, f * 3.0],
                normal: [0.0, 1.0, -f],
                extent: [[0.1, 0.2, 0.3], [f, 0.5, 0.6]],
                coverage: 0.75,
            };
            let radiosity = [[f, 1.0, 2.0], [3.0, 4.0, f]];
            let acc = [[1e-300, f as f64, 2.5], [f64::MAX, 0.0, -1.0]];
            props[(k * 7) as usize] = prop;
            held.store(k * 7, prop, radiosity, acc);
        }
        for compress in [false, true] {
            let mut bytes = Vec::new();
            for slot in 0..5 {
                held.encode(slot, &mut bytes);
            }
            assert_eq!(bytes.len(), 5 * RECORD_BYTES);
            let mut back = Held::default();
            // A freed slot is taken first.
            back.store(99, held.prop[0], held.radiosity[0], held.acc[0]);
            back.free.push(0);
            let mut entries = Vec::new();
            back.decode_all(&unseal(&seal(bytes, compress)), &props, &mut entries);
            let slots: Vec<u32> = entries.iter().map(|e| e.index).collect();
            assert_eq!(slots, [0, 1, 2, 3, 4]);
            assert_eq!(back.ids, held.ids);
            assert_eq!(back.prop, held.prop);
            assert_eq!(back.radiosity, held.radiosity);
            assert_eq!(back.acc, held.acc);
        }
    }
}

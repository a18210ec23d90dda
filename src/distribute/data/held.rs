//! The surfels a rank has met in the data mode, with their radiosity and this rank's part of
//! their light, and the list of those its lines hold for the current direction; their form on
//! the wire between ranks.

use crate::checkpoint::{Gathered, Radiosity};
use crate::solve::dispatch::OrderedEntry;
use crate::solve::propagate::PropSurfel;

/// Bytes of one surfel on the wire: id (4) and radiosity (24). Its propagation data does not
/// travel (every rank of this in-memory mode holds the whole scene's, and finds it by id), nor
/// does its light: each rank keeps its own part of it (`Held::acc`).
pub const RECORD_BYTES: usize = 28;

/// Every surfel a rank's lines have held in some direction, each in a place of its own that it
/// keeps for the rest of the solve (so that the links, numbered by place, replay straight
/// into these arrays), and `order`: the places the current direction's lines hold, in its
/// octant order (what dispatch reads).
///
/// A surfel's light is not carried from rank to rank: each rank adds what its lines gather to
/// its own part (`acc`), and the parts are added at the end of the iteration, on the rank that
/// owns the surfel's radiosity (`DataSolver::reduce`). So after the first iteration, whose
/// exchanges bring every surfel a rank will meet, an iteration whose links are kept moves
/// nothing until its end.
pub(super) struct Held {
    /// By place: the surfel's id, propagation data, radiosity and this rank's light.
    pub(super) ids: Vec<u32>,
    pub(super) prop: Vec<PropSurfel>,
    pub(super) radiosity: Vec<Radiosity>,
    /// `B - E` by place, what the lines carry when the direct-light pass runs (else empty).
    pub(super) reflected: Vec<Radiosity>,
    keeps_reflected: bool,
    pub(super) acc: Vec<Gathered>,
    /// The place of every surfel id (`u32::MAX`: not met).
    place_of: Vec<u32>,
    /// The places the current direction's lines hold, in its order.
    pub(super) order: Vec<OrderedEntry>,
}

impl Held {
    /// No surfel met yet, of a scene of `surfels`; `direct`: keep `reflected`.
    pub(super) fn new(surfels: usize, direct: bool) -> Self {
        Held {
            ids: Vec::new(),
            prop: Vec::new(),
            radiosity: Vec::new(),
            reflected: Vec::new(),
            keeps_reflected: direct,
            acc: Vec::new(),
            place_of: vec![u32::MAX; surfels],
            order: Vec::new(),
        }
    }

    pub(super) fn len(&self) -> usize {
        self.order.len()
    }

    /// Surfels met so far.
    pub(super) fn met(&self) -> usize {
        self.ids.len()
    }

    /// What the lines carry by place (the radiosity, or `B - E` with the direct pass), and this
    /// rank's light, which replays add to.
    pub(super) fn carried_and_light(&mut self) -> (&[Radiosity], &mut [Gathered]) {
        let carried = if self.keeps_reflected {
            &self.reflected
        } else {
            &self.radiosity
        };
        (carried, &mut self.acc)
    }

    /// The place of surfel `id`, if met.
    pub(super) fn place(&self, id: u32) -> Option<u32> {
        let p = self.place_of[id as usize];
        (p != u32::MAX).then_some(p)
    }

    /// The place of surfel `id`, meeting it (with this radiosity and no light yet) if new.
    /// `emission` is its emission, for `reflected`.
    pub(super) fn meet(
        &mut self,
        id: u32,
        prop: PropSurfel,
        radiosity: Radiosity,
        emission: &Radiosity,
    ) -> u32 {
        if let Some(p) = self.place(id) {
            return p;
        }
        let p = self.ids.len() as u32;
        self.place_of[id as usize] = p;
        self.ids.push(id);
        self.prop.push(prop);
        self.radiosity.push(radiosity);
        if self.keeps_reflected {
            self.reflected
                .push(crate::solve::update::reflected_part(&radiosity, emission));
        }
        self.acc.push([[0.0; 3]; 2]);
        p
    }

    /// Sets the radiosity of the surfel at `place` (and what its lines carry).
    pub(super) fn set_radiosity(
        &mut self,
        place: usize,
        radiosity: Radiosity,
        emission: &Radiosity,
    ) {
        self.radiosity[place] = radiosity;
        if self.keeps_reflected {
            self.reflected[place] = crate::solve::update::reflected_part(&radiosity, emission);
        }
    }

    /// Appends the surfel at `place` in wire form (little-endian, the layout `decode_all`
    /// reads).
    pub(super) fn encode(&self, place: u32, out: &mut Vec<u8>) {
        let i = place as usize;
        out.extend_from_slice(&self.ids[i].to_le_bytes());
        for f in self.radiosity[i].iter().flatten() {
            out.extend_from_slice(&f.to_le_bytes());
        }
    }

    /// Meets the surfels of a pack made by `encode` (their propagation data from `props`, their
    /// emission from `emission`, by id) and appends their entries, in pack order, to `entries`.
    pub(super) fn decode_all(
        &mut self,
        bytes: &[u8],
        props: &[PropSurfel],
        emission: &[Radiosity],
        entries: &mut Vec<OrderedEntry>,
    ) {
        for r in bytes.chunks_exact(RECORD_BYTES) {
            let id = u32::from_le_bytes([r[0], r[1], r[2], r[3]]);
            let place = match self.place(id) {
                Some(p) => p,
                None => {
                    let f = |k: usize| f32::from_le_bytes([r[k], r[k + 1], r[k + 2], r[k + 3]]);
                    let radiosity = [[f(4), f(8), f(12)], [f(16), f(20), f(24)]];
                    self.meet(id, props[id as usize], radiosity, &emission[id as usize])
                }
            };
            entries.push(OrderedEntry {
                voxel: props[id as usize].voxel,
                index: place,
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::distribute::data::wire::{seal, unseal};

    fn prop(k: u32) -> PropSurfel {
        let f = k as f32 + 0.25;
        PropSurfel {
            voxel: [k as i32, -(k as i32), 3],
            group: k + 100,
            point: [f, f * 2.0, f * 3.0],
            normal: [0.0, 1.0, -f],
            extent: [[0.1, 0.2, 0.3], [f, 0.5, 0.6]],
            coverage: 0.75,
            inside_back: k % 3 == 0,
            no_area: k % 5 == 0,
            rank: (k % 7) as u8,
            mate_sides: (k * 37) as u16,
        }
    }

    /// Surfels sent keep their id and radiosity; one met already keeps its place and its part
    /// of the light; the lines carry `B - E` when the direct pass runs.
    #[test]
    fn records_survive_the_wire_and_met_surfels_keep_their_place() {
        let props: Vec<PropSurfel> = (0..29).map(prop).collect();
        let emission: Vec<Radiosity> = (0..29).map(|k| [[k as f32 * 0.125; 3], [0.0; 3]]).collect();
        let mut sender = Held::new(29, false);
        for id in [0u32, 7, 14, 21, 28] {
            let f = id as f32 + 0.5;
            sender.meet(
                id,
                props[id as usize],
                [[f, 1.0, 2.0], [3.0, 4.0, f]],
                &emission[0],
            );
        }
        for compress in [false, true] {
            let mut bytes = Vec::new();
            for place in 0..5 {
                sender.encode(place, &mut bytes);
            }
            assert_eq!(bytes.len(), 5 * RECORD_BYTES);
            let mut back = Held::new(29, true);
            // Surfel 14 was met before, with light of its own.
            let before = back.meet(14, props[14], sender.radiosity[2], &emission[14]);
            back.acc[before as usize] = [[1.5; 3]; 2];
            let mut entries = Vec::new();
            back.decode_all(
                &unseal(&seal(bytes, compress)),
                &props,
                &emission,
                &mut entries,
            );
            let places: Vec<u32> = entries.iter().map(|e| e.index).collect();
            assert_eq!(places, [1, 2, 0, 3, 4]);
            assert_eq!(back.ids, [14, 0, 7, 21, 28]);
            for (e, id) in entries.iter().zip([0usize, 7, 14, 21, 28]) {
                let p = e.index as usize;
                assert_eq!(e.voxel, props[id].voxel);
                assert_eq!(back.prop[p], props[id]);
                assert_eq!(back.place(id as u32), Some(e.index));
                let sent = sender.radiosity[sender.place(id as u32).unwrap() as usize];
                assert_eq!(back.radiosity[p], sent);
                let e_id = emission[id];
                let carried = crate::solve::update::reflected_part(&sent, &e_id);
                assert_eq!(back.reflected[p], carried);
            }
            assert_eq!(back.acc[0], [[1.5; 3]; 2]);
            assert_eq!(back.acc[1], [[0.0; 3]; 2]);
            assert_eq!(back.place(1), None);
        }
    }
}

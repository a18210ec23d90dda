//! What names a run in its checkpoints: the solver, the scene, the grid, the directions and the
//! settings that change the answer, with checksums of the scene and the direction set.

use super::*;

/// Which solver wrote a checkpoint (their surfel orders differ).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Solver {
    InMemory = 1,
    OutOfCore = 2,
}

impl Solver {
    fn name(self) -> &'static str {
        match self {
            Solver::InMemory => "the in-memory solver",
            Solver::OutOfCore => "the out-of-core solver (a shard set or --memory)",
        }
    }
}

/// What a checkpoint must match to be continued from.
#[derive(Clone, Debug, PartialEq)]
pub struct Identity {
    pub solver: Solver,
    pub surfels: u64,
    pub dims: [u32; 3],
    pub voxel_size: f64,
    pub directions: u32,
    /// CRC-32 of the direction vectors and their solid angles.
    pub directions_checksum: u32,
    /// Channels solved (1 for a grey scene solved once, else 3).
    pub channels: u32,
    /// Tail extrapolation on.
    pub accelerate: bool,
    /// The Chebyshev semi-iteration allowed (`--chebyshev`; format version 6, false before).
    pub chebyshev: bool,
    /// CRC-32 of the voxelized scene (see [`scene_checksum`]) or of the shard set.
    pub scene_checksum: u32,
}

impl Identity {
    /// The identity of an in-memory solve of `set` over `directions`.
    pub fn in_memory(
        set: &SurfelSet,
        directions: &DirectionSet,
        channels: usize,
        accelerate: bool,
    ) -> Self {
        Identity {
            solver: Solver::InMemory,
            surfels: set.surfels.len() as u64,
            dims: set.grid.dims,
            voxel_size: set.grid.voxel_size,
            directions: directions.len() as u32,
            directions_checksum: directions_checksum(directions),
            channels: channels as u32,
            accelerate,
            chebyshev: false,
            scene_checksum: scene_checksum(&set.grid, &set.normals, &set.materials, |h| {
                set.surfels.iter().for_each(|s| hash_surfel(h, s))
            }),
        }
    }

    /// The identity of a solve that also runs the direct-light pass over `dense` (see
    /// `solve::direct`): its direct light changes every iteration's answer, so its direction set
    /// joins the directions' checksum.
    pub fn with_direct_pass(mut self, dense: Option<&DirectionSet>) -> Self {
        if let Some(dense) = dense {
            let mut h = crc32fast::Hasher::new();
            h.update(&self.directions_checksum.to_le_bytes());
            h.update(b"direct");
            h.update(&directions_checksum(dense).to_le_bytes());
            self.directions_checksum = h.finalize();
        }
        self
    }

    /// The identity of a solve that may run the Chebyshev semi-iteration (see
    /// `solve::accelerate`): it iterates differently from one that may not.
    pub fn with_chebyshev(mut self, chebyshev: bool) -> Self {
        self.chebyshev = chebyshev;
        self
    }

    /// How `self` (the checkpoint's) differs from `this` (the run's), in words.
    pub(super) fn mismatch(&self, this: &Identity) -> Option<String> {
        if self.solver != this.solver {
            return Some(format!(
                "it was written by {}, and this run uses {}",
                self.solver.name(),
                this.solver.name()
            ));
        }
        if self.dims != this.dims || self.voxel_size != this.voxel_size {
            let [a, b, c] = self.dims;
            let [x, y, z] = this.dims;
            return Some(format!(
                "it is for a grid of {a} x {b} x {c} voxels of {}, and this run's is {x} x {y} x \
                 {z} voxels of {} (another --resolution or --voxel-size?)",
                self.voxel_size, this.voxel_size
            ));
        }
        if self.directions != this.directions {
            return Some(format!(
                "it is for {} directions, and this run uses {} (another --directions or \
                 --quality?)",
                self.directions, this.directions
            ));
        }
        if self.directions_checksum != this.directions_checksum {
            return Some(format!(
                "it is for {} directions but another direction set or direct-light pass \
                 (another --direct-directions or --quality?)",
                self.directions
            ));
        }
        if self.surfels != this.surfels || self.scene_checksum != this.scene_checksum {
            return Some(format!(
                "it is for another scene ({} surfels, checksum {:#010x}; this run: {} surfels, \
                 checksum {:#010x})",
                self.surfels, self.scene_checksum, this.surfels, this.scene_checksum
            ));
        }
        if self.channels != this.channels || self.accelerate != this.accelerate {
            return Some(format!(
                "it was made with {} channel(s) and extrapolation {}, and this run has {} and {} \
                 (another --quality, --iterations or --tolerance?)",
                self.channels,
                if self.accelerate { "on" } else { "off" },
                this.channels,
                if this.accelerate { "on" } else { "off" }
            ));
        }
        if self.chebyshev != this.chebyshev {
            let on = |c: bool| if c { "with" } else { "without" };
            return Some(format!(
                "it was made {} the Chebyshev semi-iteration, and this run is {} it \
                 (--chebyshev, --no-chebyshev: on in every --quality preset)",
                on(self.chebyshev),
                on(this.chebyshev)
            ));
        }
        None
    }
}

/// CRC-32 of a direction set: the integer vectors and the solid angles' bits.
pub fn directions_checksum(directions: &DirectionSet) -> u32 {
    let mut h = crc32fast::Hasher::new();
    for d in &directions.directions {
        for v in d.vector {
            h.update(&v.to_le_bytes());
        }
        h.update(&d.solid_angle.to_bits().to_le_bytes());
    }
    h.finalize()
}

/// CRC-32 of everything of a voxelized scene that the radiosity depends on: the grid, the
/// normal table, the materials, and every surfel (fed by `surfels`, in solver order).
pub fn scene_checksum(
    grid: &Grid,
    normals: &[[f32; 3]],
    materials: &[Material],
    surfels: impl FnOnce(&mut crc32fast::Hasher),
) -> u32 {
    let mut h = crc32fast::Hasher::new();
    for o in grid.origin {
        h.update(&o.to_bits().to_le_bytes());
    }
    h.update(&grid.voxel_size.to_bits().to_le_bytes());
    for d in grid.dims {
        h.update(&d.to_le_bytes());
    }
    for n in normals.iter().flatten() {
        h.update(&n.to_bits().to_le_bytes());
    }
    for m in materials {
        for v in m.reflectance.iter().chain(&m.emission) {
            h.update(&v.to_bits().to_le_bytes());
        }
    }
    surfels(&mut h);
    h.finalize()
}

/// Feeds one surfel's fields to a scene checksum.
pub fn hash_surfel(h: &mut crc32fast::Hasher, s: &Surfel) {
    let mut b = [0u8; 80];
    let mut at = 0;
    let mut put = |w: [u8; 4]| {
        b[at..at + 4].copy_from_slice(&w);
        at += 4;
    };
    s.voxel.iter().for_each(|v| put(v.to_le_bytes()));
    s.point
        .iter()
        .chain(&s.normal)
        .chain(std::iter::once(&s.area))
        .chain(s.extent.iter().flatten())
        .for_each(|v| put(v.to_bits().to_le_bytes()));
    [s.normal_id, s.group, s.material[0], s.material[1]]
        .iter()
        .for_each(|v| put(v.to_le_bytes()));
    h.update(&b[..at]);
}

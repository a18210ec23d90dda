//! Surface voxels and the surface elements (surfels) they hold.
//!
//! The voxelizer (`voxelize`) turns a [`crate::scene::Scene`] into a [`SurfelSet`]: a [`Grid`]
//! (origin, voxel size, dimensions) and a list of [`Surfel`]s. A surfel is the part of one plane
//! group (coplanar triangles, see `voxelize`) inside one voxel: a voxel where two walls meet holds
//! two surfels, a corner voxel three. Surfels are two-sided: side 0 ("front") faces along
//! `normal` and is the side its triangles face; side 1 ("back") faces along `-normal`. Each side
//! has its own material and radiosity.
//!
//! Positions inside the solver are in voxel units: voxel `v` covers `[v, v + 1)` on each axis and
//! a surfel's surface point is `v + point`. World position = `grid.origin + (v + point) * voxel_size`.

pub(crate) mod disjoint;
mod enclosed;
pub(crate) mod polygon;
mod solids;
pub mod voxelize;

use glam::DVec3;

/// A voxel's three coordinates packed 21 bits each into one `u64` (a key for the solver's fast
/// hash map, `solve::mix_hash`), or `None` outside `0..2^21`, where no grid reaches
/// (`voxelize::MAX_GRID_EDGE` is 2^20): a look-up there finds nothing.
pub fn packed_voxel(voxel: [i32; 3]) -> Option<u64> {
    const BITS: u32 = 21;
    let mut key = 0u64;
    for c in voxel {
        if !(0..1 << BITS).contains(&c) {
            return None;
        }
        key = key << BITS | c as u64;
    }
    Some(key)
}

/// The voxel grid: world position of voxel `(0, 0, 0)`'s low corner, the edge length of a voxel,
/// and the number of voxels along each axis.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Grid {
    pub origin: [f64; 3],
    pub voxel_size: f64,
    pub dims: [u32; 3],
}

impl Grid {
    /// World position of a point given in voxel units.
    pub fn to_world(&self, p: DVec3) -> DVec3 {
        DVec3::from(self.origin) + p * self.voxel_size
    }

    /// Voxel-unit position of a world point.
    pub fn to_voxel_units(&self, p: DVec3) -> DVec3 {
        (p - DVec3::from(self.origin)) / self.voxel_size
    }
}

/// Side index of the front side (facing along the surfel normal).
pub const FRONT: usize = 0;
/// Side index of the back side (facing along minus the surfel normal).
pub const BACK: usize = 1;

/// One surface element: the piece of one plane group inside one voxel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Surfel {
    /// Integer voxel coordinates.
    pub voxel: [i32; 3],
    /// Surface point relative to the voxel's low corner, in voxel units, each in `[0, 1]`.
    pub point: [f32; 3],
    /// Unit normal of the front side (equal to `normals.get(normal_id)`).
    pub normal: [f32; 3],
    /// Index into the set's normal table.
    pub normal_id: u32,
    /// Plane group: surfels with the same group lie on one plane and never light each other.
    pub group: u32,
    /// Area of surface inside the voxel, in voxel-size squared (0 for a voxel only touched).
    pub area: f32,
    /// Material index of the front and the back side.
    pub material: [u32; 2],
    /// Bounding box of the surface piece inside the voxel (low and high corner, voxel units
    /// relative to the voxel's low corner). Tells at an edge whether the piece lies on one side of
    /// a neighbouring plane or runs through it (a T-junction).
    pub extent: [[f32; 3]; 2],
}

/// Absolute position (voxel units) of a point given as a voxel and an offset inside it.
pub fn absolute_position(voxel: [i32; 3], point: [f32; 3]) -> DVec3 {
    DVec3::new(
        voxel[0] as f64 + point[0] as f64,
        voxel[1] as f64 + point[1] as f64,
        voxel[2] as f64 + point[2] as f64,
    )
}

/// The normal of side `side` (FRONT or BACK) of a surface whose front normal is `normal`.
pub fn oriented_normal(normal: [f32; 3], side: usize) -> DVec3 {
    let n = DVec3::new(normal[0] as f64, normal[1] as f64, normal[2] as f64);
    if side == FRONT {
        n
    } else {
        -n
    }
}

impl Surfel {
    /// The surface point in voxel units (absolute).
    pub fn position(&self) -> DVec3 {
        absolute_position(self.voxel, self.point)
    }

    /// Unit normal of side `side` (FRONT or BACK).
    pub fn side_normal(&self, side: usize) -> DVec3 {
        oriented_normal(self.normal, side)
    }
}

/// The voxelized scene: grid, surfels and the tables they index.
#[derive(Clone, Debug)]
pub struct SurfelSet {
    pub grid: Grid,
    pub surfels: Vec<Surfel>,
    /// Distinct unit normals; `Surfel::normal_id` indexes it.
    pub normals: Vec<[f32; 3]>,
    /// Materials, as in the scene.
    pub materials: Vec<crate::scene::Material>,
}

impl SurfelSet {
    /// Number of distinct voxels (surfels sharing a voxel count once). Surfels are grouped by
    /// voxel after voxelization, so equal voxels are adjacent.
    pub fn voxel_count(&self) -> usize {
        let mut count = 0;
        let mut last: Option<[i32; 3]> = None;
        for s in &self.surfels {
            if last != Some(s.voxel) {
                count += 1;
                last = Some(s.voxel);
            }
        }
        count
    }
}

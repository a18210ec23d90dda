//! Tunnel-free surface voxelization into surfels.
//!
//! A voxel `v` holds a surface when a triangle meets the cube `[v, v + 1]` other than only on
//! its three *far* faces (those where the plane's coordinate `n.x` is largest). For a plane this
//! selects the *standard* digital plane `{mu <= n.v < mu + |n|_1}`, which has no 26-tunnel: two
//! 26-neighbours differ in `n.v` by at most `|n|_1`, so no 26-connected discrete line can cross the
//! surface without containing one of its voxels, and light cannot leak through walls (the naive
//! plane, thinner, leaks along diagonals). Voxels a triangle only touches on a near face, edge or
//! corner are kept (with zero area).
//!
//! Triangles are grouped into **plane groups**: coplanar triangles (same unoriented plane, to
//! 1e-6 in the normal and 1e-4 voxel in the offset) share a group whatever side they face. Each
//! (voxel, group) pair becomes one [`Surfel`] whose surface point is the area-weighted centroid of
//! the group's triangles clipped to the voxel (the mean contact point for zero area). So a voxel on
//! the edge of two walls holds two surfels, a corner voxel three, and a thin two-sided sheet (a
//! single quad lit from both sides) one surfel with two sides. The surfel's front is the side its
//! triangles face and takes one of their materials, drawn by area share where there are several
//! (`drawn_material`: a window's rim in its wall); its back takes the same
//! reflectance without emission (emission leaves the front of a triangle only), or, where every
//! triangle of the surfel is a face of a closed solid wound outward with nothing inside it
//! (`enclosed`), the black material `Material::inside_of_solids`, whose side sees nothing and is
//! never searched from (`mark_inside`). Where triangles of
//! one plane face both ways in one voxel (two solids pressed together, a sheet modelled twice back
//! to back), each facing gets its own surfel with its own piece: merging them would put the surface
//! point where neither piece is, and rays would be misjudged at the seam. Where either facing is
//! a solid's face, the two are in contact and each keeps only what the other does not cover; a
//! solid standing on a plane without a face on it hides the plane's part behind its faces
//! (`merge_voxel`; `solids` tells a solid's faces). Where neither is, the sheet is modelled
//! twice: each facing's back side, when the other facing covers most of it, faces into the other
//! copy and takes `Material::inside_of_solids` (`mark_doubled`), so the sheet is seen, lit and
//! counted once.
//!
//! Numbering: plane groups and their normals are numbered in triangle order; the flipped normals
//! of back-facing surfels and the unlit copies of emitting materials are fixed before any surfel
//! is made ([`Tables`]), and the pieces of a surfel are merged in a fixed order (their key ends in
//! the triangle index). So the surfels are a function of the scene alone, and the out-of-core
//! conversion (`convert::stream`), which meets them in another order, makes exactly the same ones.
//!
//! Not done here: triangles of a finely tessellated curved surface are not merged, so a voxel may
//! hold several surfels of nearly parallel planes; they behave correctly (they do not light each
//! other) but cost memory.

use super::polygon::{
    clip, clip_to_unit_cube, contains, outside_of, polygon_area_centroid, NEGLIGIBLE_AREA,
};
use super::{Grid, Surfel, SurfelSet, BACK, FRONT};
use crate::scene::{Material, Scene};
use glam::DVec3;
use rayon::prelude::*;
use std::collections::HashMap;

/// How the grid is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum GridSpec {
    /// This many voxels along the longest side of the scene's bounds (at least 2).
    Resolution(u32),
    /// Voxel edge length in scene units.
    VoxelSize(f64),
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum VoxelizeError {
    #[error("resolution {0} is too small: use at least 2 voxels along the longest side")]
    ResolutionTooSmall(u32),
    #[error("voxel size {0} must be a positive finite number")]
    BadVoxelSize(f64),
    #[error("the scene is a single point (all vertices equal): it has no extent to voxelize")]
    NoExtent,
    #[error(
        "the grid would be {dims:?} voxels; the largest supported is {max} along each axis \
         (lower --resolution or raise the voxel size)"
    )]
    GridTooLarge { dims: [u64; 3], max: u64 },
    #[error("the scene produced {0} surfels; at most 4294967295 are supported in one set")]
    TooManySurfels(usize),
}

/// Largest grid edge: keeps `(i, j)` line counts and voxel coordinates comfortably in range.
pub const MAX_GRID_EDGE: u64 = 1 << 20;

/// Chooses the grid so that the scene's bounding planes pass through voxel centres (a wall on the
/// bounds is then one voxel thick instead of straddling two layers).
pub fn grid_for(scene: &Scene, spec: GridSpec) -> Result<Grid, VoxelizeError> {
    let bounds = scene.bounds();
    let extent = bounds.extent();
    let longest = extent.max_element();
    let voxel_size = match spec {
        GridSpec::Resolution(n) if n < 2 => return Err(VoxelizeError::ResolutionTooSmall(n)),
        GridSpec::Resolution(n) => {
            if longest <= 0.0 {
                return Err(VoxelizeError::NoExtent);
            }
            longest / (n - 1) as f64
        }
        GridSpec::VoxelSize(v) if !(v.is_finite() && v > 0.0) => {
            return Err(VoxelizeError::BadVoxelSize(v))
        }
        GridSpec::VoxelSize(v) => v,
    };
    let dims_f = (extent / voxel_size + 0.5).floor() + 1.0;
    let dims64 = [dims_f.x as u64, dims_f.y as u64, dims_f.z as u64];
    if dims64.iter().any(|&d| d > MAX_GRID_EDGE) || !dims_f.is_finite() {
        return Err(VoxelizeError::GridTooLarge {
            dims: dims64,
            max: MAX_GRID_EDGE,
        });
    }
    let origin = bounds.min - DVec3::splat(voxel_size * 0.5);
    Ok(Grid {
        origin: origin.to_array(),
        voxel_size,
        dims: dims64.map(|d| d as u32),
    })
}

/// Marks every triangle that repeats an earlier one (same vertices, same winding): one surface
/// modelled twice, as bad exports often do, whose area, and so emitted power, would otherwise
/// count twice. Sorting 16 bytes per triangle (a hash and an index) keeps the transient memory
/// small, which the converter's address-space limit needs; equal hashes are confirmed exactly.
fn duplicates(scene: &Scene) -> Vec<bool> {
    use std::hash::{Hash, Hasher};
    let mut keyed: Vec<(u64, u32)> = scene
        .triangles
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let mut h = std::collections::hash_map::DefaultHasher::new();
            triangle_key(t).hash(&mut h);
            (h.finish(), i as u32)
        })
        .collect();
    keyed.sort_unstable();
    let mut duplicate = vec![false; scene.triangles.len()];
    for run in keyed.chunk_by(|a, b| a.0 == b.0).filter(|r| r.len() > 1) {
        for (k, &(_, i)) in run.iter().enumerate() {
            let key = triangle_key(&scene.triangles[i as usize]);
            // Earlier entries of the run have lower indices (sorted by hash, then index).
            if run[..k]
                .iter()
                .any(|&(_, j)| triangle_key(&scene.triangles[j as usize]) == key)
            {
                duplicate[i as usize] = true;
            }
        }
    }
    duplicate
}

/// The exact vertices of a triangle, rotated to start at the smallest one (so that the same
/// triangle listed from another vertex, with the same winding, has the same key).
fn triangle_key(t: &crate::scene::Triangle) -> [[u64; 3]; 3] {
    let v = t.vertices.map(|p| p.to_array().map(f64::to_bits));
    let first = (0..3).min_by_key(|&k| v[k]).unwrap_or(0);
    [v[first], v[(first + 1) % 3], v[(first + 2) % 3]]
}

/// Interleaves the bits of three non-negative coordinates (below 2^21) into a Morton code.
pub fn morton(voxel: [i32; 3]) -> u64 {
    fn spread(v: i32) -> u64 {
        let mut x = (v as u64) & 0x1f_ffff;
        x = (x | x << 32) & 0x1f00000000ffff;
        x = (x | x << 16) & 0x1f0000ff0000ff;
        x = (x | x << 8) & 0x100f00f00f00f00f;
        x = (x | x << 4) & 0x10c30c30c30c30c3;
        (x | x << 2) & 0x1249249249249249
    }
    spread(voxel[0]) | spread(voxel[1]) << 1 | spread(voxel[2]) << 2
}

/// One triangle's share of one voxel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Piece {
    pub(crate) voxel: [i32; 3],
    pub(crate) group: u32,
    pub(crate) side: u8,
    pub(crate) material: u32,
    /// Index of the triangle in the scene: the last part of the merge key, so that the pieces of
    /// one surfel are always combined in the same order and its floating-point sums come out
    /// bit for bit the same whatever sorted them (in memory here, on disk in `convert`).
    pub(crate) triangle: u32,
    pub(crate) area: f64,
    /// Area-weighted centroid sum (voxel units, relative to the voxel corner).
    pub(crate) centroid_sum: DVec3,
    /// Mean of the clipped polygon's vertices, for zero-area contacts.
    pub(crate) contact: DVec3,
    /// Bounding box of the clipped polygon.
    pub(crate) lo: DVec3,
    pub(crate) hi: DVec3,
}

impl Piece {
    /// Within one voxel, the order pieces are merged in: by plane group, facing, material, then
    /// triangle. Unique per piece (a triangle has at most one piece per voxel).
    pub(crate) fn merge_key(&self) -> (u32, u8, u32, u32) {
        (self.group, self.side, self.material, self.triangle)
    }
}

/// A triangle's plane in voxel units, in canonical orientation.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Plane {
    normal: DVec3,
    offset: f64,
    side: u8,
}

fn canonical_plane(q: &[DVec3; 3]) -> Option<Plane> {
    let cross = (q[1] - q[0]).cross(q[2] - q[0]);
    let len = cross.length();
    if len.partial_cmp(&1e-14) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    let mut normal = cross / len;
    let lead = normal
        .to_array()
        .into_iter()
        .find(|c| c.abs() > 1e-9)
        .unwrap_or(1.0);
    let side = if lead < 0.0 {
        normal = -normal;
        BACK as u8
    } else {
        FRONT as u8
    };
    Some(Plane {
        normal,
        offset: normal.dot(q[0]),
        side,
    })
}

fn plane_key(p: &Plane) -> [i64; 4] {
    [
        (p.normal.x * 1e6).round() as i64,
        (p.normal.y * 1e6).round() as i64,
        (p.normal.z * 1e6).round() as i64,
        (p.offset * 1e4).round() as i64,
    ]
}

/// The scene's triangles sorted into plane groups, with the normal table of the groups. Grows
/// with the triangles, not the surfels: the part of the voxelization every path holds whole.
pub(crate) struct PlaneGroups {
    pub(crate) grid: Grid,
    /// Per triangle: its plane and group, `None` for a degenerate triangle.
    planes: Vec<Option<(Plane, u32)>>,
    /// Per group: the id of its (front-facing) normal in `normals`.
    group_normal: Vec<u32>,
    /// One entry per distinct group normal, in order of first appearance.
    normals: Vec<[f32; 3]>,
    /// Per triangle: whether it is a face of a solid lying behind it (`solids`).
    pub(crate) solid_backed: Vec<bool>,
    /// Per triangle: whether its back side lies inside a closed solid (`enclosed`).
    pub(crate) inside_backed: Vec<bool>,
    /// Some plane holds triangles of both facings, none a solid's face: a sheet that may be
    /// modelled twice, back to back (`mark_doubled`).
    pub(crate) two_facings: bool,
}

impl PlaneGroups {
    /// Groups the triangles of `scene` on `grid`, assigning group and normal ids in triangle
    /// order so that they are reproducible.
    pub(crate) fn new(scene: &Scene, grid: Grid) -> Self {
        let mut group_of_key: HashMap<[i64; 4], u32> = HashMap::new();
        let mut normal_of_key: HashMap<[i64; 3], u32> = HashMap::new();
        let mut normals: Vec<[f32; 3]> = Vec::new();
        let mut group_normal: Vec<u32> = Vec::new();
        let mut planes = Vec::with_capacity(scene.triangles.len());
        let duplicate = duplicates(scene);
        for (t, &dup) in scene.triangles.iter().zip(&duplicate) {
            if dup {
                planes.push(None);
                continue;
            }
            let q = t.vertices.map(|v| grid.to_voxel_units(v));
            let entry = canonical_plane(&q).map(|plane| {
                let key = plane_key(&plane);
                let next = group_of_key.len() as u32;
                let group = *group_of_key.entry(key).or_insert(next);
                if group == next {
                    let nkey = [key[0], key[1], key[2]];
                    let next_normal = normals.len() as u32;
                    let id = *normal_of_key.entry(nkey).or_insert(next_normal);
                    if id == next_normal {
                        normals.push(plane.normal.as_vec3().to_array());
                    }
                    group_normal.push(id);
                }
                (plane, group)
            });
            planes.push(entry);
        }
        let solid_backed = super::solids::solid_backed(scene);
        // Facings met per group (bit 0: side 0, bit 1: side 1), of triangles of no solid.
        let mut facings = vec![0u8; group_normal.len()];
        for (entry, &solid) in planes.iter().zip(&solid_backed) {
            if let (Some((plane, group)), false) = (entry, solid) {
                facings[*group as usize] |= 1 << plane.side;
            }
        }
        PlaneGroups {
            grid,
            planes,
            group_normal,
            normals,
            solid_backed,
            inside_backed: super::enclosed::inside_backed(scene),
            two_facings: facings.contains(&3),
        }
    }

    /// Number of distinct group normals (the flags [`Tables::new`] takes are indexed by them).
    pub(crate) fn normal_count(&self) -> usize {
        self.normals.len()
    }

    /// The group normal id of a piece (before any flip for its facing).
    pub(crate) fn normal_of(&self, piece: &Piece) -> u32 {
        self.group_normal[piece.group as usize]
    }

    /// The polygon of `piece` (voxel units relative to its voxel's corner), clipped again from
    /// its triangle of `scene` exactly as [`Self::triangle_pieces`] clipped it.
    pub(crate) fn piece_polygon(&self, scene: &Scene, piece: &Piece) -> Vec<DVec3> {
        let t = &scene.triangles[piece.triangle as usize];
        let corner = DVec3::new(
            piece.voxel[0] as f64,
            piece.voxel[1] as f64,
            piece.voxel[2] as f64,
        );
        let mut polygon: Vec<DVec3> = t
            .vertices
            .iter()
            .map(|v| self.grid.to_voxel_units(*v) - corner)
            .collect();
        let mut scratch = Vec::with_capacity(12);
        clip_to_unit_cube(&mut polygon, &mut scratch);
        polygon
    }

    /// Feeds the pieces of triangle `index` of `scene` to `emit`, stopping at its first error.
    pub(crate) fn triangle_pieces<E>(
        &self,
        scene: &Scene,
        index: usize,
        emit: &mut impl FnMut(Piece) -> Result<(), E>,
    ) -> Result<(), E> {
        let Some((plane, group)) = &self.planes[index] else {
            return Ok(());
        };
        let t = &scene.triangles[index];
        let q = t.vertices.map(|v| self.grid.to_voxel_units(v));
        let info = PieceInfo {
            group: *group,
            material: t.material,
            triangle: index as u32,
        };
        triangle_pieces(&q, plane, info, self.grid.dims, emit)
    }
}

/// The tables surfels index beyond the plane groups: normals for back-facing surfels and the
/// unlit back sides of emitters.
///
/// Both are fixed before any surfel is made, from facts a single pass over the pieces (or the
/// scene alone) establishes, never from the order surfels are met: the flipped normal of group
/// normal `k` exists when some piece of a group with normal `k` faces back, and the flipped
/// normals are appended in increasing `k`; every emitting material of the scene gets an unlit
/// copy, appended in material order. So a path that meets surfels in another order (the
/// out-of-core conversion meets them in shard order) numbers them exactly as this one does.
#[derive(Clone, Debug)]
pub(crate) struct Tables {
    group_normal: Vec<u32>,
    pub(crate) normals: Vec<[f32; 3]>,
    /// Per group normal: the id of its flipped copy, if some piece faces back.
    flipped: Vec<Option<u32>>,
    pub(crate) materials: Vec<Material>,
    /// Per scene material: the id of its unlit copy (emitters only).
    unlit: Vec<Option<u32>>,
    /// The id of [`Material::inside_of_solids`], appended when some triangle's back side lies
    /// inside a closed solid.
    inside: Option<u32>,
}

impl Tables {
    /// `back_facing[k]`: whether some piece of a group with normal `k` faces back.
    pub(crate) fn new(scene: &Scene, groups: &PlaneGroups, back_facing: &[bool]) -> Self {
        let mut normals = groups.normals.clone();
        let flipped = (0..groups.normals.len())
            .map(|k| {
                back_facing.get(k).copied().unwrap_or(false).then(|| {
                    let n = groups.normals[k];
                    normals.push([-n[0], -n[1], -n[2]]);
                    (normals.len() - 1) as u32
                })
            })
            .collect();
        let mut materials = scene.materials.clone();
        let unlit = scene
            .materials
            .iter()
            .map(|m| {
                m.is_emitter().then(|| {
                    materials.push(Material::new(
                        &format!("{} (unlit side)", m.name),
                        m.reflectance,
                        [0.0; 3],
                    ));
                    (materials.len() - 1) as u32
                })
            })
            .collect();
        let inside = (groups.inside_backed.iter().any(|&b| b) || groups.two_facings).then(|| {
            materials.push(Material::inside_of_solids());
            (materials.len() - 1) as u32
        });
        Tables {
            group_normal: groups.group_normal.clone(),
            normals,
            flipped,
            materials,
            unlit,
            inside,
        }
    }
}

/// Voxelizes `scene` (which must have passed `Scene::validate`) on the grid `spec` selects.
pub fn voxelize(scene: &Scene, spec: GridSpec) -> Result<SurfelSet, VoxelizeError> {
    let grid = grid_for(scene, spec)?;
    let groups = PlaneGroups::new(scene, grid);

    let progress = crate::progress::bar(scene.triangles.len() as u64, "voxelize");
    let mut pieces: Vec<Piece> = (0..scene.triangles.len())
        .into_par_iter()
        .flat_map_iter(|index| {
            let mut out = Vec::new();
            let _ = groups.triangle_pieces(scene, index, &mut |p| {
                out.push(p);
                Ok::<(), std::convert::Infallible>(())
            });
            progress.inc(1);
            out
        })
        .collect();
    progress.finish_and_clear();

    let mut back_facing = vec![false; groups.normal_count()];
    for p in &pieces {
        if p.side as usize == BACK {
            back_facing[groups.normal_of(p) as usize] = true;
        }
    }
    let tables = Tables::new(scene, &groups, &back_facing);

    // Surfels are stored in Morton (Z-curve) order of their voxels: discrete lines run in every
    // direction, and along a Z-curve voxels that are close in space are mostly close in memory,
    // which keeps the solver's per-line gathers in cache far better than a row-major order.
    pieces.par_sort_unstable_by_key(|p| (morton(p.voxel), p.merge_key()));

    // Triangles of one plane facing opposite ways (two solids pressed together, or a sheet
    // modelled twice back to back) become two surfels, each with its own piece and point, so that
    // a ray can tell which piece it crosses, and each without the part the other covers
    // (`contact`).
    let surfels: Vec<Surfel> = pieces
        .par_chunk_by(|a, b| a.voxel == b.voxel)
        .flat_map_iter(|voxel| merge_voxel(voxel, &tables, &groups, scene))
        .collect();
    if surfels.len() > u32::MAX as usize {
        return Err(VoxelizeError::TooManySurfels(surfels.len()));
    }
    Ok(SurfelSet {
        grid,
        surfels,
        normals: tables.normals,
        materials: tables.materials,
    })
}

/// The material of the surfel of `run` (pieces of one voxel, plane and facing, sorted by
/// material within it; `area` their sum). Where several materials share the piece (the rim of a
/// window or a lamp set in an opening of its wall or ceiling, in the same plane), each is taken
/// with the probability of its share of the area, by a threshold that a hash of the voxel, the
/// plane and the facing fixes (so every path that voxelizes the scene draws the same). Taking the
/// material covering most of the piece made every rim voxel all or nothing alike: along a
/// straight rim each voxel holds the same share, so a window lost or gained a strip along each
/// edge, 3.1 % of a window's power at resolution 128 (`docs/accuracy.md`); drawn so, the
/// rim's emitting area comes out right on average, voxel by voxel errors scattering instead of
/// adding up.
fn drawn_material(run: &[Piece], area: f64) -> u32 {
    let first = run[0].material;
    if run.iter().all(|p| p.material == first) || area <= 1e-12 {
        return first;
    }
    let key = Piece::merge_key(&run[0]);
    let voxel = run[0].voxel.map(|c| c as u32 as u64);
    let mixed = [voxel[0], voxel[1], voxel[2], key.0 as u64, key.1 as u64]
        .iter()
        .fold(0x243F_6A88_85A3_08D3u64, |h, &v| splitmix(h ^ v));
    // A threshold in [0, area): 53 bits of the hash, as a fraction.
    let threshold = (mixed >> 11) as f64 / (1u64 << 53) as f64 * area;
    let mut below = 0.0;
    for p in run {
        below += p.area;
        if below > threshold {
            return p.material;
        }
    }
    run[run.len() - 1].material
}

/// One step of the SplitMix64 generator: a bijective mix of all 64 bits.
fn splitmix(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Merges the pieces of one (voxel, group, facing), sorted by [`Piece::merge_key`], into a
/// surfel whose front is the side its triangles face; the back takes the front's reflectance
/// without its emission. A function of the pieces alone.
pub(crate) fn merge_run(run: &[Piece], tables: &Tables) -> Surfel {
    let area: f64 = run.iter().map(|p| p.area).sum();
    let mut point = if area > 1e-12 {
        run.iter().map(|p| p.centroid_sum).sum::<DVec3>() / area
    } else {
        run.iter().map(|p| p.contact).sum::<DVec3>() / run.len() as f64
    };
    // The centroid of pieces that form an L (two faces meeting in the voxel) can fall in the
    // notch, off the surface, where rays from it would start in the wrong room. When it lies in no
    // piece's bounding box, use the centroid of the largest piece, which is on the surface.
    let margin = 1e-6;
    let inside_some = run
        .iter()
        .any(|p| point.cmpge(p.lo - margin).all() && point.cmple(p.hi + margin).all());
    if !inside_some {
        if let Some(largest) = run.iter().max_by(|a, b| a.area.total_cmp(&b.area)) {
            point = if largest.area > 1e-12 {
                largest.centroid_sum / largest.area
            } else {
                largest.contact
            };
        }
    }
    let point = point.clamp(DVec3::ZERO, DVec3::ONE);
    let front = drawn_material(run, area);
    let back = tables
        .unlit
        .get(front as usize)
        .copied()
        .flatten()
        .unwrap_or(front);
    let group = run[0].group;
    let mut normal_id = tables.group_normal[group as usize];
    if run[0].side as usize == BACK {
        // Always present: `Tables::new` was told about every back-facing piece.
        normal_id = tables.flipped[normal_id as usize].unwrap_or(normal_id);
    }
    Surfel {
        voxel: run[0].voxel,
        point: point.as_vec3().to_array(),
        normal: tables.normals[normal_id as usize],
        normal_id,
        group,
        area: area as f32,
        material: [front, back],
        extent: [
            run.iter()
                .fold(DVec3::ONE, |a, p| a.min(p.lo))
                .as_vec3()
                .to_array(),
            run.iter()
                .fold(DVec3::ZERO, |a, p| a.max(p.hi))
                .as_vec3()
                .to_array(),
        ],
    }
}

/// The surfels of the pieces of one voxel, sorted by `Piece::merge_key` (so a plane group's
/// pieces, and within it a facing's, are consecutive): one per plane group and facing, each
/// without the part of its pieces that no light can reach because a solid covers it.
///
/// **Why.** A surfel has the area and centroid of its triangles in the voxel. A floor that runs
/// on under a wall box 0.15 m thick kept, in the voxels of the wall's foot, its whole area and a
/// surface point that could lie under the wall: rays from that point start inside the wall and
/// gather its dark inner sides, so the visible strips of floor beside the wall came out dark and
/// the light that fell on them was lost. In a corridor 2 m wide between such walls (resolution
/// 32, voxels of 0.39 m) a third of the floor's and ceiling's voxels were such strips: the
/// corridor measured 10 to 28 % dark against the path-traced reference (docs/accuracy.md).
///
/// **What is hidden**, on faces of a solid (`solids`: joined along an edge to a face behind
/// them) and what they rest on:
/// - *Faces pressed together*: where triangles of one plane face both ways in the voxel and
///   either facing is a solid's (a wall's foot on the floor, a sofa's back against its seat),
///   each facing loses what the other covers. Every piece (a convex polygon, a triangle clipped
///   to the voxel) is cut by every opposite piece into convex parts outside it. A sheet modelled
///   twice back to back, free of any solid, keeps both faces whole.
/// - *Solids standing on a plane* without a face on it (the Cornell box's blocks have no
///   bottom): a solid's face that meets the plane along an edge and rises in front of it hides
///   what lies behind it; where several stand in the voxel, what lies behind all of them (the
///   corner of a box).
///
/// The surfel is then merged from the visible parts by the usual rule ([`merge_run`]): area,
/// centroid, box and material of what is seen. A facing covered entirely (the wall's foot
/// itself) keeps its point and box with area 0: it stays a voxel-mate that stops rays at the
/// seam, and it neither absorbs nor counts in any sum. The polygons are clipped again from the
/// triangles, as `triangle_pieces` clipped them, so both voxelizers (in memory and
/// `convert::stream`) give the same surfels bit for bit.
pub(crate) fn merge_voxel(
    pieces: &[Piece],
    tables: &Tables,
    groups: &PlaneGroups,
    scene: &Scene,
) -> Vec<Surfel> {
    let mut surfels = Vec::with_capacity(4);
    let runs: Vec<&[Piece]> = pieces
        .chunk_by(|a, b| a.group == b.group && a.side == b.side)
        .collect();
    let solid = |p: &Piece| groups.solid_backed[p.triangle as usize];
    // Nothing can be hidden without a solid's face and a second surface in the voxel.
    if runs.len() < 2 || !pieces.iter().any(solid) {
        surfels.extend(runs.iter().map(|run| merge_run(run, tables)));
        mark_inside(&mut surfels, &runs, groups, tables);
        mark_doubled(&mut surfels, &runs, groups, scene, tables);
        return surfels;
    }
    let polygons: Vec<Vec<DVec3>> = pieces
        .iter()
        .map(|p| groups.piece_polygon(scene, p))
        .collect();
    let facing = |p: &Piece| {
        scene.triangles[p.triangle as usize]
            .cross()
            .normalize_or_zero()
    };
    let mut start = 0;
    for run in &runs {
        let range = start..start + run.len();
        start += run.len();
        let group = run[0].group;
        // The other facing of the plane, where either facing is a solid's: in contact.
        let contact = pieces.iter().filter(|p| p.group == group).any(&solid);
        let covering: Vec<&Vec<DVec3>> = pieces
            .iter()
            .zip(&polygons)
            .filter(|(p, _)| contact && p.group == group && p.side != run[0].side)
            .map(|(_, polygon)| polygon)
            .collect();
        // Faces of solids standing on the plane, in front of it: what lies behind them is
        // inside the solid.
        let (origin, normal) = (polygons[range.start][0], facing(&run[0]));
        let standing: Vec<(DVec3, DVec3)> = pieces
            .iter()
            .zip(&polygons)
            .filter(|(p, polygon)| {
                p.group != group && solid(p) && stands_on(polygon, origin, normal)
            })
            .map(|(p, polygon)| (polygon[0], facing(p)))
            .collect();
        surfels.push(visible_surfel(
            run,
            &polygons[range],
            &covering,
            &standing,
            tables,
        ));
    }
    mark_inside(&mut surfels, &runs, groups, tables);
    mark_doubled(&mut surfels, &runs, groups, scene, tables);
    surfels
}

/// Gives the back side of a run the material [`Material::inside_of_solids`] where pieces of the
/// same plane facing the other way, of no solid, cover most of it: a sheet modelled twice, back
/// to back (as exports of two-sided faces often do). Each copy's back side faces into the other
/// copy, where nothing is seen; its front is the sheet's side. Left as they were, both copies'
/// sides would gather and absorb, counting the sheet twice in the power balance, while the
/// lines meet only one of each pair: a closed scene's scales (`solve::closed`) would then move
/// every surface's light by the sheet's imbalance.
fn mark_doubled(
    surfels: &mut [Surfel],
    runs: &[&[Piece]],
    groups: &PlaneGroups,
    scene: &Scene,
    tables: &Tables,
) {
    let Some(inside) = tables.inside else {
        return;
    };
    if runs.len() < 2 {
        return;
    }
    let solid = |p: &Piece| groups.solid_backed[p.triangle as usize];
    for (surfel, run) in surfels.iter_mut().zip(runs) {
        let other: Vec<&Piece> = runs
            .iter()
            .filter(|r| r[0].group == run[0].group && r[0].side != run[0].side)
            .flat_map(|r| r.iter())
            .collect();
        if other.is_empty()
            || surfel.area <= 0.0
            || run.iter().chain(other.iter().copied()).any(solid)
        {
            continue;
        }
        let covers: Vec<Vec<DVec3>> = other
            .iter()
            .map(|p| groups.piece_polygon(scene, p))
            .collect();
        let (mut area, mut uncovered) = (0.0, 0.0);
        for piece in run.iter() {
            let polygon = groups.piece_polygon(scene, piece);
            area += polygon_area_centroid(&polygon).0;
            let mut visible = vec![polygon];
            for cover in &covers {
                visible = visible
                    .iter()
                    .flat_map(|part| outside_of(part, cover))
                    .collect();
            }
            uncovered += visible
                .iter()
                .map(|part| polygon_area_centroid(part).0)
                .sum::<f64>();
        }
        if area > NEGLIGIBLE_AREA && uncovered < 0.5 * area {
            surfel.material[BACK] = inside;
        }
    }
}

/// Gives the surfels whose pieces all have their back side inside a closed solid (`enclosed`)
/// the material [`Material::inside_of_solids`] on that side: nothing there is ever seen, and
/// propagation does not search from it. `surfels` and `runs` are parallel.
fn mark_inside(surfels: &mut [Surfel], runs: &[&[Piece]], groups: &PlaneGroups, tables: &Tables) {
    let Some(inside) = tables.inside else {
        return;
    };
    for (surfel, run) in surfels.iter_mut().zip(runs) {
        if run
            .iter()
            .all(|p| groups.inside_backed[p.triangle as usize])
        {
            surfel.material[BACK] = inside;
        }
    }
}

/// Whether a solid's face `polygon` stands on the plane through `origin` with `normal`: it meets
/// the plane along an edge (two corners on it) and rises in front of it (the side `normal`
/// points to). Tolerances in voxel units: rounding of clipped corners, and a rise well above it.
fn stands_on(polygon: &[DVec3], origin: DVec3, normal: DVec3) -> bool {
    let height = |p: &DVec3| (*p - origin).dot(normal);
    polygon.iter().filter(|p| height(p).abs() <= 1e-6).count() >= 2
        && polygon.iter().any(|p| height(p) > 1e-4)
}

/// The surfel of `run` (one plane group and facing; `polygons` its pieces' polygons) without
/// what the `covering` polygons of the other facing hide, nor what lies behind every face of
/// `standing` (each a point on the face and the normal it faces along: a solid standing on the
/// plane, whose inside is behind its faces).
fn visible_surfel(
    run: &[Piece],
    polygons: &[Vec<DVec3>],
    covering: &[&Vec<DVec3>],
    standing: &[(DVec3, DVec3)],
    tables: &Tables,
) -> Surfel {
    if covering.is_empty() && standing.is_empty() {
        return merge_run(run, tables);
    }
    let mut parts: Vec<Piece> = Vec::new();
    // The visible parts' polygons (of the parts with area).
    let mut shapes: Vec<Vec<DVec3>> = Vec::new();
    for (piece, polygon) in run.iter().zip(polygons) {
        if piece.area <= NEGLIGIBLE_AREA {
            // A contact along an edge or a corner: nothing to hide.
            parts.push(*piece);
            continue;
        }
        let mut visible = vec![polygon.clone()];
        for cover in covering {
            visible = visible
                .iter()
                .flat_map(|part| outside_of(part, cover))
                .collect();
        }
        if !standing.is_empty() {
            let inside = standing
                .iter()
                .fold(polygon.clone(), |part, &(at, n)| clip(&part, at, -n));
            if polygon_area_centroid(&inside).0 > NEGLIGIBLE_AREA {
                visible = visible
                    .iter()
                    .flat_map(|part| outside_of(part, &inside))
                    .collect();
            }
        }
        for part in visible {
            if let Some(p) = part_piece(piece, &part) {
                parts.push(p);
                shapes.push(part);
            }
        }
    }
    if parts.iter().all(|p| p.area <= NEGLIGIBLE_AREA) {
        // Covered entirely: the place and box it had, without area.
        let mut surfel = merge_run(run, tables);
        surfel.area = 0.0;
        return surfel;
    }
    let mut surfel = merge_run(&parts, tables);
    // What is left can be an L or two strips, whose centroid may lie on the hidden part (even
    // inside a part's box, which is all `merge_run` checks): then the largest part's centroid.
    let point = DVec3::from(surfel.point.map(f64::from));
    if !shapes.is_empty() && !shapes.iter().any(|shape| contains(shape, point)) {
        let largest = parts
            .iter()
            .filter(|p| p.area > NEGLIGIBLE_AREA)
            .max_by(|a, b| a.area.total_cmp(&b.area))
            .expect("some part has area");
        surfel.point = (largest.centroid_sum / largest.area)
            .clamp(DVec3::ZERO, DVec3::ONE)
            .as_vec3()
            .to_array();
    }
    surfel
}

/// A piece standing for `part` of `piece`'s polygon (`None` if it has no area).
fn part_piece(piece: &Piece, part: &[DVec3]) -> Option<Piece> {
    let (area, centroid_sum) = polygon_area_centroid(part);
    if area <= NEGLIGIBLE_AREA {
        return None;
    }
    Some(Piece {
        area,
        centroid_sum,
        contact: part.iter().sum::<DVec3>() / part.len() as f64,
        lo: part.iter().fold(DVec3::ONE, |a, p| a.min(*p)),
        hi: part.iter().fold(DVec3::ZERO, |a, p| a.max(*p)),
        ..*piece
    })
}

/// What a triangle's pieces share.
struct PieceInfo {
    group: u32,
    material: u32,
    triangle: u32,
}

/// Feeds the pieces of one triangle (vertices in voxel units) to `emit`, one voxel at a time, so
/// that a caller can bound what it holds even for a triangle that covers millions of voxels.
fn triangle_pieces<E>(
    q: &[DVec3; 3],
    plane: &Plane,
    info: PieceInfo,
    dims: [u32; 3],
    emit: &mut impl FnMut(Piece) -> Result<(), E>,
) -> Result<(), E> {
    let lo = q[0].min(q[1]).min(q[2]).floor();
    let hi = q[0].max(q[1]).max(q[2]).floor();
    let clamp = |x: f64, k: usize| x.clamp(0.0, dims[k] as f64 - 1.0) as i64;
    let lo = [clamp(lo.x, 0), clamp(lo.y, 1), clamp(lo.z, 2)];
    let hi = [clamp(hi.x, 0), clamp(hi.y, 1), clamp(hi.z, 2)];
    let n = plane.normal.to_array();
    // Walk columns along the dominant normal axis w; in each, only the layers the plane crosses.
    let w = (0..3)
        .max_by(|&a, &b| n[a].abs().total_cmp(&n[b].abs()))
        .unwrap_or(2);
    let (u, v) = ((w + 1) % 3, (w + 2) % 3);
    let plane_w = |pu: f64, pv: f64| (plane.offset - n[u] * pu - n[v] * pv) / n[w];
    let mut polygon = Vec::with_capacity(12);
    let mut scratch = Vec::with_capacity(12);
    for cu in lo[u]..=hi[u] {
        for cv in lo[v]..=hi[v] {
            let (fu, fv) = (cu as f64, cv as f64);
            let corners = [
                plane_w(fu, fv),
                plane_w(fu + 1.0, fv),
                plane_w(fu, fv + 1.0),
                plane_w(fu + 1.0, fv + 1.0),
            ];
            let wmin = corners.iter().copied().fold(f64::INFINITY, f64::min);
            let wmax = corners.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let first = (wmin.floor() as i64).max(lo[w]);
            let last = (wmax.floor() as i64).min(hi[w]);
            for cw in first..=last {
                let mut voxel = [0i64; 3];
                voxel[u] = cu;
                voxel[v] = cv;
                voxel[w] = cw;
                let corner = DVec3::new(voxel[0] as f64, voxel[1] as f64, voxel[2] as f64);
                polygon.clear();
                polygon.extend(q.iter().map(|p| *p - corner));
                clip_to_unit_cube(&mut polygon, &mut scratch);
                if polygon.is_empty() || only_on_far_face(&polygon, n) {
                    continue;
                }
                let (area, centroid_sum) = polygon_area_centroid(&polygon);
                let contact = polygon.iter().sum::<DVec3>() / polygon.len() as f64;
                let lo = polygon.iter().fold(DVec3::ONE, |a, p| a.min(*p));
                let hi = polygon.iter().fold(DVec3::ZERO, |a, p| a.max(*p));
                emit(Piece {
                    voxel: voxel.map(|c| c as i32),
                    group: info.group,
                    side: plane.side,
                    material: info.material,
                    triangle: info.triangle,
                    area,
                    centroid_sum,
                    contact,
                    lo,
                    hi,
                })?;
            }
        }
    }
    Ok(())
}

/// True when every point lies on one of the cube's three *far* faces: for axis `k` the face where
/// `n.x` is largest (`x_k = 1` if `n_k >= 0`, else `x_k = 0`). Such a contact belongs to the
/// neighbouring voxel. This makes the kept voxels exactly the standard digital plane
/// `{mu <= n.v < mu + |n|_1}`: half-open in the plane's own coordinate, so a plane through lattice
/// corners can neither be doubled nor thinned into a 26-tunnel. (Half-open cubes `[v, v + 1)` would
/// be open at both ends of that range for normals with mixed signs.)
fn only_on_far_face(polygon: &[DVec3], normal: [f64; 3]) -> bool {
    (0..3).any(|axis| {
        if normal[axis] < 0.0 {
            polygon.iter().all(|p| p[axis] <= 0.0)
        } else {
            polygon.iter().all(|p| p[axis] >= 1.0)
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn piece(voxel: [i32; 3], material: u32, area: f64) -> Piece {
        Piece {
            voxel,
            group: 7,
            side: 0,
            material,
            triangle: material,
            area,
            centroid_sum: DVec3::splat(0.5) * area,
            contact: DVec3::splat(0.5),
            lo: DVec3::ZERO,
            hi: DVec3::ONE,
        }
    }

    #[test]
    fn a_piece_of_two_materials_takes_each_by_its_share_of_the_area() {
        // Rim voxels of a window in its wall, each 30 % window: the window must come out on
        // about 30 % of them (the majority rule gave it none), the same every time.
        let voxels: Vec<[i32; 3]> = (0..100)
            .flat_map(|x| (0..100).map(move |y| [x, y, 3]))
            .collect();
        let draw = |v: [i32; 3]| drawn_material(&[piece(v, 1, 0.7), piece(v, 2, 0.3)], 1.0);
        let window = voxels.iter().filter(|&&v| draw(v) == 2).count();
        let share = window as f64 / voxels.len() as f64;
        assert!((share - 0.3).abs() < 0.02, "{share}");
        assert!(voxels.iter().all(|&v| draw(v) == draw(v)));
        // One material, or a piece without area: nothing to draw.
        let v = [1, 2, 3];
        assert_eq!(
            drawn_material(&[piece(v, 4, 0.2), piece(v, 4, 0.5)], 0.7),
            4
        );
        assert_eq!(
            drawn_material(&[piece(v, 4, 0.0), piece(v, 5, 0.0)], 0.0),
            4
        );
        // A material with no area there is never drawn.
        assert!(voxels
            .iter()
            .all(|&v| drawn_material(&[piece(v, 1, 0.0), piece(v, 2, 0.6)], 0.6) == 2));
    }
    use crate::scene::{Material, Scene};
    use std::collections::HashSet;

    fn single_triangle_scene(v: [DVec3; 3]) -> Scene {
        let mut scene = Scene::default();
        let m = scene.add_material(Material::new("grey", [0.5; 3], [0.0; 3]));
        scene.add_polygon(&v, m);
        // Two far points fix the bounds (and so the grid origin, -100.5) whatever the triangle.
        scene.add_polygon(&[DVec3::splat(-100.0); 3], m);
        scene.add_polygon(&[DVec3::splat(100.0); 3], m);
        scene
    }

    /// Walks a 26-connected discrete line through the grid and reports whether it meets a voxel
    /// of `set`; the line starts on one side of the plane and ends on the other.
    #[test]
    fn oblique_planes_have_no_26_tunnels() {
        let planes = [
            DVec3::new(1.0, 1.0, 0.0),
            DVec3::new(1.0, 2.0, 3.0),
            DVec3::new(-2.0, 1.0, 5.0),
            DVec3::new(1.0, 1.0, 1.0),
            DVec3::new(1.0, 1.0, 0.0),
        ];
        for (k, n) in planes.into_iter().enumerate() {
            let n = n.normalize();
            // A big triangle through c; the last plane, x + y = 16, passes exactly through lattice
            // corners (the case where a wrongly half-opened cube would thin the plane).
            let c = if k == 4 {
                DVec3::new(8.0, 8.0, 8.0)
            } else {
                DVec3::splat(8.3)
            };
            let t1 = n.any_orthonormal_vector();
            let t2 = n.cross(t1);
            let v = if k == 4 {
                [
                    DVec3::new(-32.0, 48.0, -40.0),
                    DVec3::new(48.0, -32.0, -40.0),
                    DVec3::new(8.0, 8.0, 60.0),
                ]
            } else {
                [
                    c + t1 * 40.0,
                    c - t1 * 20.0 + t2 * 35.0,
                    c - t1 * 20.0 - t2 * 35.0,
                ]
            };
            let set = voxelize(&single_triangle_scene(v), GridSpec::VoxelSize(1.0)).unwrap();
            assert_eq!(set.grid.origin, [-100.5; 3]);
            let origin = DVec3::from(set.grid.origin);
            let voxels: HashSet<[i32; 3]> = set.surfels.iter().map(|s| s.voxel).collect();
            // Every 26-connected line step crossing the plane must hit a surface voxel.
            let side = |p: [i32; 3]| {
                let centre =
                    origin + DVec3::new(p[0] as f64 + 0.5, p[1] as f64 + 0.5, p[2] as f64 + 0.5);
                (centre - c).dot(n)
            };
            // Scan a block around the centre, well inside the triangle (its inradius is 20).
            let centre = ((c - origin) / set.grid.voxel_size).floor().as_ivec3();
            for x in centre.x - 6..centre.x + 6 {
                for y in centre.y - 6..centre.y + 6 {
                    for z in centre.z - 6..centre.z + 6 {
                        let a = [x, y, z];
                        for dx in -1..=1 {
                            for dy in -1..=1 {
                                for dz in -1..=1 {
                                    let b = [x + dx, y + dy, z + dz];
                                    if side(a) < 0.0 && side(b) > 0.0 {
                                        assert!(
                                            voxels.contains(&a) || voxels.contains(&b),
                                            "tunnel between {a:?} and {b:?} for normal {n:?}"
                                        );
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn axis_aligned_wall_on_bounds_is_one_voxel_thick_and_area_is_conserved() {
        let mut scene = Scene::default();
        let m = scene.add_material(Material::new("w", [0.5; 3], [1.0; 3]));
        scene.add_box(DVec3::ZERO, DVec3::ONE, m, true);
        let set = voxelize(&scene, GridSpec::Resolution(9)).unwrap();
        assert_eq!(set.grid.dims, [9, 9, 9]);
        // Each wall covers 9x9 voxels; 6 walls share 12 edges (2 surfels each) and 8 corners.
        assert_eq!(set.voxel_count(), 9 * 9 * 9 - 7 * 7 * 7);
        assert_eq!(set.surfels.len(), 6 * 81);
        let total_area: f64 = set.surfels.iter().map(|s| s.area as f64).sum();
        let expected = 6.0 / (set.grid.voxel_size * set.grid.voxel_size);
        assert!(
            (total_area - expected).abs() < 1e-6 * expected,
            "{total_area} vs {expected}"
        );
        // Inward-facing walls: the front of the floor (z=0 wall) faces +z.
        for s in &set.surfels {
            let p = s.position();
            let centre = DVec3::splat(4.5);
            assert!(p.cmpge(DVec3::ZERO).all() && p.cmple(DVec3::splat(9.0)).all());
            // Walls face inwards, so the emitting side is the one whose normal points inwards.
            let side = if set.materials[s.material[FRONT] as usize].is_emitter() {
                FRONT
            } else {
                BACK
            };
            assert!(!set.materials[s.material[1 - side] as usize].is_emitter());
            assert!(
                (centre - p).dot(s.side_normal(side)) > 0.0,
                "surfel {s:?} emits outwards"
            );
        }
    }

    #[test]
    fn back_of_an_emitter_does_not_emit() {
        let mut scene = Scene::default();
        let lamp = scene.add_material(Material::new("lamp", [0.2; 3], [5.0; 3]));
        scene.add_polygon(
            &[DVec3::ZERO, DVec3::X, DVec3::new(1.0, 1.0, 0.0), DVec3::Y],
            lamp,
        );
        let set = voxelize(&scene, GridSpec::Resolution(5)).unwrap();
        for s in &set.surfels {
            let emits: Vec<bool> = s
                .material
                .iter()
                .map(|&m| set.materials[m as usize].is_emitter())
                .collect();
            assert_eq!(emits.iter().filter(|&&e| e).count(), 1);
        }
    }

    #[test]
    fn morton_interleaves_bits() {
        assert_eq!(morton([1, 0, 0]), 1);
        assert_eq!(morton([0, 1, 0]), 2);
        assert_eq!(morton([0, 0, 1]), 4);
        assert_eq!(morton([3, 3, 3]), 63);
        assert_eq!(morton([0x1f_ffff, 0, 0]), 0x1249249249249249);
        // Order-preserving along each axis.
        assert!(morton([5, 9, 2]) < morton([6, 9, 2]));
    }

    #[test]
    fn rejects_bad_specs() {
        let mut scene = Scene::default();
        let m = scene.add_material(Material::new("w", [0.5; 3], [0.0; 3]));
        scene.add_box(DVec3::ZERO, DVec3::ONE, m, true);
        assert_eq!(
            voxelize(&scene, GridSpec::Resolution(1)).unwrap_err(),
            VoxelizeError::ResolutionTooSmall(1)
        );
        assert!(matches!(
            voxelize(&scene, GridSpec::VoxelSize(-1.0)),
            Err(VoxelizeError::BadVoxelSize(_))
        ));
        assert!(matches!(
            voxelize(&scene, GridSpec::VoxelSize(1e-9)),
            Err(VoxelizeError::GridTooLarge { .. })
        ));
    }
}

//! The radiosity baked onto the scene's own triangles: the mesh that `baked.glb` and `baked.ply`
//! hold (written by [`super::glb`] and [`super::mesh_ply`]).
//!
//! Each triangle of the input is baked on its front (the side its winding faces) and, where that
//! side carries light too ([`BACK_LIT`]), on its back as a second triangle of reversed winding: a
//! partition lit from both sides shows both, the outside of a closed room (dark) and the inner
//! sides of solids are left out. A vertex's value
//! is what `voxrad probe` answers at that point for that side ([`ProbeIndex::lookup`]: the
//! surfels of the facing side near it), so the baked mesh is exactly as right as the probes.
//!
//! Triangles are cut where the light varies across them: an edge needs a cut when it is longer
//! than [`BakeOptions::max_edge`] voxels, or longer than [`BakeOptions::min_edge`] voxels and its
//! midpoint's luminance is more than [`BakeOptions::tolerance`] off the mean of its ends; a
//! triangle with such an edge is halved across its longest edge, together with its neighbour
//! across that edge (conforming longest-edge bisection, after Rivara), until no edge needs a cut.
//! Triangles stay well shaped, and vertices are shared by position and side, so that triangles
//! of one plane meeting along an edge stay joined vertex to vertex: no crack, no T-junction.

use super::probe::ProbeIndex;
use super::results::Results;
use super::{luminance, render::ToneMap};
use crate::scene::Scene;
use glam::DVec3;
use rayon::prelude::*;
use rustc_hash::FxHashMap;

/// How finely triangles are cut.
#[derive(Clone, Copy, Debug)]
pub struct BakeOptions {
    /// Edges longer than this (voxels) are always halved: the light between two far vertices is
    /// not known from them.
    pub max_edge: f64,
    /// Edges at most this long (voxels) are never halved: below a voxel the surfels say nothing
    /// new.
    pub min_edge: f64,
    /// Relative departure of an edge's midpoint from the mean of its ends (luminance) above
    /// which the edge is halved.
    pub tolerance: f64,
}

impl Default for BakeOptions {
    fn default() -> Self {
        BakeOptions {
            max_edge: 8.0,
            min_edge: 1.0,
            tolerance: 0.02,
        }
    }
}

/// A triangle mesh with the radiosity of the side each vertex's normal faces.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BakedMesh {
    /// World positions.
    pub positions: Vec<[f32; 3]>,
    /// Unit normals of the side baked (the front's for a front triangle, reversed for a back).
    pub normals: Vec<[f32; 3]>,
    /// Linear radiosity `B` (units of `Ke`), RGB.
    pub radiosity: Vec<[f32; 3]>,
    /// Three vertex indices a triangle, wound counter-clockwise seen from the normal's side.
    pub indices: Vec<u32>,
    /// The tone map of the results (as the preview's), for display colours.
    pub tone: Option<ToneMap>,
}

impl BakedMesh {
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// The display colour of vertex `v` as linear RGB in `[0, 1]` (the preview's tone map,
    /// before its sRGB encoding: what glTF's `COLOR_0` holds).
    pub fn linear_colour(&self, v: usize) -> [f32; 3] {
        let tone = self.tone.unwrap_or(ToneMap { exposure: 1.0 });
        tone.linear(self.radiosity[v])
    }

    /// The display colour of vertex `v` as 8-bit sRGB (what the PNG preview shows).
    pub fn srgb_colour(&self, v: usize) -> [u8; 3] {
        let tone = self.tone.unwrap_or(ToneMap { exposure: 1.0 });
        tone.map(self.radiosity[v])
    }
}

/// Bakes the radiosity of `results` onto the triangles of `scene`.
pub fn bake(scene: &Scene, results: &Results, options: &BakeOptions) -> BakedMesh {
    let index = ProbeIndex::new(results);
    let tone = ToneMap::for_results(results);
    // Luminances below this are dark for the purpose of cutting: no cut chases noise in the dark.
    let dark = 1e-3 / tone.exposure;
    // Triangles share baked vertices only within one plane and side, so each set of coplanar
    // triangles joined by their corners is cut on its own: in parallel, and holding only that
    // set's bookkeeping (the whole scene's took about 2 KB a surfel).
    let parts: Vec<BakedMesh> = plane_components(scene)
        .par_iter()
        .map(|triangles| {
            let mut refine = Refinement::new(&index, results.grid.voxel_size, options, dark);
            for &t in triangles {
                refine.add_triangle(&scene.triangles[t], tone);
            }
            refine.run();
            let mut part = BakedMesh::default();
            refine.append_to(&mut part);
            part
        })
        .collect();
    let mut mesh = BakedMesh {
        tone: Some(tone),
        ..Default::default()
    };
    for part in parts {
        let base = mesh.positions.len() as u32;
        mesh.positions.extend(part.positions);
        mesh.normals.extend(part.normals);
        mesh.radiosity.extend(part.radiosity);
        mesh.indices.extend(part.indices.iter().map(|&i| base + i));
    }
    mesh
}

/// The unit normal of a triangle's front, if it has one.
fn front_normal(t: &crate::scene::Triangle) -> Option<DVec3> {
    let cross = t.cross();
    (cross.length() > 0.0 && cross.is_finite()).then(|| cross.normalize())
}

/// The scene's triangles (those with a normal) in sets that may share baked vertices: coplanar
/// (the same normal up to its sign, bit for bit, as the vertices' keys have it) and joined by
/// corners, in the order of their first triangles.
fn plane_components(scene: &Scene) -> Vec<Vec<usize>> {
    let n = scene.triangles.len();
    let mut parent: Vec<usize> = (0..n).collect();
    fn root(parent: &mut [usize], mut k: usize) -> usize {
        while parent[k] != k {
            parent[k] = parent[parent[k]];
            k = parent[k];
        }
        k
    }
    let mut first_at: FxHashMap<([u64; 3], [u64; 3]), usize> = FxHashMap::default();
    for (t, triangle) in scene.triangles.iter().enumerate() {
        let Some(normal) = front_normal(triangle) else {
            continue;
        };
        // One sign for both faces of a plane.
        let lead = [normal.x, normal.y, normal.z]
            .into_iter()
            .find(|&c| c != 0.0)
            .unwrap_or(1.0);
        let canonical = if lead > 0.0 { normal } else { -normal };
        let key_normal = canonical.to_array().map(f64::to_bits);
        for p in triangle.vertices {
            let key = (p.to_array().map(f64::to_bits), key_normal);
            match first_at.get(&key) {
                Some(&other) => {
                    let (a, b) = (root(&mut parent, t), root(&mut parent, other));
                    if a != b {
                        parent[a.max(b)] = a.min(b);
                    }
                }
                None => {
                    first_at.insert(key, t);
                }
            }
        }
    }
    let mut slot: FxHashMap<usize, usize> = FxHashMap::default();
    let mut components: Vec<Vec<usize>> = Vec::new();
    for (t, triangle) in scene.triangles.iter().enumerate() {
        if front_normal(triangle).is_none() {
            continue;
        }
        let r = root(&mut parent, t);
        let next = components.len();
        let c = *slot.entry(r).or_insert(next);
        if c == next {
            components.push(Vec::new());
        }
        components[c].push(t);
    }
    components
}

/// Fraction of the preview's white a triangle's back must reach (at a corner or the centre) to be
/// baked. The inner sides of solids are not quite black (light that leaks through their edges:
/// 0.3 to 4 % of white inside the Cornell box's blocks at resolution 64), the lit sides of
/// partitions are far brighter.
const BACK_LIT: f64 = 0.05;

/// The triangles of every baked side while they are cut: conforming longest-edge bisection
/// (Rivara's), over vertices shared by position and side normal, so that triangles of one plane
/// and side that meet along an edge stay joined vertex to vertex as they are cut.
struct Refinement<'a> {
    index: &'a ProbeIndex<'a>,
    voxel: f64,
    options: &'a BakeOptions,
    dark: f64,
    points: Vec<DVec3>,
    normals: Vec<DVec3>,
    values: Vec<[f32; 3]>,
    /// Vertex by the bits of its position and normal. The maps hash with `rustc_hash`'s
    /// multiply-rotate hash: the standard library's SipHash took about a third of a bake's
    /// instructions, and its protection against chosen keys buys nothing for keys made here.
    vertex_at: FxHashMap<([u64; 3], [u64; 3]), usize>,
    midpoints: FxHashMap<(usize, usize), usize>,
    /// Whether an edge needs a cut, once decided.
    decisions: FxHashMap<(usize, usize), bool>,
    triangles: Vec<[usize; 3]>,
    alive: Vec<bool>,
    /// The live triangles on each edge (two inside a surface, one on its rim).
    edges: FxHashMap<(usize, usize), Vec<usize>>,
}

fn edge_key(a: usize, b: usize) -> (usize, usize) {
    (a.min(b), a.max(b))
}

impl<'a> Refinement<'a> {
    fn new(index: &'a ProbeIndex<'a>, voxel: f64, options: &'a BakeOptions, dark: f64) -> Self {
        Refinement {
            index,
            voxel,
            options,
            dark,
            points: Vec::new(),
            normals: Vec::new(),
            values: Vec::new(),
            vertex_at: FxHashMap::default(),
            midpoints: FxHashMap::default(),
            decisions: FxHashMap::default(),
            triangles: Vec::new(),
            alive: Vec::new(),
            edges: FxHashMap::default(),
        }
    }

    /// Adds an input triangle's front and, where it carries light ([`BACK_LIT`] of the tone
    /// map's white), its back: the same corners facing the other way, wound the other way round.
    fn add_triangle(&mut self, triangle: &crate::scene::Triangle, tone: ToneMap) {
        let Some(normal) = front_normal(triangle) else {
            return;
        };
        let [a, b, c] = triangle.vertices.map(|p| self.vertex(p, normal));
        self.add([a, b, c]);
        let centre = (triangle.vertices[0] + triangle.vertices[1] + triangle.vertices[2]) / 3.0;
        let centre_value = self.index.radiosity_at(centre, -normal).map(|v| v as f32);
        let back_values = triangle
            .vertices
            .map(|p| self.index.radiosity_at(p, -normal).map(|v| v as f32));
        let lit = back_values
            .iter()
            .chain([&centre_value])
            .any(|b| luminance(*b) > BACK_LIT / tone.exposure);
        if lit {
            let back = triangle.vertices.map(|p| self.vertex(p, -normal));
            self.add([back[0], back[2], back[1]]);
        }
    }

    fn vertex(&mut self, p: DVec3, normal: DVec3) -> usize {
        let key = (
            p.to_array().map(f64::to_bits),
            normal.to_array().map(f64::to_bits),
        );
        if let Some(&k) = self.vertex_at.get(&key) {
            return k;
        }
        let radiosity = self.index.radiosity_at(p, normal);
        self.points.push(p);
        self.normals.push(normal);
        self.values.push(radiosity.map(|v| v as f32));
        let k = self.points.len() - 1;
        self.vertex_at.insert(key, k);
        k
    }

    fn midpoint(&mut self, a: usize, b: usize) -> usize {
        let key = edge_key(a, b);
        if let Some(&m) = self.midpoints.get(&key) {
            return m;
        }
        let m = self.vertex((self.points[a] + self.points[b]) / 2.0, self.normals[a]);
        self.midpoints.insert(key, m);
        m
    }

    fn add(&mut self, t: [usize; 3]) {
        let id = self.triangles.len();
        self.triangles.push(t);
        self.alive.push(true);
        for e in 0..3 {
            self.edges
                .entry(edge_key(t[e], t[(e + 1) % 3]))
                .or_default()
                .push(id);
        }
    }

    fn remove(&mut self, id: usize) {
        self.alive[id] = false;
        let t = self.triangles[id];
        for e in 0..3 {
            if let Some(list) = self.edges.get_mut(&edge_key(t[e], t[(e + 1) % 3])) {
                list.retain(|&x| x != id);
            }
        }
    }

    fn length(&self, a: usize, b: usize) -> f64 {
        self.points[a].distance(self.points[b])
    }

    /// Whether edge `a`-`b` needs a cut (see the module header); decided once per edge.
    fn needs_cut(&mut self, a: usize, b: usize) -> bool {
        let key = edge_key(a, b);
        if let Some(&d) = self.decisions.get(&key) {
            return d;
        }
        let length = self.length(a, b) / self.voxel;
        let d = if length <= self.options.min_edge {
            false
        } else if length > self.options.max_edge {
            true
        } else {
            let m = self.midpoint(a, b);
            let (la, lb, lm) = (
                luminance(self.values[a]),
                luminance(self.values[b]),
                luminance(self.values[m]),
            );
            let scale = la.max(lb).max(lm).max(self.dark);
            (lm - 0.5 * (la + lb)).abs() > self.options.tolerance * scale
        };
        self.decisions.insert(key, d);
        d
    }

    /// The longest edge of triangle `id`, as a key.
    fn longest_edge(&self, id: usize) -> (usize, usize) {
        let t = self.triangles[id];
        let edges = [0, 1, 2].map(|e| edge_key(t[e], t[(e + 1) % 3]));
        // Ties go to the smaller key, so that two triangles sharing two equally long edges
        // agree on which is longest.
        edges
            .into_iter()
            .max_by(|&x, &y| {
                self.length(x.0, x.1)
                    .total_cmp(&self.length(y.0, y.1))
                    .then(y.cmp(&x))
            })
            .unwrap_or(edges[0])
    }

    /// Cuts until no live triangle has an edge that needs a cut.
    fn run(&mut self) {
        let mut id = 0;
        while id < self.triangles.len() {
            if self.alive[id] {
                let t = self.triangles[id];
                if (0..3).any(|e| self.needs_cut(t[e], t[(e + 1) % 3])) {
                    self.bisect(id, 0);
                }
            }
            id += 1;
        }
    }

    /// Bisects triangle `id` at the midpoint of its longest edge together with the triangle on
    /// the other side of that edge, which is first bisected along its own longest edge until
    /// the shared edge is its longest too (the longest-edge propagation path): no cut leaves a
    /// vertex in the middle of a neighbour's edge.
    fn bisect(&mut self, id: usize, depth: u32) {
        let edge = self.longest_edge(id);
        while self.alive[id] && depth <= MAX_DEPTH {
            let neighbour = self.edges[&edge]
                .iter()
                .copied()
                .find(|&n| n != id && self.alive[n]);
            match neighbour {
                None => {
                    self.split(id, edge);
                    return;
                }
                Some(n) if self.longest_edge(n) == edge => {
                    self.split(id, edge);
                    self.split(n, edge);
                    return;
                }
                Some(n) => self.bisect(n, depth + 1),
            }
        }
    }

    /// Replaces triangle `id` by its two halves at the midpoint of its edge `edge`.
    fn split(&mut self, id: usize, edge: (usize, usize)) {
        let m = self.midpoint(edge.0, edge.1);
        let t = self.triangles[id];
        // Rotate so that the cut edge comes first, keeping the winding.
        let e = (0..3)
            .find(|&e| edge_key(t[e], t[(e + 1) % 3]) == edge)
            .expect("the cut edge is an edge of the triangle");
        let (p, q, r) = (t[e], t[(e + 1) % 3], t[(e + 2) % 3]);
        self.remove(id);
        self.add([p, m, r]);
        self.add([m, q, r]);
    }

    /// Adds the vertices the live triangles use, and the triangles, to `mesh`.
    fn append_to(&self, mesh: &mut BakedMesh) {
        let mut slot = vec![u32::MAX; self.points.len()];
        for (t, _) in self.triangles.iter().zip(&self.alive).filter(|(_, &a)| a) {
            for &k in t {
                if slot[k] == u32::MAX {
                    slot[k] = mesh.positions.len() as u32;
                    mesh.positions.push(self.points[k].as_vec3().to_array());
                    mesh.normals.push(self.normals[k].as_vec3().to_array());
                    mesh.radiosity.push(self.values[k]);
                }
                mesh.indices.push(slot[k]);
            }
        }
    }
}

/// Deepest chain of neighbours one bisection may cut first (the longest-edge propagation path
/// is a handful of triangles in a mesh of fair triangles; this only guards against a runaway).
const MAX_DEPTH: u32 = 64;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::testutil;
    use crate::scene::{Material, Triangle};
    use std::collections::HashMap;

    /// Two triangles over the lit square of `testutil::lit_square` (world z = 0.5 + 0.25 * 0.5).
    fn square_scene(n: i32) -> (Scene, Results) {
        let (set, solution) = testutil::lit_square(n);
        let results = Results::from_solution(&set, &solution).unwrap();
        let grid = results.grid;
        let corner = |x: f64, y: f64| grid.to_world(DVec3::new(x, y, 0.5));
        let (a, b, c, d) = (
            corner(0.0, 0.0),
            corner(n as f64, 0.0),
            corner(n as f64, n as f64),
            corner(0.0, n as f64),
        );
        let scene = Scene {
            triangles: vec![
                Triangle {
                    vertices: [a, b, c],
                    material: 0,
                },
                Triangle {
                    vertices: [a, c, d],
                    material: 0,
                },
            ],
            materials: vec![Material::new("white", [0.5; 3], [0.0; 3])],
            source: "square".into(),
        };
        (scene, results)
    }

    #[test]
    fn the_square_is_covered_without_cracks_and_cut_where_the_light_varies() {
        let n = 16;
        let (scene, results) = square_scene(n);
        let options = BakeOptions::default();
        let mesh = bake(&scene, &results, &options);
        // Only the front: the back of the square is dark.
        assert!(mesh.normals.iter().all(|v| *v == [0.0, 0.0, 1.0]));
        let p = |k: u32| DVec3::from(mesh.positions[k as usize].map(f64::from));
        let voxel = results.grid.voxel_size;
        // The triangles cover the square once: their areas add up to it.
        let area: f64 = mesh
            .indices
            .chunks_exact(3)
            .map(|t| 0.5 * (p(t[1]) - p(t[0])).cross(p(t[2]) - p(t[0])).length())
            .sum();
        let square = (n as f64 * voxel).powi(2);
        // Positions are f32.
        assert!((area - square).abs() < 1e-6 * square, "{area} vs {square}");
        // No T-junction: every edge inside the square is used by exactly two triangles, once
        // in each direction, and the edges used once lie on the square's rim. (Vertices are
        // compared by position, so that a vertex made twice would show.)
        let key = |k: u32| mesh.positions[k as usize].map(f32::to_bits);
        // (position bits of its two ends) -> (uses, its two vertices)
        type Edge = ([u32; 3], [u32; 3]);
        let mut uses: HashMap<Edge, (i32, u32, u32)> = HashMap::new();
        for t in mesh.indices.chunks_exact(3) {
            for e in 0..3 {
                let (a, b) = (t[e], t[(e + 1) % 3]);
                uses.entry((key(a), key(b))).or_insert((0, a, b)).0 += 1;
            }
        }
        for (&(ka, kb), &(count, a, b)) in &uses {
            assert_eq!(count, 1);
            if !uses.contains_key(&(kb, ka)) {
                let mid = results.grid.to_voxel_units((p(a) + p(b)) / 2.0);
                let on_rim = [mid.x, mid.y]
                    .iter()
                    .any(|&c| c.abs() < 1e-6 || (c - n as f64).abs() < 1e-6);
                assert!(on_rim, "open edge inside the square at {mid}");
            }
            // Every edge within the longest allowed.
            assert!(p(a).distance(p(b)) <= options.max_edge * voxel * (1.0 + 1e-6));
        }
        // The light rises from the rim to the middle: cut finer than the longest edge allows.
        assert!(mesh.triangle_count() > 2 * (n as usize / 8).pow(2) * 2);
        // A vertex holds what a probe there reads.
        let index = ProbeIndex::new(&results);
        for (k, q) in mesh.positions.iter().enumerate() {
            let row = index.lookup(DVec3::from(q.map(f64::from)), DVec3::Z);
            assert_eq!(mesh.radiosity[k], row.radiosity.map(|v| v as f32));
        }
    }

    #[test]
    fn uniform_light_is_not_cut_below_the_longest_edge() {
        let (scene, mut results) = square_scene(16);
        for r in &mut results.records {
            r.radiosity[0] = [2.0; 3];
        }
        let mesh = bake(&scene, &results, &BakeOptions::default());
        // The 16-voxel square's diagonal halves are cut to edges of at most 8 voxels only.
        assert!(mesh.triangle_count() <= 16, "{}", mesh.triangle_count());
        assert!(mesh.radiosity.iter().all(|b| *b == [2.0; 3]));
    }
}

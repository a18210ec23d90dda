//! Plain scene descriptions: triangles with materials, as read from a file or made by a generator.
//!
//! A [`Scene`] is the input of voxelization and nothing more: world-space triangles, each naming a
//! [`Material`] by index. Readers (`obj`) and generators (`crate::gen`) produce it; the voxelizer
//! consumes it. Invariants a `Scene` holds once [`Scene::validate`] has passed: every coordinate is
//! finite, every material index is in range, every reflectance is in `[0, 1)` and every emission
//! is finite and non-negative, and there is at least one triangle.

pub mod obj;

use glam::DVec3;
use std::path::PathBuf;

/// The name of [`Material::inside_of_solids`] in a surfel set's materials.
pub const INSIDE_OF_SOLIDS: &str = "(inside of a solid)";

/// A diffuse material. Channels are RGB.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    pub name: String,
    /// Diffuse reflectance `rho` per channel, in `[0, 1)` (MTL `Kd`).
    pub reflectance: [f64; 3],
    /// Emitted radiosity `E` per channel (MTL `Ke`), in the scene's power-per-area unit.
    /// Emission leaves the front side of a triangle only (the side its winding's normal points to).
    pub emission: [f64; 3],
    /// The back side of a closed solid's face, inside the solid: it gathers no light and sends
    /// none (set by the voxelizer, `voxel::enclosed`; never by a scene file).
    pub inside: bool,
}

impl Material {
    pub fn new(name: &str, reflectance: [f64; 3], emission: [f64; 3]) -> Self {
        Material {
            name: name.to_string(),
            reflectance,
            emission,
            inside: false,
        }
    }

    /// The material of the back sides inside closed solids (`voxel::enclosed`): black, dark,
    /// and never searched from by propagation.
    pub fn inside_of_solids() -> Self {
        Material {
            inside: true,
            ..Material::new(INSIDE_OF_SOLIDS, [0.0; 3], [0.0; 3])
        }
    }

    pub fn is_emitter(&self) -> bool {
        self.emission.iter().any(|&e| e > 0.0)
    }

    /// Equal channels in both reflectance and emission: a scene whose used materials are all
    /// grey is solved in one channel (every solver decides it with this).
    pub fn is_grey(&self) -> bool {
        let equal = |v: &[f64; 3]| v[0] == v[1] && v[1] == v[2];
        equal(&self.reflectance) && equal(&self.emission)
    }
}

/// One triangle in world space. The front side is the one `(v1 - v0) x (v2 - v0)` points to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Triangle {
    pub vertices: [DVec3; 3],
    pub material: u32,
}

impl Triangle {
    /// Unnormalised normal `(v1 - v0) x (v2 - v0)`; its length is twice the area.
    pub fn cross(&self) -> DVec3 {
        (self.vertices[1] - self.vertices[0]).cross(self.vertices[2] - self.vertices[0])
    }

    pub fn area(&self) -> f64 {
        0.5 * self.cross().length()
    }
}

/// Axis-aligned bounds in world units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bounds {
    pub min: DVec3,
    pub max: DVec3,
}

impl Bounds {
    pub fn extent(&self) -> DVec3 {
        self.max - self.min
    }
}

/// A whole scene: triangles and the materials they name.
#[derive(Clone, Debug, Default)]
pub struct Scene {
    pub triangles: Vec<Triangle>,
    pub materials: Vec<Material>,
    /// Where the scene came from (a file path, or a generator's name), for messages.
    pub source: PathBuf,
}

/// Why a scene cannot be solved. Readers wrap this with the file and line they know.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SceneProblem {
    #[error("the scene has no surfaces (no triangle with a non-zero area)")]
    Empty,
    #[error("triangle {triangle} has a coordinate that is not a finite number")]
    NonFiniteCoordinate { triangle: usize },
    #[error("triangle {triangle} names material {material}, but only {count} materials exist")]
    MaterialOutOfRange {
        triangle: usize,
        material: u32,
        count: usize,
    },
    #[error(
        "material '{name}' has reflectance {value} in channel {channel}; \
         reflectance must be at least 0 and below 1 (1 or more would create energy)"
    )]
    BadReflectance {
        name: String,
        channel: usize,
        value: f64,
    },
    #[error(
        "material '{name}' has emission {value} in channel {channel}; \
         emission must be a finite number, 0 or more"
    )]
    BadEmission {
        name: String,
        channel: usize,
        value: f64,
    },
}

impl Scene {
    /// Bounds of all triangle vertices. Call after [`Scene::validate`].
    pub fn bounds(&self) -> Bounds {
        let mut min = DVec3::splat(f64::INFINITY);
        let mut max = DVec3::splat(f64::NEG_INFINITY);
        for t in &self.triangles {
            for v in &t.vertices {
                min = min.min(*v);
                max = max.max(*v);
            }
        }
        Bounds { min, max }
    }

    /// Checks the invariants listed in the module header. Degenerate (zero-area) triangles are
    /// allowed here and dropped by the voxelizer; a scene made only of them is `Empty`.
    pub fn validate(&self) -> Result<(), SceneProblem> {
        for m in &self.materials {
            for (channel, &value) in m.reflectance.iter().enumerate() {
                if !(0.0..1.0).contains(&value) {
                    return Err(SceneProblem::BadReflectance {
                        name: m.name.clone(),
                        channel,
                        value,
                    });
                }
            }
            for (channel, &value) in m.emission.iter().enumerate() {
                if !value.is_finite() || value < 0.0 {
                    return Err(SceneProblem::BadEmission {
                        name: m.name.clone(),
                        channel,
                        value,
                    });
                }
            }
        }
        let mut any_area = false;
        for (i, t) in self.triangles.iter().enumerate() {
            if t.vertices.iter().any(|v| !v.is_finite()) {
                return Err(SceneProblem::NonFiniteCoordinate { triangle: i });
            }
            if t.material as usize >= self.materials.len() {
                return Err(SceneProblem::MaterialOutOfRange {
                    triangle: i,
                    material: t.material,
                    count: self.materials.len(),
                });
            }
            any_area |= t.area() > 0.0;
        }
        if !any_area {
            return Err(SceneProblem::Empty);
        }
        Ok(())
    }

    /// Adds a material and returns its index.
    pub fn add_material(&mut self, material: Material) -> u32 {
        self.materials.push(material);
        (self.materials.len() - 1) as u32
    }

    /// Adds a planar convex polygon (fan-triangulated) with the given material.
    pub fn add_polygon(&mut self, points: &[DVec3], material: u32) {
        for k in 1..points.len().saturating_sub(1) {
            self.triangles.push(Triangle {
                vertices: [points[0], points[k], points[k + 1]],
                material,
            });
        }
    }

    /// Adds the six faces of an axis-aligned box, fronts facing outwards (or inwards if `inward`).
    pub fn add_box(&mut self, min: DVec3, max: DVec3, material: u32, inward: bool) {
        let c = |x: usize, y: usize, z: usize| {
            DVec3::new(
                if x == 0 { min.x } else { max.x },
                if y == 0 { min.y } else { max.y },
                if z == 0 { min.z } else { max.z },
            )
        };
        // Each face listed counter-clockwise seen from outside.
        let faces = [
            [c(0, 0, 0), c(0, 0, 1), c(0, 1, 1), c(0, 1, 0)], // -x
            [c(1, 0, 0), c(1, 1, 0), c(1, 1, 1), c(1, 0, 1)], // +x
            [c(0, 0, 0), c(1, 0, 0), c(1, 0, 1), c(0, 0, 1)], // -y
            [c(0, 1, 0), c(0, 1, 1), c(1, 1, 1), c(1, 1, 0)], // +y
            [c(0, 0, 0), c(0, 1, 0), c(1, 1, 0), c(1, 0, 0)], // -z
            [c(0, 0, 1), c(1, 0, 1), c(1, 1, 1), c(0, 1, 1)], // +z
        ];
        for mut f in faces {
            if inward {
                f.reverse();
            }
            self.add_polygon(&f, material);
        }
    }
}

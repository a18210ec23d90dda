//! The Cornell box, from the measurements published by the Cornell Program of Computer Graphics
//! ("Cornell Box data", <https://www.graphics.cornell.edu/online/box/data.html>), in millimetres
//! and in the data's own coordinates: y up, the open side at z = 0, the camera at
//! (278, 273, -800) looking along +z. Seen from the camera, the red wall (x ~ 550) is on the left
//! and the green wall (x = 0) on the right, as the data page names them.
//!
//! Deviations from the data, each on purpose:
//! - The light quad is at y = 548.7 instead of 548.8, so it does not coincide with the ceiling
//!   (a common choice, e.g. the usd-assets and McGuire versions lower it slightly).
//! - The ceiling has a rectangular hole exactly above the light (the real box has its lamp in an
//!   opening of the ceiling). Without it, the ceiling and the light would overlap over the whole
//!   lamp, 0.1 mm apart, i.e. two downward-facing surfaces in the same voxels at any usable
//!   resolution. The ceiling part hidden by the lamp sees only the lamp's back, so removing it
//!   changes nothing a camera or a probe below the lamp can see.
//!
//! Colours: the RGB reductions of the measured spectra used by Morgan McGuire's Computer Graphics
//! Archive ("CornellBox-Original", 2017) and by Benedikt Bitterli's Rendering Resources
//! ("cornell-box", 2016): white (0.725, 0.71, 0.68), red (0.63, 0.065, 0.05),
//! green (0.14, 0.45, 0.091), light radiance (17, 12, 4) with a lamp reflectance of 0.78. voxrad's
//! `Ke` is emitted radiosity, so the light gets `E = pi * L`.

use super::add_facing;
use crate::scene::{Material, Scene};
use glam::DVec3;
use std::f64::consts::PI;

/// Material indices of [`cornell_box`], in the order they are added.
pub const WHITE: u32 = 0;
pub const RED: u32 = 1;
pub const GREEN: u32 = 2;
pub const LIGHT: u32 = 3;

/// Lamp radiance `L` per channel (McGuire / Bitterli); emission is `pi * L`.
pub const LIGHT_RADIANCE: [f64; 3] = [17.0, 12.0, 4.0];
/// Height of the lamp quad (the data's 548.8 lowered by 0.1 mm, see the module header).
pub const LIGHT_Y: f64 = 548.7;
/// Height of the ceiling in the data.
pub const CEILING_Y: f64 = 548.8;
/// The lamp's extent in x and z (130 x 105 mm).
pub const LIGHT_X: [f64; 2] = [213.0, 343.0];
pub const LIGHT_Z: [f64; 2] = [227.0, 332.0];

fn p(x: f64, y: f64, z: f64) -> DVec3 {
    DVec3::new(x, y, z)
}

/// The Cornell box: 4 materials ([`WHITE`], [`RED`], [`GREEN`], [`LIGHT`]), walls facing into the
/// box, the blocks' faces facing outwards, the lamp facing down.
pub fn cornell_box() -> Scene {
    let mut s = Scene {
        source: "generator:cornell_box".into(),
        ..Scene::default()
    };
    s.add_material(Material::new("white", [0.725, 0.71, 0.68], [0.0; 3]));
    s.add_material(Material::new("red", [0.63, 0.065, 0.05], [0.0; 3]));
    s.add_material(Material::new("green", [0.14, 0.45, 0.091], [0.0; 3]));
    s.add_material(Material::new(
        "light",
        [0.78, 0.78, 0.78],
        LIGHT_RADIANCE.map(|l| PI * l),
    ));

    let up = DVec3::Y;
    let down = DVec3::NEG_Y;

    // Floor (white).
    add_facing(
        &mut s,
        &[
            p(552.8, 0.0, 0.0),
            p(0.0, 0.0, 0.0),
            p(0.0, 0.0, 559.2),
            p(549.6, 0.0, 559.2),
        ],
        up,
        WHITE,
    );

    // Ceiling (white): the data's quad 0..556 x 0..559.2, minus the lamp opening, as four
    // rectangles around it.
    let (x0, x1) = (LIGHT_X[0], LIGHT_X[1]);
    let (z0, z1) = (LIGHT_Z[0], LIGHT_Z[1]);
    let y = CEILING_Y;
    for (xa, xb, za, zb) in [
        (0.0, 556.0, 0.0, z0),
        (0.0, 556.0, z1, 559.2),
        (0.0, x0, z0, z1),
        (x1, 556.0, z0, z1),
    ] {
        add_facing(
            &mut s,
            &[p(xa, y, za), p(xb, y, za), p(xb, y, zb), p(xa, y, zb)],
            down,
            WHITE,
        );
    }

    // Back wall (white), facing the camera (-z).
    add_facing(
        &mut s,
        &[
            p(549.6, 0.0, 559.2),
            p(0.0, 0.0, 559.2),
            p(0.0, 548.8, 559.2),
            p(556.0, 548.8, 559.2),
        ],
        DVec3::NEG_Z,
        WHITE,
    );

    // Right wall (green, x = 0), facing +x.
    add_facing(
        &mut s,
        &[
            p(0.0, 0.0, 559.2),
            p(0.0, 0.0, 0.0),
            p(0.0, 548.8, 0.0),
            p(0.0, 548.8, 559.2),
        ],
        DVec3::X,
        GREEN,
    );

    // Left wall (red, x ~ 550..556; the data's quad is not planar, the fan splits it into two
    // exact triangles), facing -x.
    add_facing(
        &mut s,
        &[
            p(552.8, 0.0, 0.0),
            p(549.6, 0.0, 559.2),
            p(556.0, 548.8, 559.2),
            p(556.0, 548.8, 0.0),
        ],
        DVec3::NEG_X,
        RED,
    );

    // Blocks: the data's top quad and base footprint; sides face away from the block's axis.
    add_block(
        &mut s,
        &[(130.0, 65.0), (82.0, 225.0), (240.0, 272.0), (290.0, 114.0)],
        165.0,
    );
    add_block(
        &mut s,
        &[
            (423.0, 247.0),
            (265.0, 296.0),
            (314.0, 456.0),
            (472.0, 406.0),
        ],
        330.0,
    );

    // Light, facing down.
    add_facing(
        &mut s,
        &[
            p(x1, LIGHT_Y, z0),
            p(x1, LIGHT_Y, z1),
            p(x0, LIGHT_Y, z1),
            p(x0, LIGHT_Y, z0),
        ],
        down,
        LIGHT,
    );
    s
}

/// A block standing on the floor: its top (facing up) and its four sides (facing out). The data
/// gives no bottom face (it would lie on the floor, invisible).
fn add_block(s: &mut Scene, footprint: &[(f64, f64); 4], height: f64) {
    let top: Vec<DVec3> = footprint.iter().map(|&(x, z)| p(x, height, z)).collect();
    add_facing(s, &top, DVec3::Y, WHITE);
    let centre = footprint
        .iter()
        .fold(DVec3::ZERO, |acc, &(x, z)| acc + p(x, 0.0, z))
        / 4.0;
    for k in 0..4 {
        let (ax, az) = footprint[k];
        let (bx, bz) = footprint[(k + 1) % 4];
        let side = [
            p(ax, 0.0, az),
            p(bx, 0.0, bz),
            p(bx, height, bz),
            p(ax, height, az),
        ];
        let mid = p(0.5 * (ax + bx), 0.0, 0.5 * (az + bz));
        add_facing(s, &side, mid - centre, WHITE);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn centroid(t: &crate::scene::Triangle) -> DVec3 {
        (t.vertices[0] + t.vertices[1] + t.vertices[2]) / 3.0
    }

    #[test]
    fn validates_with_four_materials() {
        let s = cornell_box();
        assert_eq!(s.validate(), Ok(()));
        assert_eq!(s.materials.len(), 4);
        let names: Vec<&str> = s.materials.iter().map(|m| m.name.as_str()).collect();
        assert_eq!(names, ["white", "red", "green", "light"]);
        // 1 floor + 4 ceiling pieces + back + 2 side walls = 8 quads, 2 blocks x 5 quads, 1 light.
        assert_eq!(s.triangles.len(), 2 * (8 + 10 + 1));
        for t in &s.triangles {
            assert!(t.area() > 0.0);
        }
    }

    #[test]
    fn walls_face_the_box_centre() {
        let s = cornell_box();
        let b = s.bounds();
        let centre = 0.5 * (b.min + b.max);
        // Room surfaces are those on the bounding planes (floor, ceiling, walls); their fronts
        // must face the centre.
        let mut room = 0;
        for t in &s.triangles {
            let c = centroid(t);
            let on_shell = c.y < 1e-9
                || (c.y - CEILING_Y).abs() < 1e-9
                || c.z > 559.2 - 1e-9
                || c.x < 1e-9
                || c.x > 549.0;
            if t.material == LIGHT || !on_shell {
                continue;
            }
            room += 1;
            assert!(
                t.cross().dot(centre - c) > 0.0,
                "a wall triangle at {c:?} faces away from the centre"
            );
        }
        // Floor 2 + ceiling 8 + back 2 + green 2 + red 2.
        assert_eq!(room, 16);
    }

    #[test]
    fn block_faces_face_outwards_and_tops_up() {
        let s = cornell_box();
        for (x_range, height) in [((80.0, 295.0), 165.0), ((260.0, 475.0), 330.0)] {
            let tris: Vec<_> = s
                .triangles
                .iter()
                .filter(|t| {
                    let c = centroid(t);
                    c.y > 1e-9
                        && c.y <= height + 1e-9
                        && t.vertices
                            .iter()
                            .all(|v| v.x >= x_range.0 && v.x <= x_range.1)
                        && t.vertices.iter().all(|v| v.y <= height + 1e-9)
                        && t.vertices.iter().all(|v| v.z > 1.0 && v.z < 500.0)
                })
                .collect();
            assert_eq!(tris.len(), 10);
            let centre = tris.iter().map(|t| centroid(t)).sum::<DVec3>() / tris.len() as f64;
            for t in tris {
                let n = t.cross().normalize();
                if (centroid(t).y - height).abs() < 1e-9 {
                    assert!(n.y > 0.999, "block top must face up");
                } else {
                    let out = centroid(t) - centre;
                    assert!(DVec3::new(out.x, 0.0, out.z).dot(n) > 0.0);
                    assert!(n.y.abs() < 1e-9);
                }
            }
        }
    }

    #[test]
    fn light_faces_down_with_the_measured_area() {
        let s = cornell_box();
        let lights: Vec<_> = s.triangles.iter().filter(|t| t.material == LIGHT).collect();
        assert_eq!(lights.len(), 2);
        let area: f64 = lights.iter().map(|t| t.area()).sum();
        assert!((area - 130.0 * 105.0).abs() < 1e-6);
        for t in &lights {
            let n = t.cross().normalize();
            assert!((n - DVec3::NEG_Y).length() < 1e-12);
            assert!(t.vertices.iter().all(|v| v.y == LIGHT_Y));
        }
        let e = s.materials[LIGHT as usize].emission;
        for c in 0..3 {
            assert!((e[c] - PI * LIGHT_RADIANCE[c]).abs() < 1e-12);
        }
        assert!(s.materials.iter().filter(|m| m.is_emitter()).count() == 1);
    }

    #[test]
    fn ceiling_hole_matches_the_lamp() {
        let s = cornell_box();
        let ceiling: f64 = s
            .triangles
            .iter()
            .filter(|t| t.vertices.iter().all(|v| v.y == CEILING_Y))
            .map(|t| t.area())
            .sum();
        assert!((ceiling - (556.0 * 559.2 - 130.0 * 105.0)).abs() < 1e-6);
    }
}

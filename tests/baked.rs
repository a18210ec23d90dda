//! The baked outputs of a default solve, opened as their users' tools open them:
//!
//! - `baked.glb` passes Khronos' glTF validator (npm `gltf-validator`, installed by `.ci/run` into
//!   `tools/gltf-validate`; this test fails, saying so, where it is missing), and its
//!   `_RADIOSITY` attribute holds the same floats as `baked.ply`;
//! - the baked radiosity, interpolated across the baked triangles at the probes of the
//!   path-traced reference (`tests/data/reference/cornell`), is as close to the reference as
//!   `voxrad probe` at those points; and a baked vertex holds what `voxrad probe` answers there;
//! - `render.exr` reads back as RGBA with the picture's linear radiosity;
//! - `voxrad bake` writes the same mesh as the solve did, and refuses an unknown extension.

use std::path::{Path, PathBuf};
use std::process::Command;
use tempfile::TempDir;
use voxrad::study::reference::Reference;

mod common;
use common::cli::*;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The baked mesh as read back from `baked.ply`.
struct Mesh {
    positions: Vec<[f32; 3]>,
    normals: Vec<[f32; 3]>,
    radiosity: Vec<[f32; 3]>,
    faces: Vec<[u32; 3]>,
}

fn f32_at(b: &[u8], at: usize) -> f32 {
    f32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

/// Reads the binary PLY `voxrad` writes (the layout its header declares, checked here).
fn read_ply(path: &Path) -> Mesh {
    let bytes = std::fs::read(path).unwrap();
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("PLY header end")
        + 11;
    let header = std::str::from_utf8(&bytes[..end]).unwrap();
    let count = |element: &str| -> usize {
        header
            .lines()
            .find_map(|l| l.strip_prefix(&format!("element {element} ")))
            .unwrap_or_else(|| panic!("no element {element}"))
            .parse()
            .unwrap()
    };
    let properties: Vec<&str> = header
        .lines()
        .filter(|l| l.starts_with("property"))
        .collect();
    assert_eq!(
        properties,
        [
            "property float x",
            "property float y",
            "property float z",
            "property float nx",
            "property float ny",
            "property float nz",
            "property float radiosity_r",
            "property float radiosity_g",
            "property float radiosity_b",
            "property uchar red",
            "property uchar green",
            "property uchar blue",
            "property list uchar uint vertex_indices",
        ]
    );
    assert!(header.starts_with("ply\nformat binary_little_endian 1.0\n"));
    let (vertices, faces) = (count("vertex"), count("face"));
    assert_eq!(bytes.len(), end + vertices * 39 + faces * 13, "PLY length");
    let mut mesh = Mesh {
        positions: Vec::new(),
        normals: Vec::new(),
        radiosity: Vec::new(),
        faces: Vec::new(),
    };
    for v in 0..vertices {
        let at = end + 39 * v;
        let f = |k: usize| f32_at(&bytes, at + 4 * k);
        mesh.positions.push([f(0), f(1), f(2)]);
        mesh.normals.push([f(3), f(4), f(5)]);
        mesh.radiosity.push([f(6), f(7), f(8)]);
    }
    for t in 0..faces {
        let at = end + 39 * vertices + 13 * t;
        assert_eq!(bytes[at], 3);
        let face = [0, 1, 2].map(|k| u32_at(&bytes, at + 1 + 4 * k));
        assert!(face.iter().all(|&i| (i as usize) < vertices));
        mesh.faces.push(face);
    }
    mesh
}

/// The floats of accessor `name` of the GLB's only mesh primitive.
fn glb_attribute(path: &Path, name: &str) -> Vec<[f32; 3]> {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[..4], b"glTF");
    assert_eq!(u32_at(&bytes, 4), 2);
    assert_eq!(u32_at(&bytes, 8) as usize, bytes.len());
    let json_len = u32_at(&bytes, 12) as usize;
    assert_eq!(&bytes[16..20], b"JSON");
    let json: serde_json::Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
    let bin_at = 20 + json_len;
    assert_eq!(&bytes[bin_at + 4..bin_at + 8], b"BIN\0");
    let bin = &bytes[bin_at + 8..];
    let accessor_index = json["meshes"][0]["primitives"][0]["attributes"][name]
        .as_u64()
        .unwrap_or_else(|| panic!("no attribute {name}")) as usize;
    let accessor = &json["accessors"][accessor_index];
    assert_eq!(accessor["type"], "VEC3");
    assert_eq!(accessor["componentType"], 5126);
    let view = &json["bufferViews"][accessor["bufferView"].as_u64().unwrap() as usize];
    let offset = view["byteOffset"].as_u64().unwrap_or(0) as usize;
    let count = accessor["count"].as_u64().unwrap() as usize;
    (0..count)
        .map(|i| [0, 1, 2].map(|k| f32_at(bin, offset + 12 * i + 4 * k)))
        .collect()
}

/// Runs Khronos' validator on `glb`; panics with its report on an error, or when it is not
/// installed.
fn validate_gltf(glb: &Path) {
    let tool = root().join("tools/gltf-validate");
    assert!(
        tool.join("node_modules/gltf-validator").is_dir(),
        "Khronos' glTF validator is not installed: run `npm ci --prefix tools/gltf-validate` \
         (Node.js and npm; `.ci/run` does it)"
    );
    let out = Command::new("node")
        .arg(tool.join("validate.js"))
        .arg(glb)
        .output()
        .expect("run node (Node.js is needed for the glTF validator)");
    let report = String::from_utf8_lossy(&out.stdout);
    println!("{report}");
    assert!(
        out.status.success(),
        "the glTF validator finds errors:\n{report}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(report.contains(" 0 errors, 0 warnings"), "{report}");
}

/// The baked radiosity (sum of channels) at `p` on the side facing `n`: interpolated in the
/// baked triangle of that side that contains `p`, if any.
fn baked_at(mesh: &Mesh, p: [f64; 3], n: [f64; 3], tolerance: f64) -> Option<f64> {
    let v = |k: u32| mesh.positions[k as usize].map(f64::from);
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    for t in &mesh.faces {
        let normal = mesh.normals[t[0] as usize].map(f64::from);
        if dot(normal, n) < 0.99 {
            continue;
        }
        let (a, b, c) = (v(t[0]), v(t[1]), v(t[2]));
        if dot(sub(p, a), normal).abs() > tolerance {
            continue;
        }
        // Barycentric weights in the triangle's plane.
        let (e1, e2, q) = (sub(b, a), sub(c, a), sub(p, a));
        let (d11, d12, d22) = (dot(e1, e1), dot(e1, e2), dot(e2, e2));
        let (q1, q2) = (dot(q, e1), dot(q, e2));
        let det = d11 * d22 - d12 * d12;
        if det <= 0.0 {
            continue;
        }
        let w1 = (d22 * q1 - d12 * q2) / det;
        let w2 = (d11 * q2 - d12 * q1) / det;
        let w0 = 1.0 - w1 - w2;
        let slack = -1e-6;
        if !(w0 >= slack && w1 >= slack && w2 >= slack) {
            continue;
        }
        let sum = |k: u32| {
            mesh.radiosity[k as usize]
                .iter()
                .map(|&x| x as f64)
                .sum::<f64>()
        };
        return Some(w0 * sum(t[0]) + w1 * sum(t[1]) + w2 * sum(t[2]));
    }
    None
}

/// `voxrad probe` rows (header, then 12 numbers a row).
fn probe(dir: &Path, points: &Path) -> Vec<Vec<f64>> {
    let o = voxrad(&["probe", &s(dir), "--points", &s(points)]);
    assert_ok(&o, "probe");
    let text = String::from_utf8(o.stdout).unwrap();
    text.lines()
        .skip(1)
        .map(|l| l.split(',').map(|x| x.parse().unwrap()).collect())
        .collect()
}

#[test]
fn a_default_solve_bakes_a_valid_mesh_as_right_as_the_probes() {
    let tmp = TempDir::new().unwrap();
    let out = tmp.path().join("cornell");
    let o = voxrad(&[
        "solve",
        &s(&root().join("examples/cornell_box.obj")),
        "--out",
        &s(&out),
        "--resolution",
        "64",
        "--threads",
        "2",
    ]);
    assert_ok(&o, "solve");
    let glb = out.join("baked.glb");
    validate_gltf(&glb);
    let mesh = read_ply(&out.join("baked.ply"));
    assert!(mesh.faces.len() > 1000, "{} triangles", mesh.faces.len());
    assert_eq!(glb_attribute(&glb, "_RADIOSITY"), mesh.radiosity);
    assert_eq!(glb_attribute(&glb, "POSITION"), mesh.positions);
    for n in &mesh.normals {
        let length = n.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((length - 1.0).abs() < 1e-5, "normal {n:?}");
    }

    // Against the path-traced reference, at its probes: the baked mesh, interpolated, and
    // `voxrad probe`.
    let reference_dir = root().join("tests/data/reference/cornell");
    let reference = Reference::load(&reference_dir).unwrap();
    let voxel = 556.0 / 64.0;
    let baked: Vec<Option<f64>> = reference
        .points()
        .iter()
        .map(|(p, n)| {
            let n = n.normalize();
            baked_at(&mesh, p.to_array(), n.to_array(), 1e-3 * voxel)
        })
        .collect();
    let probed: Vec<Option<f64>> = probe(&out, &reference_dir.join("probes.csv"))
        .iter()
        .map(|row| Some(row[6] + row[7] + row[8]))
        .collect();
    let (b, p) = (reference.compare(&baked), reference.compare(&probed));
    println!(
        "baked: mean {:.2} %, max {:.1} % over {} probes; probe: mean {:.2} %, max {:.1} % over {}",
        100.0 * b.mean,
        100.0 * b.max,
        b.compared,
        100.0 * p.mean,
        100.0 * p.max,
        p.compared
    );
    assert!(
        b.compared * 10 >= reference.probes.len() * 9,
        "only {} of {} probes lie on a baked triangle",
        b.compared,
        reference.probes.len()
    );
    assert!(
        b.mean <= p.mean + 0.005,
        "the baked mesh is further from the reference ({:.2} %) than the probes ({:.2} %)",
        100.0 * b.mean,
        100.0 * p.mean
    );
    assert!(
        p.mean < 0.04 && b.mean < 0.04,
        "mean errors {} / {}",
        b.mean,
        p.mean
    );

    // A baked vertex holds what `voxrad probe` answers there, on its side.
    let points = tmp.path().join("vertices.csv");
    let step = (mesh.positions.len() / 300).max(1);
    let picked: Vec<usize> = (0..mesh.positions.len()).step_by(step).collect();
    let text: String = picked
        .iter()
        .map(|&k| {
            let (p, n) = (mesh.positions[k], mesh.normals[k]);
            format!("{},{},{},{},{},{}\n", p[0], p[1], p[2], n[0], n[1], n[2])
        })
        .collect();
    std::fs::write(&points, format!("x,y,z,nx,ny,nz\n{text}")).unwrap();
    for (row, &k) in probe(&out, &points).iter().zip(&picked) {
        for c in 0..3 {
            let (probed, baked) = (row[6 + c], mesh.radiosity[k][c] as f64);
            assert!(
                (probed - baked).abs() <= 1e-5 * probed.abs().max(1e-3),
                "vertex {k}: probe {probed} vs baked {baked}"
            );
        }
    }

    // render.exr: RGBA, the picture's size, linear radiosity where something is drawn.
    let image = exr::prelude::read_first_rgba_layer_from_file(
        out.join("render.exr"),
        |resolution, _| vec![vec![[0f32; 4]; resolution.width()]; resolution.height()],
        |pixels, position, (r, g, b, a): (f32, f32, f32, f32)| {
            pixels[position.y()][position.x()] = [r, g, b, a]
        },
    )
    .expect("read render.exr");
    let pixels = &image.layer_data.channel_data.pixels;
    assert_eq!((pixels.len(), pixels[0].len()), (600, 800));
    let drawn: Vec<&[f32; 4]> = pixels.iter().flatten().filter(|p| p[3] == 1.0).collect();
    assert!(drawn.len() > 800 * 600 / 2, "{} pixels drawn", drawn.len());
    assert!(drawn
        .iter()
        .all(|p| p[..3].iter().all(|&c| c.is_finite() && c >= 0.0)));
    // The lamp (E up to 53) is the brightest thing in view.
    let brightest = drawn.iter().map(|p| p[0]).fold(0.0f32, f32::max);
    assert!(brightest > 40.0, "brightest red {brightest}");

    // `voxrad bake` makes the same mesh from the results; an unknown extension is refused.
    let again = tmp.path().join("again.glb");
    let o = voxrad(&["bake", &s(&out), "--out", &s(&again)]);
    assert_ok(&o, "bake");
    assert_eq!(
        std::fs::read(&again).unwrap(),
        std::fs::read(&glb).unwrap(),
        "voxrad bake and the solve bake differently"
    );
    let o = voxrad(&["bake", &s(&out), "--out", &s(&tmp.path().join("x.obj"))]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("x.obj"));
}

//! A [`BakedMesh`] as glTF 2.0 binary (`baked.glb`): one mesh, one unlit material, per-vertex
//! `POSITION`, `NORMAL`, `COLOR_0` (the display colour, linear, as the preview's tone map makes
//! it) and `_RADIOSITY` (the linear radiosity `B`, float RGB, units of `Ke`).
//!
//! The material is `KHR_materials_unlit` with a white base colour, so a viewer shows `COLOR_0`
//! as it is (lighting the baked light again would count it twice); it is single-sided, since the
//! lit backs of two-sided surfaces are triangles of their own. The JSON is built with
//! `gltf-json`; the GLB container (a 12-byte header, a JSON chunk padded with spaces, a binary
//! chunk padded with zeros, every length a multiple of 4) is written here.

use super::bake::BakedMesh;
use super::{atomic, OutputError};
use gltf_json as json;
use json::validation::Checked::Valid;
use json::validation::USize64;
use std::collections::BTreeMap;
use std::path::Path;

/// `glTF` in little-endian.
const GLB_MAGIC: u32 = 0x4654_6C67;
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;

/// Writes `mesh` to `path` as GLB; returns the file's length in bytes.
pub fn write_glb(path: &Path, mesh: &BakedMesh) -> Result<u64, OutputError> {
    let (json, bin) = encode(path, mesh)?;
    let json_len = json.len().next_multiple_of(4);
    let bin_len = bin.len().next_multiple_of(4);
    let total = 12 + 8 + json_len + if bin.is_empty() { 0 } else { 8 + bin_len };
    let total32 = u32::try_from(total).map_err(|_| {
        OutputError::invalid(
            path,
            format!("the baked mesh needs {total} bytes; a GLB file holds at most 4 GiB"),
        )
    })?;
    atomic::write_atomically(path, |w| {
        for word in [GLB_MAGIC, 2, total32, json_len as u32, CHUNK_JSON] {
            w.write_all(&word.to_le_bytes())?;
        }
        w.write_all(&json)?;
        w.write_all(&vec![b' '; json_len - json.len()])?;
        if !bin.is_empty() {
            w.write_all(&(bin_len as u32).to_le_bytes())?;
            w.write_all(&CHUNK_BIN.to_le_bytes())?;
            w.write_all(&bin)?;
            w.write_all(&vec![0u8; bin_len - bin.len()])?;
        }
        Ok(())
    })?;
    Ok(total as u64)
}

/// The JSON chunk and the binary chunk (unpadded) of `mesh`.
fn encode(path: &Path, mesh: &BakedMesh) -> Result<(Vec<u8>, Vec<u8>), OutputError> {
    let vertices = mesh.positions.len();
    if u32::try_from(vertices).is_err() {
        return Err(OutputError::invalid(
            path,
            format!("{vertices} vertices is more than 32-bit indices can name"),
        ));
    }
    let colours: Vec<[f32; 3]> = (0..vertices).map(|v| mesh.linear_colour(v)).collect();
    let mut root = json::Root {
        asset: json::Asset {
            generator: Some(format!("voxrad {}", env!("CARGO_PKG_VERSION"))),
            version: "2.0".to_string(),
            ..Default::default()
        },
        extensions_used: vec!["KHR_materials_unlit".to_string()],
        ..Default::default()
    };
    let mut bin: Vec<u8> = Vec::new();
    let buffer = json::Index::<json::Buffer>::new(0);
    // One buffer view per array, each starting on a multiple of 4.
    let mut view = |root: &mut json::Root, bytes: &[u8], target: json::buffer::Target| {
        let offset = bin.len();
        bin.extend_from_slice(bytes);
        root.push(json::buffer::View {
            buffer,
            byte_length: USize64::from(bytes.len()),
            byte_offset: Some(USize64::from(offset)),
            byte_stride: None,
            extensions: None,
            extras: Default::default(),
            name: None,
            target: Some(Valid(target)),
        })
    };
    let vec3 = |root: &mut json::Root,
                view: json::Index<json::buffer::View>,
                bounds: Option<([f32; 3], [f32; 3])>| {
        root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: None,
            count: USize64::from(vertices),
            component_type: Valid(json::accessor::GenericComponentType(
                json::accessor::ComponentType::F32,
            )),
            extensions: None,
            extras: Default::default(),
            type_: Valid(json::accessor::Type::Vec3),
            min: bounds.map(|b| json::Value::from(b.0.to_vec())),
            max: bounds.map(|b| json::Value::from(b.1.to_vec())),
            name: None,
            normalized: false,
            sparse: None,
        })
    };
    let mut attributes = BTreeMap::new();
    let arrays: [(json::mesh::Semantic, &[[f32; 3]]); 4] = [
        (json::mesh::Semantic::Positions, &mesh.positions),
        (json::mesh::Semantic::Normals, &mesh.normals),
        (json::mesh::Semantic::Colors(0), &colours),
        (
            json::mesh::Semantic::Extras("RADIOSITY".to_string()),
            &mesh.radiosity,
        ),
    ];
    for (semantic, values) in arrays {
        // glTF requires the bounds of positions.
        let bounds = matches!(semantic, json::mesh::Semantic::Positions).then(|| bounds(values));
        let v = view(
            &mut root,
            bytemuck::cast_slice(values),
            json::buffer::Target::ArrayBuffer,
        );
        let accessor = vec3(&mut root, v, bounds);
        attributes.insert(Valid(semantic), accessor);
    }
    let v = view(
        &mut root,
        bytemuck::cast_slice(&mesh.indices),
        json::buffer::Target::ElementArrayBuffer,
    );
    let indices = root.push(json::Accessor {
        buffer_view: Some(v),
        byte_offset: None,
        count: USize64::from(mesh.indices.len()),
        component_type: Valid(json::accessor::GenericComponentType(
            json::accessor::ComponentType::U32,
        )),
        extensions: None,
        extras: Default::default(),
        type_: Valid(json::accessor::Type::Scalar),
        min: None,
        max: None,
        name: None,
        normalized: false,
        sparse: None,
    });
    // The struct update stays for the fields that other features of `gltf-json` add.
    #[allow(clippy::needless_update)]
    let material = root.push(json::Material {
        name: Some("baked radiosity (unlit)".to_string()),
        extensions: Some(json::extensions::material::Material {
            unlit: Some(json::extensions::material::Unlit {}),
            ..Default::default()
        }),
        ..Default::default()
    });
    let mesh_index = root.push(json::Mesh {
        extensions: None,
        extras: Default::default(),
        name: Some("baked".to_string()),
        primitives: vec![json::mesh::Primitive {
            attributes,
            extensions: None,
            extras: Default::default(),
            indices: Some(indices),
            material: Some(material),
            mode: Valid(json::mesh::Mode::Triangles),
            targets: None,
        }],
        weights: None,
    });
    let node = root.push(json::Node {
        mesh: Some(mesh_index),
        name: Some("scene".to_string()),
        ..Default::default()
    });
    let scene = root.push(json::Scene {
        extensions: None,
        extras: Default::default(),
        name: None,
        nodes: vec![node],
    });
    root.scene = Some(scene);
    root.push(json::Buffer {
        byte_length: USize64::from(bin.len()),
        extensions: None,
        extras: Default::default(),
        name: None,
        uri: None,
    });
    let json = root.to_vec().map_err(|source| OutputError::Json {
        path: path.to_path_buf(),
        source,
    })?;
    Ok((json, bin))
}

/// Componentwise minimum and maximum of `values`.
fn bounds(values: &[[f32; 3]]) -> ([f32; 3], [f32; 3]) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for v in values {
        for k in 0..3 {
            lo[k] = lo[k].min(v[k]);
            hi[k] = hi[k].max(v[k]);
        }
    }
    (lo, hi)
}

//! The generated motion as one animated glTF 2.0 binary (`.glb`): a skinned stand-in body
//! on the SMPL-X-topology skeleton, the grasped object, and one animation.
//!
//! Layout (indices are fixed, the integration test relies on them):
//! * nodes `0..55`: the joints, named as the bundle's skeleton, parented as its tree.
//!   Rest TRS = the bind pose: translation `J'_j − J'_parent` (`J'_0` for the pelvis),
//!   no rotation. `J' = S J` is the bundle's rest skeleton in glTF's basis, the same basis
//!   change the frames got (the engine runs in `CoordinateSystem::Gltf` for a glb).
//! * node 55 `body`: mesh 0 with skin 0 (a root node without TRS, as the spec wants for a
//!   skinned mesh); node 56: the object, mesh 1.
//! * scene 0 = nodes 0, 55, 56.
//! * skin 0: joints = nodes 0..55, inverse bind matrices `translate(−J'_j)`, skeleton = 0.
//! * animation 0, every sampler LINEAR over the frame times `frame_index / fps`:
//!   pelvis translation (= the frame's `root_translation`, the pelvis WORLD position,
//!   which replaces the rest translation `J'_0` rather than adding to it) and rotation;
//!   the local rotation of joints 1..21 and 25..54 (jaw and eyes stay at rest); the
//!   object's translation and rotation (its mesh is in its own frame, so the node's TRS
//!   is exactly `object_translation` / `object_rotation`).
//!
//! With node TRS `T(t) R(q)` and world = parent world · local, the world position of joint
//! `j` is `p_parent + G_parent (J'_j − J'_parent)`: the engine's own forward kinematics
//! (src/skeleton.rs), so the glb reproduces `joint_positions`.
use comgrasp::skeleton::mat_vec;
use comgrasp::{CoordinateSystem, Frame};
use serde_json::{json, Value};

use crate::body_mesh;
use crate::scene::Scene;

/// Joints whose rotation the frames animate (jaw 22 and eyes 23, 24 are not modelled).
fn animated(j: usize) -> bool {
    !(22..=24).contains(&j)
}

const FLOAT: u32 = 5126;
const UNSIGNED_BYTE: u32 = 5121;
const UNSIGNED_SHORT: u32 = 5123;
const UNSIGNED_INT: u32 = 5125;
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;

/// The binary chunk and the bufferViews / accessors describing it.
#[derive(Default)]
struct Bin {
    data: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Bin {
    /// A new bufferView holding `bytes`, 4-byte aligned (every component type here is at
    /// most 4 bytes, and vertex attributes must start at multiples of 4).
    fn view(&mut self, bytes: &[u8], target: Option<u32>) -> usize {
        self.data.resize(self.data.len().next_multiple_of(4), 0);
        let mut v = json!({ "buffer": 0, "byteOffset": self.data.len(), "byteLength": bytes.len() });
        if let Some(t) = target {
            v["target"] = json!(t);
        }
        self.data.extend_from_slice(bytes);
        self.views.push(v);
        self.views.len() - 1
    }

    fn accessor(&mut self, view: usize, component: u32, count: usize, kind: &str) -> usize {
        self.accessors.push(json!({ "bufferView": view, "componentType": component, "count": count, "type": kind }));
        self.accessors.len() - 1
    }

    /// Float data of `width` components per element; `bounds` adds the exact per-component
    /// min/max (required for POSITION and animation inputs).
    fn floats(&mut self, values: &[f32], width: usize, kind: &str, target: Option<u32>, bounds: bool) -> usize {
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes, target);
        let a = self.accessor(view, FLOAT, values.len() / width, kind);
        if bounds {
            let (mut lo, mut hi) = (vec![f32::INFINITY; width], vec![f32::NEG_INFINITY; width]);
            for e in values.chunks_exact(width) {
                for k in 0..width {
                    lo[k] = lo[k].min(e[k]);
                    hi[k] = hi[k].max(e[k]);
                }
            }
            // As f64: the exact value of each f32, so a reader comparing in either
            // precision finds the declared bound equal to the data.
            self.accessors[a]["min"] = json!(lo.iter().map(|&v| f64::from(v)).collect::<Vec<_>>());
            self.accessors[a]["max"] = json!(hi.iter().map(|&v| f64::from(v)).collect::<Vec<_>>());
        }
        a
    }

    /// Triangle indices as UNSIGNED_SHORT when they fit (65535 is reserved for primitive
    /// restart), else UNSIGNED_INT.
    fn indices(&mut self, indices: &[u32], vertex_count: usize) -> usize {
        let (bytes, component): (Vec<u8>, u32) = if vertex_count < 65_535 {
            (indices.iter().flat_map(|&i| (i as u16).to_le_bytes()).collect(), UNSIGNED_SHORT)
        } else {
            (indices.iter().flat_map(|&i| i.to_le_bytes()).collect(), UNSIGNED_INT)
        };
        let view = self.view(&bytes, Some(ELEMENT_ARRAY_BUFFER));
        self.accessor(view, component, indices.len(), "SCALAR")
    }
}

/// Builds the glb. `scene` must be in glTF coordinates, and `frames` (at least one) from an
/// engine running in them; `prompt` and `fps` are recorded in the scene's `extras`.
pub fn glb(scene: &Scene, frames: &[Frame], prompt: &str, fps: f64) -> Result<Vec<u8>, String> {
    if scene.coords != CoordinateSystem::CG_COORDS_GLTF {
        return Err(format!("a glb needs glTF coordinates, the frames are in {:?}", scene.coords));
    }
    if frames.is_empty() {
        return Err("the motion has no frames; nothing to animate".into());
    }
    let n = scene.rest.len();
    if n > 256 || scene.parents.len() != n || scene.joint_names.len() != n {
        return Err(format!("skeleton with {n} joints cannot be written (1..=256, names and parents for each)"));
    }
    let mut bin = Bin::default();

    // Joint nodes in the bind pose.
    let mut nodes: Vec<Value> = (0..n)
        .map(|j| {
            let p = scene.parents[j];
            let t = if p < 0 {
                scene.rest[j]
            } else {
                let (c, q) = (scene.rest[j], scene.rest[p as usize]);
                [c[0] - q[0], c[1] - q[1], c[2] - q[2]]
            };
            json!({ "name": scene.joint_names[j], "translation": t })
        })
        .collect();
    for (j, &p) in scene.parents.iter().enumerate() {
        if p >= 0 {
            let parent = &mut nodes[p as usize];
            if parent.get("children").is_none() {
                parent["children"] = json!([]);
            }
            parent["children"].as_array_mut().expect("set above").push(json!(j));
        }
    }

    // The skinned body (mesh 0) and the skin.
    let body = body_mesh::build(&scene.rest, &scene.parents, 1.0);
    let nv = body.positions.len();
    let body_pos = bin.floats(body.positions.as_flattened(), 3, "VEC3", Some(ARRAY_BUFFER), true);
    let body_nrm = bin.floats(body.normals.as_flattened(), 3, "VEC3", Some(ARRAY_BUFFER), false);
    // One joint per vertex: the other three slots are 0 with weight 0, as the validator
    // wants unused slots to be.
    let joints: Vec<u8> = body.joints.iter().flat_map(|&j| [j, 0, 0, 0]).collect();
    let joints_view = bin.view(&joints, Some(ARRAY_BUFFER));
    let body_joints = bin.accessor(joints_view, UNSIGNED_BYTE, nv, "VEC4");
    let weights: Vec<f32> = (0..nv).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect();
    let body_weights = bin.floats(&weights, 4, "VEC4", Some(ARRAY_BUFFER), false);
    let body_idx = bin.indices(&body.indices, nv);
    // Column-major translate(−J'_j): the inverse of each joint's bind-pose world matrix.
    let ibm: Vec<f32> = scene
        .rest
        .iter()
        .flat_map(|r| [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, -r[0], -r[1], -r[2], 1.0])
        .collect();
    let ibm = bin.floats(&ibm, 16, "MAT4", None, false);
    let body_node = nodes.len();
    nodes.push(json!({ "name": "body", "mesh": 0, "skin": 0 }));

    // The object (mesh 1), one vertex per corner so creases stay sharp.
    let (obj_pos, obj_nrm) = scene.object.mesh.corners_with_normals(40.0);
    if obj_pos.is_empty() {
        return Err(format!("object {}: its mesh has only zero-area faces", scene.object.name));
    }
    let obj_pos = bin.floats(obj_pos.as_flattened(), 3, "VEC3", Some(ARRAY_BUFFER), true);
    let obj_nrm = bin.floats(obj_nrm.as_flattened(), 3, "VEC3", Some(ARRAY_BUFFER), false);
    let object_node = nodes.len();
    let f0 = &frames[0];
    nodes.push(json!({
        "name": scene.object.name,
        "mesh": 1,
        "translation": f0.object_translation,
        "rotation": f0.object_rotation,
    }));

    // The table top the object starts on (mesh 2, static), as the contact stage models it.
    let mut scene_nodes = vec![0, body_node, object_node];
    let mut meshes = vec![
        json!({ "name": "body", "primitives": [{
            "attributes": { "POSITION": body_pos, "NORMAL": body_nrm, "JOINTS_0": body_joints, "WEIGHTS_0": body_weights },
            "indices": body_idx, "material": 0 }] }),
        json!({ "name": scene.object.name, "primitives": [{
            "attributes": { "POSITION": obj_pos, "NORMAL": obj_nrm }, "material": 1 }] }),
    ];
    if let Some(corners) = scene.table(f0) {
        let (s, c) = scene.coords.basis();
        let top: Vec<f32> = corners.iter().flat_map(|p| mat_vec(&s, p).map(|v| (v * c) as f32)).collect();
        let up = mat_vec(&s, &[0.0, 0.0, 1.0]).map(|v| v as f32);
        let normals: Vec<f32> = (0..4).flat_map(|_| up).collect();
        let top_pos = bin.floats(&top, 3, "VEC3", Some(ARRAY_BUFFER), true);
        let top_nrm = bin.floats(&normals, 3, "VEC3", Some(ARRAY_BUFFER), false);
        // Counter-clockwise seen from above (the corners go clockwise about +z).
        let top_idx = bin.indices(&[0, 2, 1, 0, 3, 2], 4);
        meshes.push(json!({ "name": "table", "primitives": [{
            "attributes": { "POSITION": top_pos, "NORMAL": top_nrm }, "indices": top_idx, "material": 2 }] }));
        scene_nodes.push(nodes.len());
        nodes.push(json!({ "name": "table", "mesh": 2 }));
    }

    // The animation.
    let times: Vec<f32> = frames.iter().map(|f| f.time_s as f32).collect();
    if times.windows(2).any(|w| w[1] <= w[0]) {
        return Err("frame times are not strictly increasing".into());
    }
    let input = bin.floats(&times, 1, "SCALAR", None, true);
    let mut samplers = Vec::new();
    let mut channels = Vec::new();
    let mut channel = |bin: &mut Bin, node: usize, path: &str, values: Vec<f32>, width: usize| {
        let output = bin.floats(&values, width, if width == 3 { "VEC3" } else { "VEC4" }, None, false);
        channels.push(json!({ "sampler": samplers.len(), "target": { "node": node, "path": path } }));
        samplers.push(json!({ "input": input, "output": output, "interpolation": "LINEAR" }));
    };
    channel(&mut bin, 0, "translation", frames.iter().flat_map(|f| f.root_translation).collect(), 3);
    channel(&mut bin, 0, "rotation", continuous(frames.iter().map(|f| f.root_rotation)), 4);
    for j in (1..n).filter(|&j| animated(j)) {
        let q = frames.iter().map(|f| local_rotation(f, j));
        channel(&mut bin, j, "rotation", continuous(q), 4);
    }
    channel(&mut bin, object_node, "translation", frames.iter().flat_map(|f| f.object_translation).collect(), 3);
    channel(&mut bin, object_node, "rotation", continuous(frames.iter().map(|f| f.object_rotation)), 4);

    let root = json!({
        "asset": { "version": "2.0", "generator": format!("comgrasp {}", env!("CARGO_PKG_VERSION")) },
        "scene": 0,
        "scenes": [{
            "name": "comgrasp",
            "nodes": scene_nodes,
            "extras": { "prompt": prompt, "fps": fps, "frames": frames.len(), "object": scene.object.name },
        }],
        "nodes": nodes,
        "meshes": meshes,
        "materials": [
            { "name": "body", "pbrMetallicRoughness": { "baseColorFactor": [0.80, 0.62, 0.50, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.8 } },
            { "name": "object", "pbrMetallicRoughness": { "baseColorFactor": [0.20, 0.42, 0.80, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.4 } },
            { "name": "table", "doubleSided": true, "pbrMetallicRoughness": { "baseColorFactor": [0.55, 0.42, 0.30, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.9 } },
        ],
        "skins": [{ "name": "smplx", "joints": (0..n).collect::<Vec<_>>(), "inverseBindMatrices": ibm, "skeleton": 0 }],
        "animations": [{ "name": "motion", "samplers": samplers, "channels": channels }],
        "buffers": [{ "byteLength": bin.data.len() }],
        "bufferViews": bin.views,
        "accessors": bin.accessors,
    });
    Ok(container(&serde_json::to_vec(&root).map_err(|e| e.to_string())?, &bin.data))
}

/// The frame's local rotation of joint `j` (1..21 body, 25..39 left, 40..54 right hand).
fn local_rotation(f: &Frame, j: usize) -> [f32; 4] {
    match j {
        1..=21 => f.body_rotations[j - 1],
        25..=39 => f.left_hand_rotations[j - 25],
        40..=54 => f.right_hand_rotations[j - 40],
        _ => [0.0, 0.0, 0.0, 1.0],
    }
}

/// Quaternions with each one's sign chosen to be nearest its predecessor. Frames carry
/// `w >= 0`, which flips the sign whenever `w` crosses 0; interpolating between `q` and
/// `−q'` would spin the long way round in a player that does not pick the short arc.
fn continuous(quats: impl Iterator<Item = [f32; 4]>) -> Vec<f32> {
    let mut out: Vec<f32> = Vec::new();
    let mut prev: Option<[f32; 4]> = None;
    for mut q in quats {
        if let Some(p) = prev {
            if (0..4).map(|k| p[k] * q[k]).sum::<f32>() < 0.0 {
                q = q.map(|v| -v);
            }
        }
        out.extend_from_slice(&q);
        prev = Some(q);
    }
    out
}

/// The GLB container: 12-byte header, JSON chunk (space-padded), BIN chunk (zero-padded).
fn container(json: &[u8], bin: &[u8]) -> Vec<u8> {
    let json_len = json.len().next_multiple_of(4);
    let bin_len = bin.len().next_multiple_of(4);
    let total = 12 + 8 + json_len + 8 + bin_len;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json_len as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(json);
    out.resize(12 + 8 + json_len, b' ');
    out.extend_from_slice(&(bin_len as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(bin);
    out.resize(total, 0);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn container_is_aligned_and_sized() {
        let g = container(b"{\"a\":1}", &[1, 2, 3, 4, 5]);
        assert_eq!(&g[..4], b"glTF");
        assert_eq!(u32::from_le_bytes(g[8..12].try_into().unwrap()) as usize, g.len());
        let jl = u32::from_le_bytes(g[12..16].try_into().unwrap()) as usize;
        assert_eq!((jl, &g[16..20]), (8, &b"JSON"[..]));
        assert_eq!(&g[20..28], b"{\"a\":1} ");
        let bl = u32::from_le_bytes(g[28..32].try_into().unwrap()) as usize;
        assert_eq!((bl, &g[32..36]), (8, &b"BIN\0"[..]));
        assert_eq!(&g[36..], [1, 2, 3, 4, 5, 0, 0, 0]);
    }

    #[test]
    fn quaternion_signs_are_made_continuous() {
        let q = continuous(
            [[0.0, 0.0, 0.6, 0.8], [0.0, 0.0, -0.6, 0.8], [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.99, 0.1]].into_iter(),
        );
        assert_eq!(q, [0.0, 0.0, 0.6, 0.8, 0.0, 0.0, -0.6, 0.8, 0.0, 0.0, -1.0, 0.0, -0.0, -0.0, -0.99, -0.1]);
    }
}

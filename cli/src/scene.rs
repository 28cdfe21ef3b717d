//! What the glb and the preview draw besides the frames: the bundle's skeleton and the
//! catalogue object the prompt names, both already in the frames' coordinate system.
//!
//! A frame's rotations are `S R Sᵀ` and its positions `c S p` (src/assemble.rs); the rest
//! joints and the object's mesh vertices must get the same `c S` for the frames to pose
//! them correctly, so the conversion happens once here and nowhere else.
use comgrasp::bundle::choose_object;
use comgrasp::contact::{ObjectShape, Table};
use comgrasp::skeleton::{mat_vec, quaternion_to_matrix};
use comgrasp::Bundle;
use comgrasp::CoordinateSystem;
use comgrasp::Frame;

use comgrasp::bundle::obj;

pub struct Scene {
    pub coords: CoordinateSystem,
    pub joint_names: Vec<String>,
    /// Parent of each joint, -1 for the root (pelvis); parents precede children.
    pub parents: Vec<i32>,
    /// Rest joint positions in the frames' basis and units (`c S J`).
    pub rest: Vec<[f32; 3]>,
    pub object: SceneObject,
}

pub struct SceneObject {
    /// The catalogue name.
    pub name: String,
    /// The mesh in the object's frame, converted to the frames' basis (`c S v`), so that
    /// `object_translation + object_rotation · v` places it in the world.
    pub mesh: obj::Mesh,
    /// Its box (native world units), as the engine's contact stage sees it.
    pub shape: ObjectShape,
}

impl Scene {
    pub fn load(bundle: &Bundle, coords: CoordinateSystem, prompt: &str) -> Result<Scene, String> {
        let m = &bundle.manifest;
        let (s, c) = coords.basis();
        let to_output = |p: &[f32; 3]| mat_vec(&s, &p.map(f64::from)).map(|v| (v * c) as f32);
        // The engine's choice for the stream (the summary line reports it from the stream).
        let (index, _) = choose_object(&m.objects, prompt).ok_or("the bundle's object catalogue is empty")?;
        let entry = &m.objects[index];
        let bytes = bundle.file_bytes(&entry.mesh).map_err(|e| e.to_string())?;
        let text = String::from_utf8(bytes).map_err(|_| format!("{}: not UTF-8 text", entry.mesh))?;
        let mut mesh = obj::parse(&text).map_err(|e| format!("{}: {e}", entry.mesh))?;
        for p in &mut mesh.positions {
            *p = to_output(p);
        }
        Ok(Scene {
            coords,
            joint_names: m.skeleton.joint_names.clone(),
            parents: m.skeleton.parents.clone(),
            rest: m.skeleton.rest_joints.iter().map(to_output).collect(),
            object: SceneObject { name: entry.name.clone(), mesh, shape: ObjectShape::from_entry(entry) },
        })
    }
}

impl Scene {
    /// The table top the engine's contact stage rested the object on (`contact::Table`, from
    /// the first frame), its corners in the NATIVE world; `None` when the object starts on
    /// the ground.
    pub fn table(&self, first: &Frame) -> Option<[[f64; 3]; 4]> {
        let point = |p: &[f32; 3]| self.coords.to_native_point(&p.map(f64::from));
        let rotation = |q: &[f32; 4]| self.coords.to_native_rotation(&quaternion_to_matrix(&q.map(f64::from)));
        let table = Table::new(
            &point(&first.root_translation),
            &rotation(&first.root_rotation),
            &rotation(&first.object_rotation),
            &point(&first.object_translation),
            &self.object.shape,
        );
        table.corners()
    }
}

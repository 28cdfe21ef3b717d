//! A PNG strip of key frames for a quick look without a 3D viewer: six panels, first and
//! last frame included, each an orthographic three-quarter view from slightly above of
//! the skeleton as lines (left limbs blue, right limbs teal, each hand grey or orange by
//! its contact flag), the object's mesh as a wireframe, the table top it starts on (as the
//! engine's contact stage models it), a ground grid, and a bar showing where in the motion
//! the panel is.
//!
//! Works in every coordinate system: points are mapped back to the native world (z up,
//! right-handed, metres) with the inverse basis change first, so the camera logic exists
//! once. The camera is fixed for the whole strip (placed from the first frame's hips),
//! so the panels compare directly.
use comgrasp::skeleton::{mat_vec, quaternion_to_matrix};
use comgrasp::Frame;

use crate::png::Image;
use crate::scene::Scene;

pub const PANEL_WIDTH: u32 = 256;
pub const PANEL_HEIGHT: u32 = 320;
pub const KEY_FRAMES: usize = 6;

const BACKGROUND: [u8; 3] = [250, 250, 246];
const GRID: [u8; 3] = [214, 214, 208];
const SEPARATOR: [u8; 3] = [180, 180, 180];
const TRACK: [u8; 3] = [228, 228, 222];
const PROGRESS: [u8; 3] = [140, 140, 150];
const TRUNK: [u8; 3] = [60, 60, 70];
const LEFT: [u8; 3] = [60, 95, 165];
const RIGHT: [u8; 3] = [30, 135, 115];
const HAND_FREE: [u8; 3] = [150, 150, 158];
const HAND_CONTACT: [u8; 3] = [235, 120, 0];
const OBJECT: [u8; 3] = [150, 125, 205];
const TABLE: [u8; 3] = [176, 146, 110];

/// SMPL-X joints the drawing needs by index (the tree is fixed at 55 joints).
const LEFT_HIP: usize = 1;
const RIGHT_HIP: usize = 2;
const NECK: usize = 12;
const HEAD: usize = 15;
const LEFT_WRIST: usize = 20;
const RIGHT_WRIST: usize = 21;
const FIRST_LEFT_FINGER: usize = 25;
const FIRST_RIGHT_FINGER: usize = 40;

/// Camera: azimuth from the subject's front towards its right, and elevation.
const AZIMUTH_DEG: f64 = 35.0;
const ELEVATION_DEG: f64 = 12.0;
const MARGIN: f64 = 14.0;
/// Space at the bottom of a panel for the progress bar.
const FOOTER: f64 = 14.0;

pub struct Preview {
    pub image: Image,
    /// Index (into the frames) of each panel's frame.
    pub key_frames: Vec<usize>,
}

/// `count` indices evenly spread over `0..len`, first and last included.
pub fn key_frames(len: usize, count: usize) -> Vec<usize> {
    match (len, count) {
        (0, _) | (_, 0) => Vec::new(),
        (1, _) | (_, 1) => vec![0],
        _ => {
            let n = count.min(len);
            (0..n).map(|k| ((k * (len - 1)) as f64 / (n - 1) as f64).round() as usize).collect()
        }
    }
}

/// One key frame in the native world: joint positions and object mesh vertices.
type Posed = (Vec<[f64; 3]>, Vec<[f64; 3]>);

/// A world-space line to draw.
struct Segment {
    a: [f64; 3],
    b: [f64; 3],
    colour: [u8; 3],
    /// Half width in pixels (0 = 1 px).
    half: i64,
}

/// Renders the strip. The frames must carry joint positions (`enable_fk`).
pub fn render(scene: &Scene, frames: &[Frame]) -> Result<Preview, String> {
    if frames.is_empty() {
        return Err("the motion has no frames to preview".into());
    }
    if frames.iter().any(|f| f.has_joint_positions == 0) {
        return Err("the preview needs joint positions (forward kinematics was off)".into());
    }
    let native = |p: [f64; 3]| scene.coords.to_native_point(&p);
    let keys = key_frames(frames.len(), KEY_FRAMES);

    // World-space (native) geometry of each key frame.
    let worlds: Vec<Posed> = keys
        .iter()
        .map(|&k| {
            let f = &frames[k];
            let joints = f.joint_positions.iter().map(|p| native(p.map(f64::from))).collect();
            let r = quaternion_to_matrix(&f.object_rotation.map(f64::from));
            let t = f.object_translation.map(f64::from);
            let object = scene.object.mesh.positions.iter().map(|v| {
                let rv = mat_vec(&r, &v.map(f64::from));
                native([t[0] + rv[0], t[1] + rv[1], t[2] + rv[2]])
            });
            (joints, object.collect())
        })
        .collect();

    let cam = Camera::facing(&worlds[0].0);
    let table = scene.table(&frames[0]);
    // One scale for the strip; vertical placement shared too, so the ground lines up.
    let mut panels = Vec::with_capacity(keys.len());
    let (mut y_lo, mut y_hi, mut widest) = (f64::INFINITY, f64::NEG_INFINITY, 0.0f64);
    for (k, (joints, object)) in keys.iter().zip(&worlds) {
        let segments = segments(scene, &frames[*k], joints, object);
        let (mut x_lo, mut x_hi) = (f64::INFINITY, f64::NEG_INFINITY);
        let ground = [joints[0][0], joints[0][1], 0.0];
        for p in segments.iter().flat_map(|s| [s.a, s.b]).chain([ground]) {
            let [x, y, _] = cam.project(p);
            (x_lo, x_hi, y_lo, y_hi) = (x_lo.min(x), x_hi.max(x), y_lo.min(y), y_hi.max(y));
        }
        widest = widest.max(x_hi - x_lo);
        panels.push((segments, 0.5 * (x_lo + x_hi)));
    }
    let (w, h) = (PANEL_WIDTH as f64, PANEL_HEIGHT as f64);
    let scale = ((w - 2.0 * MARGIN) / widest.max(1e-6)).min((h - 2.0 * MARGIN - FOOTER) / (y_hi - y_lo).max(1e-6));

    let mut strip = Image::new(PANEL_WIDTH * keys.len() as u32, PANEL_HEIGHT, BACKGROUND);
    for (i, ((segments, x_mid), &k)) in panels.iter_mut().zip(&keys).enumerate() {
        let to_px = |p: [f64; 3]| {
            let [x, y, depth] = cam.project(p);
            [0.5 * w + (x - *x_mid) * scale, MARGIN + (y_hi - y) * scale, depth]
        };
        let mut panel = Image::new(PANEL_WIDTH, PANEL_HEIGHT, BACKGROUND);
        for seg in ground_grid(&worlds[0].0[0]).into_iter().chain(table.iter().flat_map(table_top)) {
            line(&mut panel, to_px(seg.a), to_px(seg.b), seg.colour, seg.half);
        }
        // Painter's order: far segments first, so nearer limbs cover them.
        segments.sort_by(|p, q| cam.depth(p).total_cmp(&cam.depth(q)));
        for seg in segments.iter() {
            line(&mut panel, to_px(seg.a), to_px(seg.b), seg.colour, seg.half);
        }
        progress_bar(&mut panel, k as f64 / (frames.len() - 1).max(1) as f64);
        if i + 1 < keys.len() {
            line(&mut panel, [w - 1.0, 0.0, 0.0], [w - 1.0, h, 0.0], SEPARATOR, 0);
        }
        blit(&mut strip, &panel, i as u32 * PANEL_WIDTH);
    }
    Ok(Preview { image: strip, key_frames: keys })
}

/// Everything of one frame as world-space segments: bones, head, wrists, object edges.
fn segments(scene: &Scene, f: &Frame, joints: &[[f64; 3]], object: &[[f64; 3]]) -> Vec<Segment> {
    let hand = |contact: u8| if contact != 0 { HAND_CONTACT } else { HAND_FREE };
    let mut out = Vec::new();
    for (j, &p) in scene.parents.iter().enumerate() {
        if p < 0 || (22..=24).contains(&j) {
            continue; // the root, and jaw / eyes (inside the head)
        }
        let (colour, half) = match j {
            FIRST_LEFT_FINGER..FIRST_RIGHT_FINGER => (hand(f.contact[0]), 0),
            FIRST_RIGHT_FINGER.. => (hand(f.contact[1]), 0),
            _ if scene.joint_names[j].starts_with("left") => (LEFT, 1),
            _ if scene.joint_names[j].starts_with("right") => (RIGHT, 1),
            _ => (TRUNK, 1),
        };
        out.push(Segment { a: joints[p as usize], b: joints[j], colour, half });
    }
    // Wrists as 7-pixel squares in the hand's contact colour: visible even when the
    // fingers are only a few pixels long.
    for (wrist, contact) in [(LEFT_WRIST, f.contact[0]), (RIGHT_WRIST, f.contact[1])] {
        let p = joints[wrist];
        out.push(Segment { a: p, b: p, colour: hand(contact), half: 3 });
    }
    // The head: a 10 cm ring around the skull centre (9 cm beyond the head joint, which
    // sits at the skull's base), in the plane of the neck and the hips' axis.
    let up = unit(sub(joints[HEAD], joints[NECK])).unwrap_or([0.0, 0.0, 1.0]);
    let centre = add(joints[HEAD], scaled(up, 0.09));
    let side = unit(sub(joints[LEFT_HIP], joints[RIGHT_HIP])).unwrap_or([1.0, 0.0, 0.0]);
    let ring = |t: f64| add(centre, add(scaled(up, 0.1 * t.cos()), scaled(side, 0.1 * t.sin())));
    for i in 0..16 {
        let (t0, t1) = (std::f64::consts::TAU * i as f64 / 16.0, std::f64::consts::TAU * (i + 1) as f64 / 16.0);
        out.push(Segment { a: ring(t0), b: ring(t1), colour: TRUNK, half: 1 });
    }
    // Object wireframe, each edge once.
    let mut edges: Vec<(u32, u32)> = scene
        .object
        .mesh
        .triangles
        .iter()
        .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
        .map(|(a, b)| (a.min(b), a.max(b)))
        .collect();
    edges.sort_unstable();
    edges.dedup();
    for (a, b) in edges {
        out.push(Segment { a: object[a as usize], b: object[b as usize], colour: OBJECT, half: 0 });
    }
    out
}

/// The table top the object started on: its outline and lines across it every 20 cm.
fn table_top(c: &[[f64; 3]; 4]) -> Vec<Segment> {
    let mut out: Vec<Segment> =
        (0..4).map(|i| Segment { a: c[i], b: c[(i + 1) % 4], colour: TABLE, half: 1 }).collect();
    let depth = (0..3).map(|k| (c[1][k] - c[0][k]).powi(2)).sum::<f64>().sqrt();
    let n = (depth / 0.2).round().max(1.0) as usize;
    for i in 1..n {
        let t = i as f64 / n as f64;
        let (a, b) = (add(c[0], scaled(sub(c[1], c[0]), t)), add(c[3], scaled(sub(c[2], c[3]), t)));
        out.push(Segment { a, b, colour: TABLE, half: 0 });
    }
    out
}

/// A 2 m square grid on the floor (z = 0) around the first frame's pelvis.
fn ground_grid(pelvis: &[f64; 3]) -> Vec<Segment> {
    let (cx, cy) = (pelvis[0], pelvis[1]);
    (-4..=4)
        .flat_map(|i| {
            let o = 0.25 * i as f64;
            [
                Segment { a: [cx + o, cy - 1.0, 0.0], b: [cx + o, cy + 1.0, 0.0], colour: GRID, half: 0 },
                Segment { a: [cx - 1.0, cy + o, 0.0], b: [cx + 1.0, cy + o, 0.0], colour: GRID, half: 0 },
            ]
        })
        .collect()
}

/// An orthographic camera in the native world (z up).
struct Camera {
    right: [f64; 3],
    up: [f64; 3],
    /// From the scene towards the camera.
    toward: [f64; 3],
}

impl Camera {
    /// Looks at the subject from its front-right and slightly above. The subject's left is
    /// the hips' direction; its front is `left × up` (SMPL-X: +x left, +y up, +z front).
    fn facing(joints: &[[f64; 3]]) -> Camera {
        let z = [0.0, 0.0, 1.0];
        let hips = sub(joints[LEFT_HIP], joints[RIGHT_HIP]);
        let left = unit([hips[0], hips[1], 0.0]).unwrap_or([1.0, 0.0, 0.0]);
        let front = cross(left, z);
        let (a, e) = (AZIMUTH_DEG.to_radians(), ELEVATION_DEG.to_radians());
        let flat = add(scaled(front, a.cos()), scaled(left, -a.sin()));
        let toward = add(scaled(flat, e.cos()), scaled(z, e.sin()));
        let right = unit(cross(z, toward)).expect("toward is not vertical");
        Camera { right, up: cross(toward, right), toward }
    }

    /// (screen x, screen y, depth) in metres; depth grows towards the camera.
    fn project(&self, p: [f64; 3]) -> [f64; 3] {
        [dot(p, self.right), dot(p, self.up), dot(p, self.toward)]
    }

    fn depth(&self, s: &Segment) -> f64 {
        0.5 * (dot(s.a, self.toward) + dot(s.b, self.toward))
    }
}

/// A line between two pixel positions with a square brush of half width `half`.
fn line(img: &mut Image, a: [f64; 3], b: [f64; 3], colour: [u8; 3], half: i64) {
    let steps = (b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil().max(1.0);
    if !steps.is_finite() || steps > 1e5 {
        return; // a degenerate projection; nothing sensible to draw
    }
    for i in 0..=steps as i64 {
        let t = i as f64 / steps;
        let (x, y) = ((a[0] + t * (b[0] - a[0])).round() as i64, (a[1] + t * (b[1] - a[1])).round() as i64);
        for dy in -half..=half {
            for dx in -half..=half {
                img.put(x + dx, y + dy, colour);
            }
        }
    }
}

/// Where the panel's frame is in the motion: a bar along the bottom edge.
fn progress_bar(img: &mut Image, t: f64) {
    let (w, h) = (img.width as f64, img.height as f64);
    let y = h - 0.5 * FOOTER;
    line(img, [MARGIN, y, 0.0], [w - MARGIN, y, 0.0], TRACK, 1);
    line(img, [MARGIN, y, 0.0], [MARGIN + t.clamp(0.0, 1.0) * (w - 2.0 * MARGIN), y, 0.0], PROGRESS, 1);
}

fn blit(dst: &mut Image, src: &Image, x0: u32) {
    let (dw, sw) = (3 * dst.width as usize, 3 * src.width as usize);
    for y in 0..src.height.min(dst.height) as usize {
        let at = y * dw + 3 * x0 as usize;
        dst.rgb[at..at + sw].copy_from_slice(&src.rgb[y * sw..(y + 1) * sw]);
    }
}

fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn scaled(a: [f64; 3], k: f64) -> [f64; 3] {
    [a[0] * k, a[1] * k, a[2] * k]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn unit(a: [f64; 3]) -> Option<[f64; 3]> {
    let n = dot(a, a).sqrt();
    (n > 1e-12 && n.is_finite()).then(|| scaled(a, 1.0 / n))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn key_frames_are_even_and_include_both_ends() {
        assert_eq!(key_frames(48, 6), [0, 9, 19, 28, 38, 47]);
        assert_eq!(key_frames(3, 6), [0, 1, 2]);
        assert_eq!(key_frames(1, 6), [0]);
        assert!(key_frames(0, 6).is_empty());
    }

    #[test]
    fn camera_is_orthonormal_and_sees_the_front() {
        // Hips along +x (left), so the front is -y; the camera sits at -y, slightly right.
        let mut joints = vec![[0.0; 3]; 55];
        joints[LEFT_HIP] = [0.1, 0.0, 1.0];
        joints[RIGHT_HIP] = [-0.1, 0.0, 1.0];
        let c = Camera::facing(&joints);
        for (a, b, want) in [
            (c.right, c.right, 1.0),
            (c.up, c.up, 1.0),
            (c.toward, c.toward, 1.0),
            (c.right, c.up, 0.0),
            (c.up, c.toward, 0.0),
        ] {
            assert!((dot(a, b) - want).abs() < 1e-12);
        }
        assert!(c.toward[1] < -0.5 && c.toward[2] > 0.0, "{:?}", c.toward);
        // Facing the subject, its left hip appears on the right of the screen.
        assert!(c.project(joints[LEFT_HIP])[0] > c.project(joints[RIGHT_HIP])[0]);
        // World up is screen up.
        assert!(c.project([0.0, 0.0, 1.0])[1] > c.project([0.0, 0.0, 0.0])[1]);
    }

    /// A standing rest body (the tiny bundle's skeleton turned upright as the training
    /// data does), in glTF coordinates, rendered: head above feet, contact colour on the
    /// right hand only, object drawn.
    #[test]
    fn a_standing_body_is_drawn_upright() {
        use crate::scene::SceneObject;
        use comgrasp::bundle::obj::Mesh;
        use comgrasp::contact::ObjectShape;
        use comgrasp::CoordinateSystem;
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../models/tiny/manifest.json");
        let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        let sk = &m["skeleton"];
        let rest: Vec<[f64; 3]> = sk["rest_joints"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| std::array::from_fn(|k| r[k].as_f64().unwrap()))
            .collect();
        let parents: Vec<i32> = sk["parents"].as_array().unwrap().iter().map(|p| p.as_i64().unwrap() as i32).collect();
        let names: Vec<String> =
            sk["joint_names"].as_array().unwrap().iter().map(|n| n.as_str().unwrap().to_string()).collect();
        // Canonical (y up, +z front, left +x) → native world (z up, facing +y), then glTF.
        let upright = |p: [f64; 3]| [-p[0], p[2], p[1] + 1.0];
        let (s, _) = CoordinateSystem::CG_COORDS_GLTF.basis();
        let gltf = |p: [f64; 3]| mat_vec(&s, &p).map(|v| v as f32);
        let mut f = Frame::default();
        for (j, r) in rest.iter().enumerate() {
            f.joint_positions[j] = gltf(upright(*r));
        }
        f.has_joint_positions = 1;
        f.contact = [0, 1];
        f.object_translation = gltf(upright(rest[RIGHT_WRIST]));
        let cube = Mesh {
            positions: vec![[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.05]],
            triangles: vec![[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]],
        };
        let scene = Scene {
            coords: CoordinateSystem::CG_COORDS_GLTF,
            joint_names: names,
            parents,
            rest: Vec::new(),
            object: SceneObject {
                name: "cube".into(),
                mesh: cube,
                shape: ObjectShape { centre: [0.025; 3], half_extents: [0.025; 3], surface: None },
            },
        };
        let p = render(&scene, &[f, f]).unwrap();
        assert_eq!((p.image.width, p.image.height, p.key_frames.clone()), (2 * PANEL_WIDTH, PANEL_HEIGHT, vec![0, 1]));
        if let Ok(dir) = std::env::var("COMGRASP_PREVIEW_DUMP") {
            std::fs::write(format!("{dir}/standing.png"), p.image.encode().unwrap()).unwrap();
        }
        let rows = |c: [u8; 3]| -> Vec<usize> {
            (0..PANEL_HEIGHT as usize)
                .filter(|&y| {
                    (0..PANEL_WIDTH as usize).any(|x| p.image.rgb[3 * (y * 2 * PANEL_WIDTH as usize + x)..][..3] == c)
                })
                .collect()
        };
        let (trunk, legs) = (rows(TRUNK), rows(LEFT));
        assert!(trunk[0] + 40 < *legs.last().unwrap(), "head above the feet");
        assert!(!rows(HAND_CONTACT).is_empty() && !rows(HAND_FREE).is_empty() && !rows(OBJECT).is_empty());
        // The object starts at the wrist, above the ground: a table top is drawn, at the
        // height of the object's bottom (the object's lowest rows, above the feet).
        let (table, object) = (rows(TABLE), rows(OBJECT));
        assert!(!table.is_empty() && table[0] < *legs.last().unwrap(), "{table:?}");
        assert!(table.iter().any(|r| (*r as i64 - *object.last().unwrap() as i64).abs() <= 20), "{table:?} {object:?}");
    }
}

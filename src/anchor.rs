//! Scene anchoring: frames in the host's world (docs/engine.md, "Scene anchoring").
//!
//! The model generates in its own frame (SynthGrasp's: the subject near the origin, the
//! object on a table in front). A host that gives the character's ground point and heading,
//! the object's start pose, or both ([`Anchor`]) gets frames moved by one rigid motion `W`
//! (a turn about the up axis and a translation, fixed at the first frame) into its world:
//!
//! * **character**: `W` maps the model's first-frame ground point (under the pelvis) and
//!   heading onto the host's.
//! * **object** (with or without the character): the generated object starts at the host's
//!   pose (the contact stage rests it there and the reach correction brings the hand to it);
//!   [`reach`](AnchorStage::new) is checked at start against a documented envelope.
//! * **object + `place_character`**: `W` only translates, so that the model's own object
//!   start lands on the host's: the character stands at the model's interaction spot.
//!
//! Inputs are in the engine's coordinate system and become native here (`S^T p / c`,
//! `S^T R S`); frames get the basis change at emit as always.

use crate::assemble::Pose;
use crate::config::{Anchor, Placement};
use crate::contact::heading;
use crate::error::{Error, Result};
use crate::frame::CoordinateSystem;
use crate::skeleton::{axis_angle, mat_mul, mat_vec, quaternion_to_matrix, sub, transpose, Mat3, Vec3, IDENTITY};

/// The host's object must be within this horizontal distance of the character's ground
/// point (its anchor, or the native origin) for the reach correction, m.
pub const REACH_HORIZONTAL: f64 = 0.8;
/// ... and its origin between these heights above the character's ground point, m.
pub const REACH_LOW: f64 = 0.3;
pub const REACH_HIGH: f64 = 1.6;

const UP: Vec3 = [0.0, 0.0, 1.0];

/// The heading angle (about +z) of a horizontal direction, 0 = +y.
fn yaw(d: [f64; 2]) -> f64 {
    (-d[0]).atan2(d[1])
}

/// One stream's anchoring, in the native world.
#[derive(Clone, Debug)]
pub struct AnchorStage {
    /// Host ground point and heading angle.
    character: Option<(Vec3, f64)>,
    /// Host object pose.
    object: Option<(Mat3, Vec3)>,
    place_character: bool,
    /// The rigid motion model frame -> host world, once the first frame set it.
    world: Option<(Mat3, Vec3)>,
}

impl AnchorStage {
    /// Converts the host's placements into the native world and checks the object's reach
    /// (`InvalidArgument` naming the distance and the envelope).
    pub fn new(a: &Anchor, coords: CoordinateSystem) -> Result<AnchorStage> {
        a.validate()?;
        let native = |p: &Placement| -> (Mat3, Vec3) {
            let q = p.rotation.map(f64::from);
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            let r = quaternion_to_matrix(&q.map(|v| v / n));
            (coords.to_native_rotation(&r), coords.to_native_point(&p.position.map(f64::from)))
        };
        let character = a.character.as_ref().map(|p| {
            let (r, g) = native(p);
            // Identity faces +y: the heading is where the rotation turns +y.
            let f = mat_vec(&r, &[0.0, 1.0, 0.0]);
            (g, if f[0].hypot(f[1]) > 1e-6 { yaw([f[0], f[1]]) } else { 0.0 })
        });
        let object = a.object.as_ref().map(native);
        if let (Some((_, o)), false) = (&object, a.place_character) {
            let g = character.map_or([0.0; 3], |(g, _)| g);
            let d = sub(o, &g);
            let (h, up) = (d[0].hypot(d[1]), d[2]);
            if h > REACH_HORIZONTAL || !(REACH_LOW..=REACH_HIGH).contains(&up) {
                return Err(Error::InvalidArgument(format!(
                    "anchor: the object is out of reach: {h:.2} m from the character's ground point and {up:.2} m above \
                     it (native metres; the reach envelope is {REACH_HORIZONTAL} m and {REACH_LOW}..{REACH_HIGH} m); \
                     move it, or set place_character"
                )));
            }
        }
        Ok(AnchorStage { character, object, place_character: a.place_character, world: None })
    }

    /// Anchoring that continues an earlier stream: the character's ground point and heading
    /// (radians about +z, 0 = +y) in the native world, where the earlier stream left it.
    pub fn continuing(ground: Vec3, heading: [f64; 2]) -> AnchorStage {
        AnchorStage { character: Some((ground, yaw(heading))), object: None, place_character: false, world: None }
    }

    /// The rigid motion from the model's frame to the host's world, once fixed.
    pub fn world(&self) -> Option<(Mat3, Vec3)> {
        self.world
    }

    /// The first frame (before the contact stage): fixes the world motion from the model's
    /// first frame and returns the object's start pose in the model's frame when the host
    /// gives it.
    pub fn begin(&mut self, pose: &Pose) -> Option<(Mat3, Vec3)> {
        let ground = [pose.pelvis[0], pose.pelvis[1], 0.0];
        let (r, t) = if self.place_character {
            let (_, o) = self.object.expect("validated: place_character has the object");
            (IDENTITY, sub(&o, &pose.object_translation))
        } else if let Some((g, psi)) = self.character {
            let model = yaw(heading(&pose.pelvis, &pose.local[0], &pose.object_centre));
            let r = axis_angle(&UP, psi - model);
            (r, sub(&g, &mat_vec(&r, &ground)))
        } else {
            (IDENTITY, [0.0; 3])
        };
        self.world = Some((r, t));
        let rt = transpose(&r);
        self.object.map(|(ro, po)| (mat_mul(&rt, &ro), mat_vec(&rt, &sub(&po, &t))))
    }

    /// Whether the host's object pose replaces the model's (an object anchor that does not
    /// place the character from it): the model's own placement of the object is moot.
    pub fn fixes_object(&self) -> bool {
        self.object.is_some() && !self.place_character
    }

    /// Moves a frame (after the contact stage) into the host's world.
    pub fn apply(&self, pose: &mut Pose) {
        if let Some((r, t)) = &self.world {
            pose.transform(r, t);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::cg_coordinate_system;

    fn placement(p: [f32; 3], yaw_deg: f32) -> Placement {
        let h = yaw_deg.to_radians() / 2.0;
        Placement { position: p, rotation: [0.0, 0.0, h.sin(), h.cos()] }
    }

    /// A model frame facing +x (root turned -90 degrees about z from SMPL-X's +z forward
    /// to... any facing: here the fallback, toward the object), pelvis at (1, 2, 0.9).
    fn model_frame() -> Pose {
        let mut p = Pose { pelvis: [1.0, 2.0, 0.9], ..Pose::default() };
        // SMPL-X +z forward -> world +x: rotate +z onto +x about y.
        p.local[0] = axis_angle(&[0.0, 1.0, 0.0], std::f64::consts::FRAC_PI_2);
        p.object_translation = [1.5, 2.0, 0.8];
        p.object_centre = p.object_translation;
        p
    }

    #[test]
    fn the_character_lands_on_the_hosts_ground_point_and_heading() {
        // Host: ground point (3, -1, 0.2), facing -x (yaw 90 degrees: +y turned to -x).
        let a = Anchor { character: Some(placement([3.0, -1.0, 0.2], 90.0)), ..Anchor::default() };
        let mut s = AnchorStage::new(&a, cg_coordinate_system::CG_COORDS_NATIVE).unwrap();
        let mut p = model_frame();
        assert_eq!(s.begin(&p), None);
        s.apply(&mut p);
        // (host values are f32)
        assert!(sub(&p.pelvis, &[3.0, -1.0, 1.1]).iter().all(|v| v.abs() < 1e-6), "{:?}", p.pelvis);
        // The object was 0.5 m ahead of the pelvis: it is 0.5 m ahead (-x) still.
        let d = sub(&p.object_translation, &p.pelvis);
        assert!((d[0] + 0.5).abs() < 1e-9 && d[1].abs() < 1e-9 && (d[2] + 0.1).abs() < 1e-9, "{d:?}");
        let f = heading(&p.pelvis, &p.local[0], &p.object_centre);
        assert!((f[0] + 1.0).abs() < 1e-9 && f[1].abs() < 1e-9, "{f:?}");
    }

    #[test]
    fn the_hosts_object_in_the_models_frame_and_in_unity_units() {
        // Unity (y up, left-handed): the object 0.6 m in front of a character at the origin.
        let unity = cg_coordinate_system::CG_COORDS_UNITY;
        let (s, _) = unity.basis();
        let to_unity = |p: [f64; 3]| mat_vec(&s, &p).map(|v| v as f32);
        let a = Anchor {
            character: Some(Placement { position: to_unity([0.0, 0.0, 0.0]), rotation: [0.0, 0.0, 0.0, 1.0] }),
            object: Some(Placement { position: to_unity([0.1, 0.6, 0.75]), rotation: [0.0, 0.0, 0.0, 1.0] }),
            place_character: false,
        };
        let mut st = AnchorStage::new(&a, unity).unwrap();
        let mut p = model_frame();
        let (_, start) = st.begin(&p).unwrap();
        // Mapped back into the host's world, the start is the host's object.
        let (r, t) = st.world.unwrap();
        let back = mat_vec(&r, &start);
        let host = [back[0] + t[0], back[1] + t[1], back[2] + t[2]];
        assert!(sub(&host, &[0.1, 0.6, 0.75]).iter().all(|v| v.abs() < 1e-6), "{host:?}");
        st.apply(&mut p);
        assert!((p.pelvis[0]).abs() < 1e-9 && p.pelvis[1].abs() < 1e-9, "{:?}", p.pelvis);
    }

    #[test]
    fn place_character_moves_the_character_to_the_objects_spot() {
        let a = Anchor { object: Some(placement([5.0, 5.0, 1.0], 30.0)), place_character: true, ..Anchor::default() };
        let mut s = AnchorStage::new(&a, cg_coordinate_system::CG_COORDS_NATIVE).unwrap();
        let mut p = model_frame();
        let (_, start) = s.begin(&p).unwrap();
        // The model's own object start is the spot: the object starts where the model put it.
        assert!(sub(&start, &p.object_translation).iter().all(|v| v.abs() < 1e-9));
        s.apply(&mut p);
        assert!(sub(&p.object_translation, &[5.0, 5.0, 1.0]).iter().all(|v| v.abs() < 1e-6));
        assert!(sub(&p.pelvis, &[4.5, 5.0, 1.1]).iter().all(|v| v.abs() < 1e-6), "{:?}", p.pelvis);
    }

    #[test]
    fn bad_anchors_are_invalid_arguments() {
        let n = cg_coordinate_system::CG_COORDS_NATIVE;
        let bad = |a: Anchor, needle: &str| match AnchorStage::new(&a, n) {
            Err(Error::InvalidArgument(m)) => assert!(m.contains(needle), "{m}"),
            other => panic!("{other:?}"),
        };
        let ok = placement([0.0, 0.5, 0.8], 0.0);
        bad(Anchor { object: Some(placement([0.0, 2.0, 0.8], 0.0)), ..Anchor::default() }, "out of reach");
        bad(Anchor { object: Some(placement([0.0, 0.5, 0.1], 0.0)), ..Anchor::default() }, "out of reach");
        bad(
            Anchor { object: Some(Placement { position: [f32::NAN, 0.0, 0.0], ..ok }), ..Anchor::default() },
            "non-finite",
        );
        bad(
            Anchor { character: Some(Placement { rotation: [0.0, 0.0, 0.5, 0.5], ..ok }), ..Anchor::default() },
            "unit quaternion",
        );
        bad(Anchor { place_character: true, ..Anchor::default() }, "place_character");
        bad(Anchor { object: Some(ok), character: Some(ok), place_character: true }, "place_character");
        // Within the envelope of a character placed near it: fine.
        let near = Anchor {
            character: Some(placement([3.0, 3.0, 0.0], 0.0)),
            object: Some(placement([3.2, 3.5, 0.9], 0.0)),
            ..Anchor::default()
        };
        assert!(AnchorStage::new(&near, n).is_ok());
        // Unreal centimetres: 80 cm high, 50 cm away is within reach.
        let cm = Anchor { object: Some(placement([0.0, -50.0, 80.0], 0.0)), ..Anchor::default() };
        assert!(AnchorStage::new(&cm, cg_coordinate_system::CG_COORDS_UNREAL).is_ok());
    }
}

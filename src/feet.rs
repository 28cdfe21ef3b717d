//! Planted feet: a foot the model stands on stays where it was put (docs/engine.md,
//! "Contact consistency", "Feet stay planted").
//!
//! A model's standing feet slide: a few millimetres per frame, back and forth at token
//! seams, where the ground truth's stand still (SynthGrasp's subjects never step). A game
//! shows it as skating. Per foot, while the model's ankle stays low and slow, the foot is
//! pinned: its ankle keeps the place and the global rotation it had when it was planted,
//! and two-bone IK on the hip and knee holds it there (nothing above the hips moves). A foot the model lifts, moves a step away or turns is let go, and its
//! correction fades back to the model's path; it is planted again, where it is shown, once
//! the model's ankle is low and slow again. Runs inside the contact stage, on the speed-
//! limited model pose (no other rule moves the legs). Causal and allocation-free.

use crate::frame::CG_NUM_JOINTS;
use crate::skeleton::{
    add, fade_rotation, limb_ik, mat_mul, mat_vec, norm, rotation_angle, scale, sub, transpose, Mat3, Vec3, IDENTITY,
};

/// Each leg as `[pelvis, hip, knee, ankle]`, left then right.
pub const LEGS: [[usize; 4]; 2] = [[0, 1, 4, 7], [0, 2, 5, 8]];
/// A free foot is planted while the model's ankle moves slower than this over the ground, m/s.
pub const PLANT_SPEED: f64 = 0.25;
/// ... and is at most this far above the lowest the model's ankles have been in the stream,
/// m; a planted foot whose model ankle rises this far above its pin is let go (a step). The
/// default model's standing legs swing its ankles 4-5 cm up and 30 cm forward and back
/// while its pelvis stays (a pendulum, not a step), hence the wide margins.
pub const FOOT_LIFT: f64 = 0.05;
/// A planted foot is let go when the model's ankle is this far from its pin over the
/// ground, m, or when the leg falls short of the pin by more than [`FOOT_LIFT`] (the pelvis
/// rose: within that, the straightened leg lifts the foot off the pin a little).
pub const FOOT_STEP: f64 = 0.3;
/// ... or when the model's foot has turned this far from the pinned one, radians.
pub const FOOT_TURN: f64 = 0.8;
/// A free foot's correction fades back to the model's path at this speed, m/s ...
pub const FOOT_FADE: f64 = 0.3;
/// ... and its turn at this rate, rad/s.
const FOOT_TURN_FADE: f64 = 1.0;

#[derive(Clone, Copy, Debug)]
struct Foot {
    planted: bool,
    /// The pinned ankle's place and global rotation (while planted).
    at: Vec3,
    rot: Mat3,
    /// What the stage adds to the model's ankle: shown = model + correction, turn · model.
    correction: Vec3,
    turn: Mat3,
    /// The model's ankle in the previous frame.
    last: Option<Vec3>,
}

const FREE_FOOT: Foot =
    Foot { planted: false, at: [0.0; 3], rot: IDENTITY, correction: [0.0; 3], turn: IDENTITY, last: None };

/// One stream's feet. Feed it every frame in order ([`Feet::apply`]).
#[derive(Clone, Debug)]
pub struct Feet {
    dt: f64,
    feet: [Foot; 2],
    /// The lowest the model's ankles have been so far (native z), the stream's standing height.
    lowest: f64,
}

impl Feet {
    /// `fps`: the bundle's frame rate (> 0).
    pub fn new(fps: f64) -> Feet {
        Feet { dt: 1.0 / fps, feet: [FREE_FOOT; 2], lowest: f64::INFINITY }
    }

    /// Which feet are pinned.
    pub fn planted(&self) -> [bool; 2] {
        self.feet.map(|f| f.planted)
    }

    /// The state moved by the rigid motion `p -> r p + t` (`r` a turn about the up axis):
    /// pins stay where they are in the world, corrections turn with it.
    pub fn moved(&self, r: &Mat3, t: &Vec3) -> Feet {
        let mut next = self.clone();
        let at = |p: &Vec3| add(&mat_vec(r, p), t);
        for f in &mut next.feet {
            f.at = at(&f.at);
            f.rot = mat_mul(r, &f.rot);
            f.correction = mat_vec(r, &f.correction);
            f.turn = mat_mul(&mat_mul(r, &f.turn), &transpose(r));
            f.last = f.last.as_ref().map(at);
        }
        next.lowest += t[2];
        next
    }

    /// Pins or frees each foot and rewrites the legs' rotations of the model pose whose FK
    /// is `global` / `joints` (its legs as the model moves them; the caller's FK is stale
    /// for the legs afterwards).
    pub fn apply(
        &mut self,
        local: &mut [Mat3; CG_NUM_JOINTS],
        global: &[Mat3; CG_NUM_JOINTS],
        joints: &[Vec3; CG_NUM_JOINTS],
    ) {
        for leg in LEGS {
            self.lowest = self.lowest.min(joints[leg[3]][2]);
        }
        for (foot, leg) in self.feet.iter_mut().zip(LEGS) {
            let (model, g) = (joints[leg[3]], global[leg[3]]);
            let ground = |v: &Vec3| norm(&[v[0], v[1], 0.0]);
            if foot.planted {
                let away = ground(&sub(&model, &foot.at)) > FOOT_STEP;
                let up = model[2] > foot.at[2] + FOOT_LIFT;
                let turned = rotation_angle(&mat_mul(&foot.rot, &transpose(&g))) > FOOT_TURN;
                let (hip, knee) = (joints[leg[1]], joints[leg[2]]);
                let leg_length = norm(&sub(&knee, &hip)) + norm(&sub(&model, &knee));
                let short = norm(&sub(&foot.at, &hip)) > leg_length + FOOT_LIFT;
                foot.planted = !(away || up || turned || short);
            } else {
                let speed = foot.last.map_or(0.0, |last| ground(&sub(&model, &last)) / self.dt);
                if speed <= PLANT_SPEED && model[2] <= self.lowest + FOOT_LIFT {
                    // Pinned where it is shown, so planting never moves it.
                    foot.planted = true;
                    foot.at = add(&model, &foot.correction);
                    foot.rot = mat_mul(&foot.turn, &g);
                }
            }
            foot.last = Some(model);
            if foot.planted {
                foot.correction = sub(&foot.at, &model);
                foot.turn = mat_mul(&foot.rot, &transpose(&g));
            } else {
                let n = norm(&foot.correction);
                let step = FOOT_FADE * self.dt;
                foot.correction = if n > step { scale(&foot.correction, (n - step) / n) } else { [0.0; 3] };
                foot.turn = fade_rotation(&foot.turn, FOOT_TURN_FADE * self.dt);
            }
            if foot.correction != [0.0; 3] || foot.turn != IDENTITY {
                limb_ik(local, global, joints, leg, &add(&model, &foot.correction), &mat_mul(&foot.turn, &g));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skeleton::{axis_angle, Skeleton, SMPLX_PARENTS};

    /// Legs with a slightly bent knee (forward is +y), everything else at the pelvis.
    fn skeleton() -> Skeleton {
        let mut r = vec![[0.0f32; 3]; CG_NUM_JOINTS];
        for (side, x) in [(0usize, 0.09f32), (1, -0.09)] {
            let [_, hip, knee, ankle] = LEGS[side];
            r[hip] = [x, 0.0, -0.08];
            r[knee] = [x, 0.03, -0.48];
            r[ankle] = [x, 0.0, -0.88];
            r[[10, 11][side]] = [x, 0.12, -0.93];
        }
        Skeleton::new(&SMPLX_PARENTS, &r).unwrap()
    }

    fn fk(s: &Skeleton, local: &[Mat3; CG_NUM_JOINTS], pelvis: Vec3) -> ([Mat3; CG_NUM_JOINTS], [Vec3; CG_NUM_JOINTS]) {
        let mut g = [IDENTITY; CG_NUM_JOINTS];
        let mut p = [[0.0; 3]; CG_NUM_JOINTS];
        s.forward(local, pelvis, &mut g, &mut p);
        (g, p)
    }

    /// Runs `frames` model poses (pelvis, hip turn about x, both legs alike) through
    /// [`Feet`]; returns the model's and the shown FK per frame.
    fn run(frames: &[(Vec3, f64)]) -> Vec<([Vec3; CG_NUM_JOINTS], [Vec3; CG_NUM_JOINTS], [Mat3; CG_NUM_JOINTS])> {
        let s = skeleton();
        let mut feet = Feet::new(30.0);
        frames
            .iter()
            .map(|&(pelvis, swing)| {
                let mut local = [IDENTITY; CG_NUM_JOINTS];
                for leg in LEGS {
                    local[leg[1]] = axis_angle(&[1.0, 0.0, 0.0], swing);
                }
                let (g, model) = fk(&s, &local, pelvis);
                feet.apply(&mut local, &g, &model);
                let (g, shown) = fk(&s, &local, pelvis);
                (model, shown, g)
            })
            .collect()
    }

    fn dist(a: &Vec3, b: &Vec3) -> f64 {
        norm(&sub(a, b))
    }

    #[test]
    fn a_standing_foot_stays_where_it_was_planted() {
        // The model's pelvis and legs sway by up to 2 cm at 0.15 m/s: its feet slide.
        let frames: Vec<(Vec3, f64)> =
            (0..60).map(|t| ([0.02 * (t as f64 * 0.25).sin(), 0.0, 0.9], 0.03 * (t as f64 * 0.2).sin())).collect();
        let out = run(&frames);
        let model_slide: f64 = out.windows(2).map(|w| dist(&w[0].0[7], &w[1].0[7])).sum();
        assert!(model_slide > 0.1, "the model's feet slide ({model_slide} m)");
        let s = skeleton();
        for (model, shown, g) in &out {
            for (side, leg) in LEGS.iter().enumerate() {
                let (ankle, toe) = (leg[3], [10, 11][side]);
                assert!(dist(&shown[ankle], &out[0].1[ankle]) < 1e-6, "ankle {ankle} moved");
                assert!(dist(&shown[toe], &out[0].1[toe]) < 1e-6, "toe {toe} moved");
                // Bones keep their lengths; the knee bends to the side the model's does.
                for j in &leg[2..] {
                    let p = SMPLX_PARENTS[*j] as usize;
                    let rest = dist(&s.rest_joints()[*j], &s.rest_joints()[p]);
                    assert!((dist(&shown[*j], &shown[p]) - rest).abs() < 1e-9);
                }
                let bend = |j: &[Vec3; CG_NUM_JOINTS]| {
                    let (thigh, shin) = (sub(&j[leg[2]], &j[leg[1]]), sub(&j[leg[3]], &j[leg[2]]));
                    crate::skeleton::cross(&thigh, &shin)[0]
                };
                assert!(bend(shown) * bend(model) > 0.0, "the knee bends backward");
                // The pelvis and everything above the legs are the model's.
                assert_eq!(g[0], IDENTITY);
            }
        }
    }

    #[test]
    fn a_step_frees_the_foot_and_it_is_planted_again_where_it_lands() {
        // Stand, then the model moves the pelvis 1 m forward over 50 frames (steps, in
        // effect) and stands again.
        let mut frames: Vec<(Vec3, f64)> = (0..10).map(|_| ([0.0, 0.0, 0.9], 0.0)).collect();
        frames.extend((1..=50).map(|t| ([0.0, 0.02 * t as f64, 0.9], 0.0)));
        frames.extend((0..40).map(|_| ([0.0, 1.0, 0.9], 0.0)));
        let out = run(&frames);
        let ankle = |f: usize| out[f].1[7];
        // Planted while the pelvis starts to move (under FOOT_STEP), then let go.
        assert!(dist(&ankle(11), &ankle(0)) < 1e-6, "{:?} {:?}", ankle(11), ankle(0));
        assert!(dist(&ankle(59), &ankle(0)) > 0.5, "the foot follows the step");
        // The freed foot returns to the model's path within FOOT_FADE and then stays.
        for w in out.windows(2) {
            let v = dist(&w[1].1[7], &w[0].1[7]) * 30.0;
            let model = dist(&w[1].0[7], &w[0].0[7]) * 30.0;
            assert!(v <= model + FOOT_FADE + 1e-6, "the foot moves {v} m/s");
        }
        let last = out.len() - 1;
        assert!(dist(&ankle(last), &out[last].0[7]) < 1e-9, "back on the model's path");
        assert!(dist(&ankle(last), &ankle(last - 10)) < 1e-9, "planted again");
    }
}

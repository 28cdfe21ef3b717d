//! The contact-consistency stage on a real model (`models/default`), through the public
//! engine API: whatever motion the model makes, the frames obey the stage's guarantees.
//!
//! Nothing here depends on the particular model's numbers (it is replaced by the trained
//! bundle): only on the stage's rules, checked on every frame of a few prompts and seeds.
use std::path::Path;
use std::time::Duration;

use comgrasp::assemble::CONTACT_THRESHOLD;
use comgrasp::contact::{ObjectShape, ObjectSurface, FADE_SPEED, MAX_SPEED, OFF_FRAMES, TIP_SPEED};
use comgrasp::skeleton::{mat_vec, quaternion_to_matrix};
use comgrasp::{Engine, EngineConfig, Frame, PollResult, StreamConfig};

const PROMPTS: [&str; 5] = [
    "A woman drinks from the mug",
    "Someone grabs the large cube with their left hand and lifts it up",
    "The woman hands the sphere over from her right hand to her left",
    "Pick up the apple and put it back",
    // seed 2 on the default: a reach whose target swings to the other side of the body while
    // the other hand holds the torus (a bow whose axis jumped threw that hand 20 cm at once)
    "The man is passing the large torus from his left hand to his right.",
];

fn engine() -> Engine {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("models").join("default");
    Engine::new(EngineConfig { bundle_path: Some(dir), enable_fk: true, ..EngineConfig::default() }).unwrap()
}

fn frames(e: &Engine, text: &str, seed: u64, raw: bool) -> Vec<Frame> {
    collect(e, text, StreamConfig { seed: Some(seed), raw_output: raw.then_some(true), ..StreamConfig::default() })
}

fn collect(e: &Engine, text: &str, cfg: StreamConfig) -> Vec<Frame> {
    let mut s = e.start(text, cfg).unwrap();
    let (mut out, mut f) = (Vec::new(), Frame::default());
    loop {
        match s.wait(&mut f, Duration::from_secs(5)) {
            PollResult::Frame => out.push(f),
            PollResult::Pending => {}
            PollResult::End => return out,
            r => panic!("{text:?}: {r:?} {:?}", s.error()),
        }
    }
}

/// SynthGrasp's fastest wrist and object, m/s (issue 17's speed bar; training data of the
/// default model, measured from its features).
const GROUND_TRUTH_PEAK: f64 = 2.75;

/// How far the object's most downward box axis leans from straight down, radians.
fn tilt(q: &[f32; 4]) -> f64 {
    let r = quaternion_to_matrix(&q.map(f64::from));
    (0..3).map(|k| r[2][k].abs()).fold(0.0, f64::max).min(1.0).acos()
}

/// The angle between two rotations (x, y, z, w quaternions), radians.
fn angle(a: &[f32; 4], b: &[f32; 4]) -> f64 {
    let d: f64 = (0..4).map(|i| f64::from(a[i]) * f64::from(b[i])).sum();
    2.0 * d.abs().min(1.0).acos()
}

fn dist(a: &[f32; 3], b: &[f32; 3]) -> f64 {
    (0..3).map(|i| (a[i] as f64 - b[i] as f64).powi(2)).sum::<f64>().sqrt()
}

fn sub(a: &[f32; 3], b: &[f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[test]
fn frames_agree_and_the_object_obeys_the_hands() {
    let e = engine();
    let bundle = e.bundle().unwrap().clone();
    let objects = &bundle.manifest.objects;
    let fps = bundle.manifest.fps;
    let mut grasps = 0;
    // Issue 17's grip bar: the holding hand's nearest joint (wrist, 15 finger joints) to the
    // object's surface (the bundle's mesh), mean over held frames and max.
    let (mut grip_sum, mut grip_max, mut grip_n) = (0.0f64, 0.0f64, 0usize);
    for text in PROMPTS {
        let (index, _) = comgrasp::bundle::choose_object(objects, text).unwrap();
        let centre_local = objects[index].centre.map(f64::from);
        let mesh = std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default").join(&objects[index].mesh),
        )
        .unwrap();
        let surface = std::sync::Arc::new(ObjectSurface::from_mesh(&comgrasp::bundle::obj::parse(&mesh).unwrap()));
        let shape = ObjectShape::from_entry(&objects[index]).with_surface(surface);
        for seed in [1, 2] {
            let fr = frames(&e, text, seed, false);
            assert!(fr.len() >= 16, "{text:?}");
            for (t, f) in fr.iter().enumerate() {
                let at = format!("{text:?} seed {seed} frame {t}");
                let r = quaternion_to_matrix(&f.object_rotation.map(f64::from));
                for (h, wrist, first) in [(0, 20, 25), (1, 21, 40)] {
                    if f.contact[h] == 1 {
                        let gap = std::iter::once(wrist).chain(first..first + 15).map(|j| {
                            let d = sub(&f.joint_positions[j], &f.object_centre).map(f64::from);
                            // into the object's frame, from its box centre
                            shape.distance(&std::array::from_fn(|k| (0..3).map(|i| r[i][k] * d[i]).sum()))
                        });
                        let gap = gap.fold(f64::INFINITY, f64::min).max(0.0);
                        (grip_sum, grip_max, grip_n) = (grip_sum + gap, grip_max.max(gap), grip_n + 1);
                    }
                }
                // Fields agree within 1 mm: wrist-to-object is the FK wrist minus the
                // centre, the centre is the object pose applied to the catalogue's centre.
                for (h, wrist) in [(0, 20), (1, 21)] {
                    let want = sub(&f.joint_positions[wrist], &f.object_centre);
                    let got = [f.left_wrist_to_object, f.right_wrist_to_object][h];
                    assert!(dist(&got, &want) < 1e-3, "{at}: wrist_to_object {got:?} vs FK {want:?}");
                }
                let r = quaternion_to_matrix(&f.object_rotation.map(f64::from));
                let c = mat_vec(&r, &centre_local);
                let want = [0, 1, 2].map(|i| (f.object_translation[i] as f64 + c[i]) as f32);
                assert!(dist(&f.object_centre, &want) < 1e-3, "{at}: centre");
            }
            // Frames each hand's own flag (the model's) has been off: a hand lets go once it
            // has been off OFF_FRAMES - 1 frames, and the last one holding puts the object
            // down for up to PUT_DOWN_FRAMES more, still showing contact.
            let mut off = vec![[0u32; 2]; fr.len()];
            for (t, f) in fr.iter().enumerate() {
                let was = if t > 0 { off[t - 1] } else { [0; 2] };
                off[t] = [0, 1].map(|h| if f.contact_probability[h] > CONTACT_THRESHOLD { 0 } else { was[h] + 1 });
            }
            for (t, w) in fr.windows(2).enumerate() {
                let (a, b) = (&w[0], &w[1]);
                let at = format!("{text:?} seed {seed} frames {t}-{}", t + 1);
                let step = dist(&a.object_translation, &b.object_translation);
                if a.contact != b.contact {
                    // A grasp, a release or a hand-over: no jump beyond what the hands move
                    // (the model's own hands jump at some token seams; the stage adds none).
                    let hands = dist(&a.joint_positions[20], &b.joint_positions[20])
                        .max(dist(&a.joint_positions[21], &b.joint_positions[21]));
                    assert!(step <= 2.0 * hands + 0.01, "{at}: the object jumps {step} m, the hands {hands} m");
                }
                if a.contact == [0, 0] && b.contact == [0, 0] {
                    // Unheld: no drift; only falling, or rising onto the support at FADE_SPEED.
                    let (pa, pb) = (a.object_translation, b.object_translation);
                    assert_eq!((pa[0], pa[1]), (pb[0], pb[1]), "{at}: an unheld object drifts");
                    // It turns only to tip onto a face of its box, toward upright, at TIP_SPEED.
                    if a.object_rotation != b.object_rotation {
                        let (ta, tb) = (tilt(&a.object_rotation), tilt(&b.object_rotation));
                        assert!(tb < ta, "{at}: an unheld object turns away from a face ({ta} -> {tb} rad)");
                        let turn = angle(&a.object_rotation, &b.object_rotation);
                        assert!(turn <= TIP_SPEED / fps + 1e-4, "{at}: it tips {turn} rad in a frame");
                    }
                    // (The last frame lands an object still falling: ContactStage::finish.)
                    if t + 2 < fr.len() {
                        // A falling object reaches ~2.5 m/s over a table's height.
                        assert!(step * fps < 4.0, "{at}: object at {} m/s", step * fps);
                        assert!(pb[2] as f64 - pa[2] as f64 <= FADE_SPEED / fps + 1e-6, "{at}: it rises");
                    }
                }
                for (h, wrist) in [(0usize, 20usize), (1, 21)] {
                    if a.contact[h] == 1 && b.contact[h] == 1 && a.contact[1 - h] == 0 && b.contact[1 - h] == 0 {
                        // Held by one hand: rigid, the wrist stays as far from the centre;
                        // while it lets go the object may slip onto the support it is put
                        // down on (at most half MAX_SPEED a frame): the frames put down, and
                        // the one before the frame the hand lets go in, which still shows its
                        // contact.
                        let (da, db) = (
                            dist(&a.joint_positions[wrist], &a.object_centre),
                            dist(&b.joint_positions[wrist], &b.object_centre),
                        );
                        let last =
                            fr[t + 2..].iter().take(2).any(|c| c.contact[h] == 0) || off[t + 1][h] + 1 >= OFF_FRAMES;
                        let slip = if last { 0.5 * MAX_SPEED / fps + 1e-3 } else { 1e-3 };
                        assert!((da - db).abs() < slip, "{at}: hand {h} slips {da} -> {db}");
                    }
                }
            }
            // Issue 17's bar: no wrist or object faster than the ground truth's peak (SynthGrasp:
            // 2.75 m/s), the model's token seams included; the last frame lands an object still
            // falling at once.
            for (t, w) in fr.windows(2).enumerate() {
                let speed = |p: fn(&Frame) -> [f32; 3]| dist(&p(&w[0]), &p(&w[1])) * fps;
                let wrist = speed(|f| f.joint_positions[20]).max(speed(|f| f.joint_positions[21]));
                assert!(wrist <= GROUND_TRUTH_PEAK, "{text:?} seed {seed} frame {t}: a wrist at {wrist} m/s");
                if t + 2 < fr.len() {
                    let object = speed(|f| f.object_translation);
                    assert!(object <= GROUND_TRUTH_PEAK, "{text:?} seed {seed} frame {t}: the object at {object} m/s");
                }
            }
            grasps += fr.windows(2).filter(|w| w[0].contact == [0, 0] && w[1].contact != [0, 0]).count();
            // The end: an object nobody holds rests on the ground or on the table it started on.
            let half = objects[index].half_extents.map(f64::from);
            let bottom = |f: &Frame| {
                let r = quaternion_to_matrix(&f.object_rotation.map(f64::from));
                f.object_centre[2] as f64 - (0..3).map(|k| r[2][k].abs() * half[k]).sum::<f64>()
            };
            let last = fr.last().unwrap();
            if last.contact == [0, 0] {
                let (b, table) = (bottom(last), bottom(&fr[0]));
                assert!(
                    b.abs() < 1e-3 || (b - table).abs() < 1e-3,
                    "{text:?} seed {seed}: ends at {b} (table {table})"
                );
            }
        }
    }
    // The stage is not vacuous on this model: some streams grasp.
    assert!(grasps > 0, "no stream grasped the object");
    let mean = grip_sum / grip_n.max(1) as f64;
    println!(
        "held frames {grip_n}: the hand {:.1} mm off the object on average, {:.1} mm at most",
        mean * 1e3,
        grip_max * 1e3
    );
    assert!(mean <= 0.01 && grip_max <= 0.03, "held: hand {mean} m off the object on average, {grip_max} m at most");
}

#[test]
fn raw_output_is_the_models_own() {
    let e = engine();
    let text = PROMPTS[0];
    let (raw, consistent) = (frames(&e, text, 1, true), frames(&e, text, 1, false));
    assert_eq!(raw.len(), consistent.len());
    for f in &raw {
        for h in 0..2 {
            assert_eq!(f.contact[h], u8::from(f.contact_probability[h] > 0.5));
        }
    }
    // Same tokens, so the same root over the ground (raised by the stream's ground lift, and
    // lowered where the model floats the body), and with free feet the same legs; the stage
    // moves the object, arms and spine, and holds the whole pose back only where a hand
    // would outrun its speed limit (a seam).
    let consistent = collect(&e, text, StreamConfig { seed: Some(1), foot_lock: Some(false), ..Default::default() });
    let lift = consistent[0].root_translation[2] - raw[0].root_translation[2];
    let same = raw
        .iter()
        .zip(&consistent)
        .filter(|(a, b)| {
            a.root_translation[..2] == b.root_translation[..2]
                && b.root_translation[2] - a.root_translation[2] <= lift + 1e-5
                && a.body_rotations[0] == b.body_rotations[0] // left hip
                && a.left_hand_rotations == b.left_hand_rotations // fingers
        })
        .count();
    assert!(same * 4 >= raw.len() * 3, "{same} of {} frames keep the model's root, legs and fingers", raw.len());
    assert!(raw.iter().zip(&consistent).any(|(a, b)| a.object_translation != b.object_translation));
}

/// CHOIS's foot sliding (docs/training.md's metric, `metrics.foot_sliding`), mm per frame:
/// the ankles' and toes' horizontal steps in frames where they are near the floor (the median
/// height of the toes in their static frames), weighted by how near.
fn foot_sliding(fr: &[Frame], fps: f64) -> f64 {
    let static_step = 0.005 * 30.0 / fps;
    let mut toes: Vec<f64> = fr
        .windows(2)
        .flat_map(|w| {
            [10, 11].map(|j| (dist(&w[0].joint_positions[j], &w[1].joint_positions[j]), w[0].joint_positions[j][2]))
        })
        .filter(|&(d, _)| d < static_step)
        .map(|(_, z)| f64::from(z))
        .collect();
    toes.sort_by(f64::total_cmp);
    let floor = toes.get(toes.len() / 2).copied().unwrap_or(0.0);
    let total: f64 = [(7, 0.08), (10, 0.04), (8, 0.08), (11, 0.04)]
        .iter()
        .map(|&(j, top)| {
            fr.windows(2)
                .map(|w| {
                    let (a, b) = (w[0].joint_positions[j], w[1].joint_positions[j]);
                    let (d, h) = (dist(&[a[0], a[1], 0.0], &[b[0], b[1], 0.0]), f64::from(a[2]) - floor);
                    if h < top {
                        (d * (2.0 - 2f64.powf(h / top))).abs()
                    } else {
                        0.0
                    }
                })
                .sum::<f64>()
                * 1000.0
                / fr.len() as f64
        })
        .sum();
    total / 4.0
}

/// Standing on the ground and planted feet: the default model's standing feet slide (CHOIS foot sliding of a few mm per
/// frame, SynthGrasp's ~0); the stage pins them, within issue 15's bar (1.5 × the ground
/// truth's + 1 mm), and moves a foot no faster than the model's plus `FOOT_FADE` when it
/// lets one go. Free feet (`foot_lock: Some(false)`) are the model's legs.
#[test]
fn planted_feet_do_not_slide() {
    let e = engine();
    let fps = e.bundle().unwrap().manifest.fps;
    let (mut pinned, mut free, mut lifts) = (0.0, 0.0, Vec::new());
    for (text, seed) in [(PROMPTS[0], 1), (PROMPTS[1], 2), (PROMPTS[2], 1), (PROMPTS[3], 3)] {
        let on = |cfg: StreamConfig| collect(&e, text, StreamConfig { seed: Some(seed), ..cfg });
        let (planted, loose) =
            (on(StreamConfig::default()), on(StreamConfig { foot_lock: Some(false), ..Default::default() }));
        assert_eq!(planted.len(), loose.len());
        // The character stands on the ground: the first frame's lower toe joint at
        // GROUND_TOE_HEIGHT (the model's own stands anywhere from 2 cm below to 15 cm above).
        let toe = |f: &Frame| f.joint_positions[10][2].min(f.joint_positions[11][2]) as f64;
        assert!(
            (toe(&planted[0]) - comgrasp::contact::GROUND_TOE_HEIGHT).abs() < 1e-4,
            "{text:?}: toe {}",
            toe(&planted[0])
        );
        lifts.push(toe(&planted[0]) - toe(&frames(&e, text, seed, true)[0]));
        let (a, b) = (foot_sliding(&planted, fps), foot_sliding(&loose, fps));
        println!("{text:?} seed {seed}: foot sliding {a:.2} mm planted, {b:.2} mm free");
        // A model that lifts the whole body (both feet 10 cm up: seed 2 of the lift) frees them.
        assert!(a <= 0.7 * b, "{text:?} seed {seed}: feet slide {a} mm per frame, free {b}");
        (pinned, free) = (pinned + a, free + b);
        for t in 1..planted.len() {
            // A foot let go catches up with the model's at FOOT_FADE; its toes turn back with it.
            let v = |f: &[Frame], j: usize| dist(&f[t].joint_positions[j], &f[t - 1].joint_positions[j]) * fps;
            for j in [7, 8] {
                let (shown, model) = (v(&planted, j), v(&loose, j));
                assert!(
                    shown <= model + comgrasp::feet::FOOT_FADE + 1e-3,
                    "{text:?} frame {t}: ankle {j} at {shown} m/s, the model's {model}"
                );
            }
            for j in [10, 11] {
                assert!(v(&planted, j) <= GROUND_TRUTH_PEAK, "{text:?} frame {t}: toe {j} at {} m/s", v(&planted, j));
            }
        }
    }
    // Issue 15's bar (1.5 x SynthGrasp's ~0 + 1 mm) on the mean, and not vacuous: the
    // model's own feet slide.
    assert!(pinned / 4.0 <= 1.0 && free / 4.0 > 1.0, "free feet {free} mm, planted {pinned} mm (four streams)");
    assert!(lifts.iter().any(|l| l.abs() > 0.01), "the model's characters all stood on the ground already: {lifts:?}");
}

/// Placement from the grasp: the resting object starts where the model's hand first closes
/// on it (the raw stream's FK wrist minus its wrist-to-object vector, at the first frame a
/// flag has been on for two frames), and every frame still comes out, once, in order.
#[test]
fn the_resting_object_starts_where_the_first_grasp_closes() {
    let e = engine();
    let mut placed = 0;
    for (text, seed) in [(PROMPTS[1], 1), (PROMPTS[3], 2), (PROMPTS[0], 3)] {
        let raw = frames(&e, text, seed, true);
        let on = |cfg: StreamConfig| collect(&e, text, StreamConfig { seed: Some(seed), ..cfg });
        let (placed_fr, kept) =
            (on(StreamConfig::default()), on(StreamConfig { grasp_placement: Some(false), ..Default::default() }));
        for fr in [&placed_fr, &kept] {
            assert_eq!(fr.len(), raw.len(), "{text:?}");
            assert!(fr.iter().enumerate().all(|(i, f)| f.frame_index == i as u64), "{text:?}: frame order");
            assert!(fr.iter().take(fr.len() - 1).all(|f| f.is_last == 0) && fr.last().unwrap().is_last == 1);
        }
        // Without placement the object rests where the model's first frame put it (in the
        // model's world raised by the ground lift).
        let lift = kept[0].root_translation[2] - raw[0].root_translation[2];
        let raised = |p: [f32; 3]| [p[0], p[1], p[2] + lift];
        assert!(dist(&kept[0].object_translation, &raised(raw[0].object_translation)) < 1e-5, "{text:?}");
        let onset = (1..raw.len().min(comgrasp::contact::PLACE_LOOKAHEAD)).find_map(|t| {
            (0..2)
                .find(|&h| {
                    raw[t].contact[h] == 1 && raw[t - 1].contact[h] == 1 && (t < 2 || raw[t - 2].contact[h] == 0)
                })
                .map(|h| (t, h))
        });
        match onset {
            Some((t, h)) => {
                let mut want = [0.0f64; 3];
                let mut n = 0.0;
                for g in (0..2).filter(|&g| {
                    raw[t].contact[g] == 1 && raw[t - 1].contact[g] == 1 && (t < 2 || raw[t - 2].contact[g] == 0)
                }) {
                    let w2o = [raw[t].left_wrist_to_object, raw[t].right_wrist_to_object][g];
                    let c = sub(&raw[t].joint_positions[[20, 21][g]], &w2o);
                    want = std::array::from_fn(|i| want[i] + c[i] as f64);
                    n += 1.0;
                }
                let want = raised(want.map(|v| (v / n) as f32));
                let d = dist(&placed_fr[0].object_centre, &want);
                assert!(
                    d < 1e-3,
                    "{text:?} seed {seed}: hand {h} closes at frame {t} on {want:?}, the object starts at {:?}",
                    placed_fr[0].object_centre
                );
                placed += 1;
            }
            None => {
                assert_eq!(placed_fr[0].object_translation, kept[0].object_translation, "{text:?}: no grasp, not moved")
            }
        }
    }
    assert!(placed > 0, "no stream grasped within the look-ahead");
}

fn placement(position: [f32; 3], yaw_deg: f32, up: [f32; 3]) -> comgrasp::Placement {
    let h = yaw_deg.to_radians() / 2.0;
    comgrasp::Placement { position, rotation: [up[0] * h.sin(), up[1] * h.sin(), up[2] * h.sin(), h.cos()] }
}

#[test]
fn anchored_streams_are_in_the_hosts_world() {
    use comgrasp::{Anchor, CoordinateSystem};
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("models").join("default");
    // glTF: y up; the host's character at (2, 0, -3) facing +x (a quarter turn from -z, the
    // native +y), the mug 0.55 m in front of it on a 0.8 m table.
    let e = Engine::new(EngineConfig {
        bundle_path: Some(dir),
        enable_fk: true,
        coordinate_system: CoordinateSystem::CG_COORDS_GLTF,
        ..EngineConfig::default()
    })
    .unwrap();
    let up = [0.0, 1.0, 0.0];
    let anchor = Anchor {
        character: Some(placement([2.0, 0.0, -3.0], -90.0, up)),
        object: Some(placement([2.55, 0.8, -3.0], 0.0, up)),
        place_character: false,
    };
    let fr = collect(&e, PROMPTS[0], StreamConfig { seed: Some(1), anchor: Some(anchor), ..StreamConfig::default() });
    let f0 = &fr[0];
    // The pelvis stands over the host's ground point; the feet on its ground (y = 0).
    assert!((f0.root_translation[0] - 2.0).abs() < 1e-4 && (f0.root_translation[2] + 3.0).abs() < 1e-4);
    let foot = f0.joint_positions[10][1].min(f0.joint_positions[11][1]);
    assert!(foot.abs() < 0.1, "feet at {foot}");
    // The mug starts exactly at the host's pose, and stays until a hand holds it.
    assert_eq!(f0.object_translation, [2.55, 0.8, -3.0]);
    // The character faces the host's heading (+x, y up): its left is -z, so the hips'
    // left-to-right axis is +z.
    let hips = sub(&f0.joint_positions[2], &f0.joint_positions[1]);
    assert!(hips[2] > 0.8 * dist(&f0.joint_positions[2], &f0.joint_positions[1]) as f32, "hips {hips:?}");
    // Out of reach: a clear error at start.
    let far = Anchor { object: Some(placement([9.0, 0.8, -3.0], 0.0, up)), ..anchor };
    let Err(err) = e.start(PROMPTS[0], StreamConfig { anchor: Some(far), ..StreamConfig::default() }) else {
        panic!("an object 7 m away is within reach")
    };
    assert!(err.to_string().contains("out of reach"), "{err}");
    // The interaction spot: the character comes to the object.
    let spot = Anchor { character: None, place_character: true, ..anchor };
    let g = collect(&e, PROMPTS[0], StreamConfig { seed: Some(1), anchor: Some(spot), ..StreamConfig::default() })[0];
    assert_eq!(g.object_translation, [2.55, 0.8, -3.0]);
    let d = dist(&g.root_translation, &g.object_translation);
    assert!(d < 0.8, "the character stands at its spot, {d} m from the mug");
}

#[test]
fn a_continued_stream_starts_where_the_earlier_one_left_off() {
    let e = engine();
    let a = frames(&e, "Someone picks up the cube and puts it back", 3, false);
    let id_of = |f: &Frame| f.stream_id;
    let cfg = StreamConfig { seed: Some(4), continue_from: Some(id_of(&a[0])), ..StreamConfig::default() };
    let mut s = e.start("Drink from it", cfg).unwrap();
    // The earlier stream's object, whatever this prompt names.
    assert_eq!(s.object().unwrap().name, "cubesmall");
    let (mut b, mut f) = (Vec::new(), Frame::default());
    loop {
        match s.wait(&mut f, Duration::from_secs(5)) {
            PollResult::Frame => b.push(f),
            PollResult::End => break,
            PollResult::Pending => {}
            r => panic!("{r:?}"),
        }
    }
    let (last, first) = (a.last().unwrap(), &b[0]);
    // No pop: the seam moves no joint further than the earlier stream's own largest step.
    let step =
        |x: &Frame, y: &Frame| (0..55).map(|j| dist(&x.joint_positions[j], &y.joint_positions[j])).fold(0.0, f64::max);
    let own = a.windows(2).map(|w| step(&w[0], &w[1])).fold(0.0, f64::max);
    let seam = step(last, first);
    assert!(seam <= own, "seam {seam} m, the earlier stream's largest step {own} m");
    assert!(dist(&last.root_translation, &first.root_translation) < 0.02);
    // The object carries over: where it was, held by the same hands.
    assert_eq!(first.contact, last.contact);
    if last.contact == [0, 0] {
        assert!(dist(&first.object_translation, &last.object_translation) < 1e-5);
    }
    // Unknown or not yet ended streams, and anchoring with continuation, are refused.
    for cfg in [
        StreamConfig { continue_from: Some(999), ..StreamConfig::default() },
        StreamConfig {
            continue_from: Some(id_of(&a[0])),
            anchor: Some(comgrasp::Anchor { place_character: false, ..Default::default() }),
            ..StreamConfig::default()
        },
    ] {
        let Err(err) = e.start("Drink from it", cfg) else { panic!("accepted") };
        assert!(matches!(err, comgrasp::Error::InvalidArgument(_)), "{err}");
    }
}

/// The Python reference (`comgrasp_train.contact_stage`, which `evaluate` runs) and this
/// stage give the same frames: tests/fixtures/contact_stage holds real raw motions
/// (`input`, de-normalized 335-D) and what the Python stage made of them (`output`;
/// scripts/contact_fixture.py, which also checks that every rule fires in some case). Both
/// are decoded as the engine decodes a frame (mean 0, std 1: the values themselves); every
/// field the stage writes must agree within the manifest's frame tolerance, the contact
/// flags exactly.
#[test]
fn the_python_reference_stage_gives_the_same_frames() {
    use comgrasp::assemble::{FrameAssembler, Pose};
    use comgrasp::bundle::{npy, obj};
    use comgrasp::contact::{ContactStage, GraspOnset};
    use comgrasp::skeleton::SMPLX_PARENTS;

    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/contact_stage");
    let index: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("index.json")).unwrap()).unwrap();
    let read = |name: &serde_json::Value| {
        let path = dir.join(name.as_str().unwrap());
        npy::read(&path).unwrap().to_f32(&path).unwrap()
    };
    let rest: Vec<[f32; 3]> = read(&index["rest_joints"]).chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    let fps = index["fps"].as_f64().unwrap();
    let tol = index["tolerance"].as_f64().unwrap();
    let width = comgrasp::bundle::manifest::FRAME_DIM;
    let coords = comgrasp::CoordinateSystem::default();
    let asm =
        FrameAssembler::new(&vec![0.0; width], &vec![1.0; width], &SMPLX_PARENTS, &rest, coords, true, fps).unwrap();
    let vec3 = |v: &serde_json::Value| -> [f64; 3] { std::array::from_fn(|i| v[i].as_f64().unwrap() as f32 as f64) };
    let cases = index["cases"].as_array().unwrap();
    assert!(cases.len() >= 4);
    for case in cases {
        let (input, output) = (read(&case["input"]), read(&case["output"]));
        assert_eq!(input.len(), output.len());
        // The surface the Python stage used (float32 samples of the bundle's mesh); the
        // engine samples the same mesh into the same points and normals.
        let samples = read(&case["surface"]);
        let surface = ObjectSurface::new(
            samples.chunks_exact(6).map(|c| [c[0], c[1], c[2]].map(f64::from)).collect(),
            samples.chunks_exact(6).map(|c| [c[3], c[4], c[5]].map(f64::from)).collect(),
        );
        let mesh_path =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default").join(case["mesh"].as_str().unwrap());
        let engine_surface =
            ObjectSurface::from_mesh(&obj::parse(&std::fs::read_to_string(mesh_path).unwrap()).unwrap());
        assert_eq!(engine_surface.points.len(), surface.points.len(), "{}: surface samples", case["object"]);
        for (a, b) in engine_surface
            .points
            .iter()
            .chain(&engine_surface.normals)
            .zip(surface.points.iter().chain(&surface.normals))
        {
            assert!((0..3).all(|i| (a[i] - b[i]).abs() < 1e-6), "{}: sample {a:?} vs {b:?}", case["object"]);
        }
        let shape = ObjectShape {
            centre: vec3(&case["centre"]),
            half_extents: vec3(&case["half_extents"]).map(f64::abs),
            surface: Some(std::sync::Arc::new(surface)),
        };
        let mut stage = ContactStage::new(shape, fps);
        let n = input.len() / width;
        // Placement from the grasp, as a stream does it (unless the case turns it off): the raw
        // frames up to the first grasp.
        let mut onset = GraspOnset::default();
        if case["place"].as_bool().unwrap() {
            onset.feed_features(&asm, &input);
        }
        assert_eq!(onset.centre().is_some(), case["placed"].as_bool().unwrap(), "{}: placed", case["prompt"]);
        let mut worst = 0.0f64;
        for t in 0..n {
            let at = format!("{} frame {t}", case["prompt"]);
            let (mut pose, mut want) = (Pose::default(), Pose::default());
            asm.decode(&input[t * width..(t + 1) * width], &mut pose);
            asm.decode(&output[t * width..(t + 1) * width], &mut want);
            stage.ground(asm.skeleton(), &mut pose);
            if let (0, Some(centre)) = (t, onset.centre()) {
                stage.place(&mut pose, &centre);
            }
            stage.apply(asm.skeleton(), &mut pose);
            if t + 1 == n {
                stage.finish(asm.skeleton(), &mut pose);
            }
            assert_eq!(pose.contact, want.contact, "{at}: contact");
            let pairs = pose
                .local
                .iter()
                .chain([&pose.object_rotation])
                .zip(want.local.iter().chain([&want.object_rotation]))
                .flat_map(|(a, b)| (0..3).flat_map(move |i| (0..3).map(move |j| (a[i][j], b[i][j]))));
            let points = [
                pose.pelvis,
                pose.object_translation,
                pose.object_centre,
                pose.wrist_to_object[0],
                pose.wrist_to_object[1],
            ]
            .into_iter()
            .zip([
                want.pelvis,
                want.object_translation,
                want.object_centre,
                want.wrist_to_object[0],
                want.wrist_to_object[1],
            ])
            .flat_map(|(a, b)| (0..3).map(move |i| (a[i], b[i])));
            for (a, b) in pairs.chain(points) {
                worst = worst.max((a - b).abs());
                assert!((a - b).abs() <= tol, "{at}: {a} vs the Python reference's {b} (tolerance {tol})");
            }
        }
        eprintln!("{}: {n} frames, largest difference {worst:.1e}", case["prompt"]);
    }
}

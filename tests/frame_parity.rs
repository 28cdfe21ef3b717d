//! Frame assembly against the tiny bundle's Python-recorded decode case
//! (`models/tiny/parity/decode/case0_*`): de-normalization bit for bit, forward
//! kinematics and quaternions against values computed with `comgrasp_train`
//! (`representation.features_to_joints`, `rotations.matrix_to_quaternion`), every
//! coordinate system, and no allocation in `assemble`.

use comgrasp::assemble::{FrameAssembler, FRAME_DIM};
use comgrasp::frame::{cg_coordinate_system as Cs, Frame};

mod alloc_counter;
use alloc_counter::count_allocs;

#[test]
fn allocation_counter_works() {
    let (_, n) = count_allocs(|| std::hint::black_box(Vec::<u8>::with_capacity(16)));
    assert!(n > 0);
}

mod bundle_support;
use bundle_support::{load_f32, tiny_dir};

/// A float32 .npy of the tiny bundle (the engine's own reader): (shape, data).
fn npy_f32(rel: &str) -> (Vec<usize>, Vec<f32>) {
    load_f32(&tiny_dir(), rel)
}

struct Manifest {
    mean: Vec<f32>,
    std: Vec<f32>,
    parents: Vec<i32>,
    rest: Vec<[f32; 3]>,
    fps: f64,
}

fn manifest() -> Manifest {
    let text = std::fs::read_to_string(tiny_dir().join("manifest.json")).unwrap();
    let m: serde_json::Value = serde_json::from_str(&text).unwrap();
    let f32s = |v: &serde_json::Value| -> Vec<f32> {
        v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect()
    };
    Manifest {
        mean: f32s(&m["normalization"]["mean"]),
        std: f32s(&m["normalization"]["std"]),
        parents: m["skeleton"]["parents"].as_array().unwrap().iter().map(|x| x.as_i64().unwrap() as i32).collect(),
        rest: m["skeleton"]["rest_joints"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| {
                let r = f32s(r);
                [r[0], r[1], r[2]]
            })
            .collect(),
        fps: m["fps"].as_f64().unwrap(),
    }
}

fn assembler(m: &Manifest, c: Cs, fk: bool) -> FrameAssembler {
    FrameAssembler::new(&m.mean, &m.std, &m.parents, &m.rest, c, fk, m.fps).unwrap()
}

/// (frame, joint, world position) from Python: features_to_joints(denormalized, rest).
const FK_REF: [(usize, usize, [f64; 3]); 24] = [
    (0, 0, [0.0383104607462883, -0.02506873570382595, 0.9077816009521484]),
    (0, 12, [0.02511826678659762, 0.485550850066956, 0.8590796596024615]),
    (0, 15, [0.021698828241556195, 0.5538704538385544, 0.9112403649325131]),
    (0, 20, [0.7310960129641328, 0.4428590747947266, 0.8092849874009576]),
    (0, 21, [-0.6749616585230062, 0.38691970048579905, 0.8137979245322136]),
    (0, 22, [0.024720663735215698, 0.528800919723201, 0.9561000012383102]),
    (0, 27, [0.8820450969478779, 0.43648035171091437, 0.831646499434878]),
    (0, 54, [-0.7573212388068207, 0.35456328194083053, 0.8804972418895839]),
    (37, 0, [0.048074763268232346, -0.02615247294306755, 0.892236590385437]),
    (37, 12, [0.027537410944208703, 0.4848563057513097, 0.8512870451110135]),
    (37, 15, [0.02327120597843197, 0.5520434611063754, 0.9048378214871244]),
    (37, 20, [0.7358967081642582, 0.4517230957017121, 0.8165911958300199]),
    (37, 21, [-0.6706606168398956, 0.38589364012324623, 0.8002688916836698]),
    (37, 22, [0.02663369414400068, 0.5265130302462906, 0.9494123744678874]),
    (37, 27, [0.8857235459512123, 0.4471847214765743, 0.8450000973198901]),
    (37, 54, [-0.7520287427989839, 0.35006505591769294, 0.8667442696733416]),
    (111, 0, [0.029497919604182243, 0.01550630945712328, 0.8938774466514587]),
    (111, 12, [0.017934755622918564, 0.5270130231688901, 0.8549773924852241]),
    (111, 15, [0.016504973596061977, 0.5946956998139106, 0.9080529142021256]),
    (111, 20, [0.7240293581401949, 0.4737161497388771, 0.8088491031298424]),
    (111, 21, [-0.6830317460974218, 0.4380606363651034, 0.809725853838863]),
    (111, 22, [0.019958664315777776, 0.56883231649687, 0.9524281034840699]),
    (111, 27, [0.8745099067464152, 0.46491897801202503, 0.8333981068951313]),
    (111, 54, [-0.7644383544392901, 0.4031281409474407, 0.8763517721585533]),
];

/// (frame, joint or None for the object, quaternion (w, x, y, z)) from Python.
const QUAT_REF: [(usize, Option<usize>, [f64; 4]); 8] = [
    (0, Some(0), [0.9995937993677533, -0.013801037450413337, -0.01467744564868026, 0.020157882330793797]),
    (0, Some(20), [0.999587542063748, 0.020130636363692733, -0.01202557765107264, 0.016579768174061166]),
    (0, Some(45), [0.9999730793748207, -0.0005770189820591561, 0.006189939686387768, -0.0038977200273824374]),
    (0, None, [0.9996366133873295, 0.01588415836728171, -0.021506179091030846, 0.00343786988968063]),
    (37, Some(0), [0.9994830067680768, -0.012980786893272077, -0.01791978404653501, 0.023325944636857814]),
    (37, Some(20), [0.9996165636650652, 0.012243169766723785, -0.0203471350834143, 0.014241647882429837]),
    (37, Some(45), [0.9999858367053608, 0.003874643068104086, -0.0034118938909452117, -0.0012932555244053437]),
    (37, None, [0.999711087292138, 0.011710893524406792, -0.020756951866811084, 0.0031218371562703145]),
];

fn joint_quat(f: &Frame, j: Option<usize>) -> [f32; 4] {
    match j {
        None => f.object_rotation,
        Some(0) => f.root_rotation,
        Some(j @ 1..=21) => f.body_rotations[j - 1],
        Some(j @ 25..=39) => f.left_hand_rotations[j - 25],
        Some(j @ 40..=54) => f.right_hand_rotations[j - 40],
        Some(j) => panic!("joint {j} has no rotation in the frame"),
    }
}

#[test]
fn denormalization_is_bit_exact() {
    let m = manifest();
    let (shape, norm) = npy_f32("parity/decode/case0_frames_offline.npy");
    let (shape2, den) = npy_f32("parity/decode/case0_frames_denormalized.npy");
    assert_eq!((shape.clone(), shape2), (vec![112, FRAME_DIM], vec![112, FRAME_DIM]));
    let a = assembler(&m, Cs::CG_COORDS_NATIVE, false);
    let mut out = [0.0f32; FRAME_DIM];
    for t in 0..shape[0] {
        a.denormalize(&norm[t * FRAME_DIM..(t + 1) * FRAME_DIM], &mut out);
        for i in 0..FRAME_DIM {
            // (contact channels: std 1, mean 0 and values inside [0, 1] here, so the
            // clamp is the identity and the bits agree too)
            assert_eq!(out[i].to_bits(), den[t * FRAME_DIM + i].to_bits(), "frame {t} channel {i}");
        }
    }
}

#[test]
fn fk_and_rotations_match_python_in_every_coordinate_system() {
    let m = manifest();
    let (_, norm) = npy_f32("parity/decode/case0_frames_offline.npy");
    let (_, den) = npy_f32("parity/decode/case0_frames_denormalized.npy");
    let frame = |t: usize| &norm[t * FRAME_DIM..(t + 1) * FRAME_DIM];
    // (coords, p' = c * S p as a closure, tolerance)
    type Map = fn([f64; 3]) -> [f64; 3];
    let systems: [(Cs, Map, f64); 4] = [
        (Cs::CG_COORDS_NATIVE, |p| p, 1e-5),
        (Cs::CG_COORDS_GLTF, |p| [p[0], p[2], -p[1]], 1e-5),
        (Cs::CG_COORDS_UNITY, |p| [-p[0], p[2], -p[1]], 1e-5),
        (Cs::CG_COORDS_UNREAL, |p| [100.0 * p[0], -100.0 * p[1], 100.0 * p[2]], 1e-3),
    ];
    for (cs, map, tol) in systems {
        let a = assembler(&m, cs, true);
        let mut f = Frame::default();
        for &(t, j, p) in &FK_REF {
            a.assemble(frame(t), 3, t as u64, false, &mut f);
            assert_eq!(f.has_joint_positions, 1);
            let want = map(p);
            for i in 0..3 {
                assert!(
                    (f.joint_positions[j][i] as f64 - want[i]).abs() < tol,
                    "{cs:?} frame {t} joint {j}: {:?} vs {want:?}",
                    f.joint_positions[j]
                );
            }
            // The pelvis is the root translation; other fields are the mapped features.
            assert_eq!(f.joint_positions[0], f.root_translation);
            let feat = |c: usize| {
                map([
                    den[t * FRAME_DIM + c] as f64,
                    den[t * FRAME_DIM + c + 1] as f64,
                    den[t * FRAME_DIM + c + 2] as f64,
                ])
            };
            for (got, col) in [
                (f.object_translation, 15),
                (f.object_centre, 18),
                (f.left_wrist_to_object, 237),
                (f.right_wrist_to_object, 331),
            ] {
                let w = feat(col);
                assert!((0..3).all(|i| (got[i] as f64 - w[i]).abs() < tol), "{cs:?} col {col}");
            }
            assert_eq!(f.time_s, t as f64 / 30.0);
        }
        if cs == Cs::CG_COORDS_NATIVE {
            for &(t, j, wxyz) in &QUAT_REF {
                a.assemble(frame(t), 3, t as u64, false, &mut f);
                let q = joint_quat(&f, j);
                let want = [wxyz[1], wxyz[2], wxyz[3], wxyz[0]];
                for i in 0..4 {
                    assert!((q[i] as f64 - want[i]).abs() < 1e-6, "frame {t} joint {j:?}: {q:?} vs {want:?}");
                }
            }
        }
    }
}

#[test]
fn assemble_does_not_allocate() {
    let m = manifest();
    let (_, norm) = npy_f32("parity/decode/case0_frames_offline.npy");
    for cs in [Cs::CG_COORDS_NATIVE, Cs::CG_COORDS_GLTF, Cs::CG_COORDS_UNITY, Cs::CG_COORDS_UNREAL] {
        for fk in [false, true] {
            let a = assembler(&m, cs, fk);
            let mut f = Frame::default();
            let (_, n) = count_allocs(|| {
                for t in 0..112 {
                    a.assemble(&norm[t * FRAME_DIM..(t + 1) * FRAME_DIM], 1, t as u64, t == 111, &mut f);
                }
            });
            assert_eq!(n, 0, "{cs:?} fk={fk}");
            assert_eq!(f.is_last, 1);
        }
    }
}

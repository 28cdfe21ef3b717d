//! The grasp gate of the default model (issue 15): `comgrasp generate --fk` on
//! `models/default` (the files the library embeds) with the engine's default output, a
//! handful of prompts × seeds, each checked by the quality report's own checker
//! (`comgrasp-data check-engine`, in the project's venv) for what a player sees:
//! * the object leaves its rest pose only while a hand holds it (`unheld_still`: no unheld
//!   motion over 20 mm / 15°);
//! * the hand the prompt names holds it (`grasp`);
//! * a lift raises it by at least 10 cm (`lift`);
//! * a drink brings it within 15 cm of the head (`drink`).
//!
//! A sampled model is judged on rates, not single samples (sampling is seeded, so the rates
//! of one bundle are exact). The lift and drink thresholds sit between what the model shipped
//! before scored on these cases and what the shipped one scores, so a regression to the old
//! model fails.
use std::path::{Path, PathBuf};
use std::process::Command;

/// (prompt, seeds): two of each intent the gate checks, left and right hand, plus two the
/// grasp and stillness rates count; six seeds each, so that a rate moves by 1/6 or 1/12 per
/// sample and not by a quarter.
const CASES: &[(&str, &[u64])] = &[
    ("The woman is lifting the small cube with her left hand.", SEEDS),
    ("The woman is lifting the small pyramid with her right hand.", SEEDS),
    ("The woman is drinking from the mug with her left hand.", SEEDS),
    ("The woman is drinking from the mug with her right hand.", SEEDS),
    ("The man is inspecting the small cube with his left hand.", SEEDS),
    ("The woman is handing over the small pyramid with her right hand.", SEEDS),
];
const SEEDS: &[u64] = &[1, 2, 3, 4, 5, 6];

/// Least share of samples with the named hand holding the object, with nothing moving it
/// otherwise, of lifts that rise 10 cm, of drinks that come within 15 cm of the head (the
/// checker's own rules and thresholds, `intent_check.CheckConfig`). On these six seeds the
/// H200-trained model shipped before scored 0.89 / 0.97 / 0.50 / 0.67; the shipped one
/// (Transformers on 7,000 sequences, guidance 2) scored 0.94 / 1.00 / 0.67 / 0.92, and scores
/// 0.97 / 0.92 / 0.83 / 0.92 since the stage places the object from the grasp, puts it down
/// from 20 cm and keeps it in a hand opened in mid-air (placement alone: 0.97 / 0.81 / 0.83 /
/// 0.92); the one shipped since 2026-12-08 (its VQ trained twice as long) scores 1.00 / 1.00 /
/// 0.92 / 1.00. Lift and drink separate the models, one sample of margin each; stillness separates
/// contact stages: 0.42 before the stage levelled an object brought down tilted before setting
/// it down and showed contact through the frame a hand lets go in, 0.79 (seeds 1-4) with the
/// second change alone, 0.81 with placement alone.
const MIN_GRASP: f64 = 0.85;
const MIN_UNHELD_STILL: f64 = 0.85;
const MIN_LIFT: f64 = 0.55;
const MIN_DRINK: f64 = 0.75;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("cli/ has a parent")
}

fn tmp(name: &str) -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("grasp-{}-{name}", std::process::id()))
}

fn rate(
    rows: &[serde_json::Value],
    keep: impl Fn(&serde_json::Value) -> bool,
    pass: impl Fn(&serde_json::Value) -> bool,
) -> f64 {
    let kept: Vec<_> = rows.iter().filter(|r| keep(r)).collect();
    assert!(!kept.is_empty(), "no sample of this kind");
    kept.iter().filter(|r| pass(r)).count() as f64 / kept.len() as f64
}

#[test]
fn the_default_model_grasps_what_the_prompt_names() {
    let checker = root().join(".venv/bin/comgrasp-data");
    assert!(checker.exists(), "{} is missing: run scripts/setup_python.sh", checker.display());
    let bundle = root().join("models/default");
    let mut rows = Vec::new();
    for (k, (prompt, seeds)) in CASES.iter().enumerate() {
        let mut files = Vec::new();
        for seed in seeds.iter() {
            let npz = tmp(&format!("p{k}_s{seed}.npz"));
            let o = Command::new(env!("CARGO_BIN_EXE_comgrasp"))
                .args(["generate", "--bundle", bundle.to_str().unwrap(), "--text", prompt])
                .args(["--seed", &seed.to_string(), "--fk", "--out", npz.to_str().unwrap()])
                .output()
                .expect("run comgrasp");
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
            files.push(npz);
        }
        // One checker per prompt, all its seeds at once: the checker's start (Python, torch)
        // costs several times what checking a motion does.
        let json = tmp(&format!("p{k}.json"));
        let c = Command::new(&checker)
            .arg("check-engine")
            .args(&files)
            .args(["--prompt", prompt, "--json", json.to_str().unwrap()])
            .output()
            .expect("run check-engine");
        let text = std::fs::read_to_string(&json).unwrap_or_else(|e| {
            panic!("check-engine wrote no {}: {e}\n{}", json.display(), String::from_utf8_lossy(&c.stderr))
        });
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        let results = v["results"].as_array().expect("check-engine's results");
        assert_eq!(results.len(), seeds.len(), "one result per file");
        for (seed, r) in seeds.iter().zip(results) {
            let mut row = r.clone();
            row["case"] = serde_json::json!(format!("{prompt} (seed {seed})"));
            rows.push(row);
        }
    }
    let report: Vec<String> = rows.iter().map(|r| format!("{}: {}", r["case"], r["reason"])).collect();
    let report = report.join("\n");
    let is = |word: &'static str| move |r: &serde_json::Value| r["prompt"].as_str().unwrap().contains(word);
    let all = |_: &serde_json::Value| true;
    let flag = |key: &'static str| move |r: &serde_json::Value| r[key].as_f64() == Some(1.0);
    let grasp = rate(&rows, all, flag("intent_grasp"));
    let still = rate(&rows, all, flag("intent_unheld_still"));
    let lift = rate(&rows, is("lifting"), flag("intent_lift"));
    let drink = rate(&rows, is("drinking"), flag("intent_drink"));
    let got = format!("grasp {grasp:.2}, unheld still {still:.2}, lift {lift:.2}, drink {drink:.2}");
    eprintln!("default model: {got}"); // shown with --nocapture, for moving the thresholds
    assert!(
        grasp >= MIN_GRASP && still >= MIN_UNHELD_STILL && lift >= MIN_LIFT && drink >= MIN_DRINK,
        "{got} (want >= {MIN_GRASP}, {MIN_UNHELD_STILL}, {MIN_LIFT}, {MIN_DRINK})\n{report}"
    );
}

//! Replays the PyTorch parity vectors of models/tiny through the engine's tract runners:
//! text (tokenizer ids, token states, pooled embedding), the step graph (teacher-forced
//! logits, greedy tokens over the full length) and the streaming decoder (chunk by chunk
//! vs PyTorch streaming and offline decoding). Tolerances come from parity/index.json.
//! Run with `--nocapture` to see the measured max abs differences.
mod bundle_support;

use std::sync::Arc;

use bundle_support::*;
use comgrasp::bundle::{N_STREAMS, STREAMS};
use comgrasp::model::StepState;
use comgrasp::{Bundle, BundleSource, Error, RuntimeOptions, StepBackend};

fn bundle() -> Arc<Bundle> {
    Bundle::load(&tiny_dir()).unwrap_or_else(|e| panic!("loading models/tiny: {e}"))
}

#[test]
fn text_encoder_matches_pytorch() {
    let b = bundle();
    let dir = tiny_dir();
    let index = parity_index(&dir);
    let cases: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("parity/text/cases.json")).unwrap()).unwrap();
    let t = b.manifest.text_encoder.max_tokens;
    let n_cases = cases["cases"].as_array().unwrap().len();
    assert!(n_cases >= 1);
    let (mut worst_emb, mut worst_states) = (0f64, 0f64);
    for (k, case) in cases["cases"].as_array().unwrap().iter().enumerate() {
        let prompt = case["prompt"].as_str().unwrap();
        let (tok, states) = b.text.token_states(prompt).unwrap();
        for (name, got) in [
            ("input_ids", &tok.input_ids),
            ("attention_mask", &tok.attention_mask),
            ("token_type_ids", &tok.token_type_ids),
        ] {
            let (_, want) = load_i64(&dir, &format!("parity/text/case{k}_{name}.npy"));
            assert_eq!(got, &want, "case {k} {name} for {prompt:?}");
        }
        let real = tok.attention_mask.iter().filter(|&&m| m == 1).count();
        assert_eq!(tok.truncated, real == t && prompt.split_whitespace().count() > t, "case {k} truncation flag");

        let rel = format!("parity/text/case{k}_{}.npy", b.manifest.text_encoder.pool_output);
        let (_, want_states) = load_f32(&dir, &rel);
        let w = b.manifest.text_encoder.dim;
        let mut d_states = 0f64;
        for (ti, &m) in tok.attention_mask.iter().enumerate() {
            if m == 1 {
                d_states =
                    d_states.max(max_abs_diff(&states[ti * w..(ti + 1) * w], &want_states[ti * w..(ti + 1) * w]));
            }
        }
        assert!(d_states <= tolerance(&index, &rel), "case {k}: token states differ by {d_states:e}");

        let rel = format!("parity/text/case{k}_embedding.npy");
        let (_, want) = load_f32(&dir, &rel);
        let got = b.text.embed(prompt).unwrap();
        let d = max_abs_diff(&got, &want);
        assert!(d <= tolerance(&index, &rel), "case {k} {prompt:?}: embedding differs by {d:e}");
        worst_emb = worst_emb.max(d);
        worst_states = worst_states.max(d_states);
        println!(
            "text case {k}: embedding max|diff| {d:.3e}, states (real tokens) {d_states:.3e}, truncated {}",
            tok.truncated
        );
    }
    println!("text: {n_cases} cases, worst embedding {worst_emb:.3e}, worst states {worst_states:.3e}");
}

#[test]
fn text_encoder_rejects_bad_text() {
    let b = bundle();
    assert!(matches!(b.text.embed(""), Err(Error::InvalidArgument(_))));
    assert!(matches!(b.text.embed("  \n\t "), Err(Error::InvalidArgument(_))));
    let long = "grasp the mug ".repeat(400);
    assert!(matches!(b.text.embed(&long), Err(Error::InvalidArgument(_))));
    // Long but under the byte limit: truncated, flagged, still an embedding.
    let e = b.text.encode(&"grasp the mug ".repeat(100)).unwrap();
    assert!(e.truncated);
    assert_eq!(e.embedding.len(), b.manifest.text_encoder.dim);
    let norm: f32 = e.embedding.iter().map(|v| v * v).sum::<f32>().sqrt();
    assert!((norm - 1.0).abs() < 1e-5);
}

struct StepCase {
    text_emb: Vec<f32>,
    logits: Vec<(Vec<usize>, Vec<f32>)>,
    tokens: Vec<[i64; N_STREAMS]>,
    greedy: Vec<[i64; N_STREAMS]>,
    files: serde_json::Value,
}

fn rows(v: (Vec<usize>, Vec<i64>)) -> Vec<[i64; N_STREAMS]> {
    assert_eq!(v.0.get(1), Some(&N_STREAMS));
    v.1.chunks_exact(N_STREAMS).map(|c| [c[0], c[1], c[2], c[3]]).collect()
}

fn step_cases() -> Vec<StepCase> {
    let dir = tiny_dir();
    let index = parity_index(&dir);
    index["step"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let f = &c["files"];
            let s = |k: &str| f[k].as_str().unwrap().to_string();
            StepCase {
                text_emb: load_f32(&dir, &s("text_emb")).1,
                logits: STREAMS.iter().map(|n| load_f32(&dir, &s(&format!("logits_{n}")))).collect(),
                tokens: rows(load_i64(&dir, &s("tokens"))),
                greedy: rows(load_i64(&dir, &s("greedy_tokens"))),
                files: f.clone(),
            }
        })
        .collect()
}

#[test]
fn step_logits_match_pytorch_teacher_forced() {
    let b = bundle();
    let index = parity_index(&tiny_dir());
    let pad = b.manifest.pad_ids();
    let mut state = b.step.new_state();
    for (ci, case) in step_cases().iter().enumerate() {
        state.reset().unwrap();
        let n = case.logits[0].0[0];
        let mut worst = [0f64; N_STREAMS];
        for pos in 0..n {
            let tokens = if pos == 0 { pad } else { case.tokens[pos - 1] };
            let got = b.step.step(&mut state, tokens, pos, &case.text_emb).unwrap();
            for s in 0..N_STREAMS {
                let (shape, want) = &case.logits[s];
                let v = shape[1];
                worst[s] = worst[s].max(max_abs_diff(got[s], &want[pos * v..(pos + 1) * v]));
            }
        }
        for s in 0..N_STREAMS {
            let rel = case.files[format!("logits_{}", STREAMS[s])].as_str().unwrap();
            let tol = tolerance(&index, rel);
            println!("step case {ci}: logits_{} max|diff| {:.3e} over {n} steps (tol {tol:e})", STREAMS[s], worst[s]);
            assert!(worst[s] <= tol, "step case {ci} stream {}: logits differ by {:e}", STREAMS[s], worst[s]);
        }
    }
}

/// Greedy decoding from `state` (reset first) over the whole sequence. Rule: Pad never,
/// End not before min_len and forced at max_len, arg max with the lowest id on ties.
fn greedy_run(b: &Bundle, state: &mut StepState, text_emb: &[f32]) -> Vec<[i64; N_STREAMS]> {
    let m = &b.manifest;
    let (end, pad) = (m.end_ids(), m.pad_ids());
    let (min_len, max_len) = (m.sampling.min_len, m.sampling.max_len);
    state.reset().unwrap();
    let mut tokens = pad;
    let mut out: Vec<[i64; N_STREAMS]> = Vec::new();
    for k in 0..=max_len {
        let logits = b.step.step(state, tokens, k, text_emb).unwrap();
        let mut next = [0i64; N_STREAMS];
        for s in 0..N_STREAMS {
            let allowed = |i: usize| {
                if k >= max_len {
                    i == end[s]
                } else {
                    i as i64 != pad[s] && !(k < min_len && i == end[s])
                }
            };
            let mut best: Option<(usize, f32)> = None;
            for (i, &x) in logits[s].iter().enumerate() {
                if allowed(i) && best.is_none_or(|(_, bx)| x > bx) {
                    best = Some((i, x));
                }
            }
            next[s] = best.unwrap().0 as i64;
        }
        if (0..N_STREAMS).any(|s| next[s] == end[s] as i64) {
            break;
        }
        out.push(next);
        tokens = next;
    }
    out
}

/// Greedy decoding through the tract step graph gives PyTorch's greedy tokens over the
/// whole sequence (every cache slot but the last is written).
#[test]
fn step_greedy_tokens_match_pytorch() {
    let b = bundle();
    let mut state = b.step.new_state();
    for (ci, case) in step_cases().iter().enumerate() {
        let out = greedy_run(&b, &mut state, &case.text_emb);
        println!("step case {ci}: greedy length {} (PyTorch {})", out.len(), case.greedy.len());
        assert_eq!(out, case.greedy, "step case {ci}: greedy tokens differ from PyTorch");
    }
}

/// Classifier-free guidance (DESIGN §4): greedy decoding from a guided state gives
/// PyTorch's guided greedy tokens over the whole sequence, on both step backends. A bundle
/// exported before guidance (COMGRASP_PARITY_BUNDLE=models/default) has no such cases;
/// models/tiny must.
#[test]
fn step_guided_greedy_tokens_match_pytorch() {
    let dir = tiny_dir();
    let index = parity_index(&dir);
    if index["step"].as_array().unwrap().iter().all(|c| c.get("guided").is_none()) {
        assert!(std::env::var_os("COMGRASP_PARITY_BUNDLE").is_some(), "models/tiny has no guided parity cases");
        println!("{}: no guided parity cases (exported before guidance)", dir.display());
        return;
    }
    for backend in [StepBackend::Tract, StepBackend::Native] {
        let opts = RuntimeOptions { step_backend: backend, ..RuntimeOptions::default() };
        let b = Bundle::load_with(BundleSource::dir(&dir), &opts).unwrap();
        assert_eq!(b.step.backend(), backend);
        for (ci, case) in step_cases().iter().enumerate() {
            let entry = &index["step"][ci];
            let scale = entry["guided"]["scale"].as_f64().unwrap();
            let want = rows(load_i64(&dir, entry["files"]["guided_greedy_tokens"].as_str().unwrap()));
            assert_eq!(want.len() as u64, entry["guided"]["length"].as_u64().unwrap());
            let mut state = b.step.new_guided_state(scale as f32);
            assert_eq!(state.guidance(), scale as f32);
            let out = greedy_run(&b, &mut state, &case.text_emb);
            println!("{backend:?} step case {ci}: guided greedy length {} (PyTorch {})", out.len(), want.len());
            assert_eq!(out, want, "{backend:?} step case {ci}: guided greedy tokens differ from PyTorch");
            let unguided = greedy_run(&b, &mut b.step.new_state(), &case.text_emb);
            assert_ne!(out, unguided, "step case {ci}: guidance {scale} changed nothing");
        }
    }
}

/// Guidance 0 is the null condition alone: the logits of a plain state fed a zero text
/// embedding, bit for bit; guidance 1 is a plain state.
#[test]
fn guidance_zero_is_the_null_condition_and_one_is_plain() {
    let b = bundle();
    let case = &step_cases()[0];
    let pad = b.manifest.pad_ids();
    let zeros = vec![0.0f32; case.text_emb.len()];
    let (mut guided, mut null) = (b.step.new_guided_state(0.0), b.step.new_state());
    assert_eq!(b.step.new_guided_state(1.0).guidance(), 1.0);
    let bits = |state: &mut StepState, tokens, pos, emb: &[f32]| -> Vec<Vec<u32>> {
        let logits = b.step.step(state, tokens, pos, emb).unwrap();
        logits.iter().map(|l| l.iter().map(|x| x.to_bits()).collect()).collect()
    };
    for pos in 0..4 {
        let tokens = if pos == 0 { pad } else { case.tokens[pos - 1] };
        assert_eq!(bits(&mut guided, tokens, pos, &case.text_emb), bits(&mut null, tokens, pos, &zeros), "step {pos}");
    }
}

#[test]
fn step_state_reuse_and_errors() {
    let b = bundle();
    let case = &step_cases()[0];
    let pad = b.manifest.pad_ids();
    let mut st = b.step.new_state();
    let first: Vec<Vec<f32>> =
        b.step.step(&mut st, pad, 0, &case.text_emb).unwrap().iter().map(|l| l.to_vec()).collect();
    b.step.step(&mut st, case.tokens[0], 1, &case.text_emb).unwrap();
    // Re-running position 0 from the same state, and from a reset state, gives the same logits.
    let again: Vec<Vec<f32>> =
        b.step.step(&mut st, pad, 0, &case.text_emb).unwrap().iter().map(|l| l.to_vec()).collect();
    assert_eq!(first, again);
    st.reset().unwrap();
    let reset: Vec<Vec<f32>> =
        b.step.step(&mut st, pad, 0, &case.text_emb).unwrap().iter().map(|l| l.to_vec()).collect();
    assert_eq!(first, reset);

    let slots = b.step.cache_slots();
    assert!(matches!(b.step.step(&mut st, pad, 5, &case.text_emb), Err(Error::WrongState(_))));
    assert!(matches!(b.step.step(&mut st, pad, slots, &case.text_emb), Err(Error::InvalidArgument(_))));
    assert!(matches!(b.step.step(&mut st, pad, 1, &case.text_emb[1..]), Err(Error::InvalidArgument(_))));
    let mut bad = case.text_emb.clone();
    bad[0] = f32::NAN;
    assert!(matches!(b.step.step(&mut st, pad, 1, &bad), Err(Error::InvalidArgument(_))));
    let vocab = b.manifest.vocab_sizes();
    assert!(matches!(
        b.step.step(&mut st, [vocab[0] as i64, 0, 0, 0], 1, &case.text_emb),
        Err(Error::InvalidArgument(_))
    ));
    assert!(matches!(b.step.step(&mut st, [0, -1, 0, 0], 1, &case.text_emb), Err(Error::InvalidArgument(_))));

    // A state belongs to the model that made it.
    let other = bundle();
    let mut foreign = other.step.new_state();
    assert!(matches!(b.step.step(&mut foreign, pad, 0, &case.text_emb), Err(Error::WrongState(_))));
}

#[test]
fn decoder_chunks_match_pytorch_stream_and_offline() {
    let b = bundle();
    let dir = tiny_dir();
    let index = parity_index(&dir);
    let dec = &index["decode"][0]["files"];
    let rel = |k: &str| dec[k].as_str().unwrap().to_string();
    let tokens = rows(load_i64(&dir, &rel("tokens")));
    let (shape, stream) = load_f32(&dir, &rel("frames_stream"));
    let (_, offline) = load_f32(&dir, &rel("frames_offline"));
    let (_, denorm) = load_f32(&dir, &rel("frames_denormalized"));
    let f = b.decoder.frames_per_token();
    assert_eq!(shape, vec![tokens.len() * f, 335]);

    let mut st = b.decoder.new_state();
    let mut all = Vec::new();
    let mut chunk = vec![0f32; b.decoder.chunk_len()];
    let mut worst_chunk = 0f64;
    for (i, t) in tokens.iter().enumerate() {
        b.decoder.decode(&mut st, *t, &mut chunk).unwrap();
        let n = chunk.len();
        worst_chunk = worst_chunk.max(max_abs_diff(&chunk, &stream[i * n..(i + 1) * n]));
        all.extend_from_slice(&chunk);
    }
    let d_stream = max_abs_diff(&all, &stream);
    let d_offline = max_abs_diff(&all, &offline);
    let norm = &b.manifest.normalization;
    let de: Vec<f32> = all
        .chunks_exact(335)
        .flat_map(|fr| fr.iter().enumerate().map(|(c, &x)| x * norm.std[c] + norm.mean[c]).collect::<Vec<_>>())
        .collect();
    let d_denorm = max_abs_diff(&de, &denorm);
    println!(
        "decoder: {} chunks, max|diff| vs PyTorch stream {d_stream:.3e}, vs offline {d_offline:.3e}, \
              denormalized {d_denorm:.3e}",
        tokens.len()
    );
    assert!(d_stream <= tolerance(&index, &rel("frames_stream")), "decoder vs stream: {d_stream:e}");
    assert!(d_offline <= tolerance(&index, &rel("frames_offline")), "decoder vs offline: {d_offline:e}");
    assert!(d_denorm <= tolerance(&index, &rel("frames_denormalized")), "denormalized: {d_denorm:e}");
    for fr in all.chunks_exact(335) {
        for c in [240, 334] {
            assert!((0.0..=1.0).contains(&fr[c]), "contact channel {c} is not a probability: {}", fr[c]);
        }
    }

    // Reset replays the same frames.
    st.reset().unwrap();
    b.decoder.decode(&mut st, tokens[0], &mut chunk).unwrap();
    assert_eq!(&chunk[..], &all[..chunk.len()]);
}

#[test]
fn decoder_rejects_bad_input() {
    let b = bundle();
    let mut st = b.decoder.new_state();
    let mut chunk = vec![0f32; b.decoder.chunk_len()];
    let books = b.manifest.codebook_sizes();
    assert!(matches!(
        b.decoder.decode(&mut st, [books[0] as i64, 0, 0, 0], &mut chunk),
        Err(Error::InvalidArgument(_))
    ));
    assert!(matches!(b.decoder.decode(&mut st, [0, 0, -3, 0], &mut chunk), Err(Error::InvalidArgument(_))));
    assert!(matches!(b.decoder.decode(&mut st, [0; 4], &mut chunk[1..]), Err(Error::InvalidArgument(_))));
    assert_eq!(st.decoded(), 0);
}

/// Load time and per-call cost on the tiny bundle (printed, never asserted).
#[test]
fn timing_report() {
    use std::time::Instant;
    let t0 = Instant::now();
    let b = bundle();
    let load = t0.elapsed();
    let case = &step_cases()[0];
    let t1 = Instant::now();
    let reps = 20;
    for _ in 0..reps {
        b.text.embed("A woman drinks from the mug.").unwrap();
    }
    let text = t1.elapsed() / reps;
    let mut st = b.step.new_state();
    let slots = b.step.cache_slots();
    let pad = b.manifest.pad_ids();
    let rounds = 10;
    let t2 = Instant::now();
    for _ in 0..rounds {
        st.reset().unwrap();
        for pos in 0..slots {
            b.step.step(&mut st, pad, pos, &case.text_emb).unwrap();
        }
    }
    let step = t2.elapsed() / (rounds * slots as u32);
    let mut ds = b.decoder.new_state();
    let mut chunk = vec![0f32; b.decoder.chunk_len()];
    let n = 50;
    let t3 = Instant::now();
    for _ in 0..n {
        b.decoder.decode(&mut ds, [0; 4], &mut chunk).unwrap();
    }
    let dec = t3.elapsed() / n;
    println!(
        "tiny bundle: load {:.1} ms, text embed {:.3} ms, step {:.3} ms, decode chunk {:.3} ms",
        load.as_secs_f64() * 1e3,
        text.as_secs_f64() * 1e3,
        step.as_secs_f64() * 1e3,
        dec.as_secs_f64() * 1e3
    );
}

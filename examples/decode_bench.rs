//! Decoder chunk cost, native vs tract, interleaved in one run (so machine load affects
//! both alike): `cargo run --release --example decode_bench -- <bundle> [chunks]`.
use std::time::Instant;

use comgrasp::bundle::N_STREAMS;
use comgrasp::model::{DecoderBackend, DecoderModel};
use comgrasp::Bundle;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    v[v.len() / 2]
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let dir = args.get(1).map(String::as_str).unwrap_or("models/default");
    let chunks: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(200);
    let with_tract = !args.iter().any(|a| a == "--native-only");
    let b = Bundle::load(std::path::Path::new(dir)).expect("bundle");
    let books = b.manifest.codebook_sizes();
    let tokens =
        |i: usize| -> [i64; N_STREAMS] { std::array::from_fn(|s| ((i * 7919 + s * 104_729) % books[s]) as i64) };
    let mut models =
        vec![("native", DecoderModel::load_backend(b.origin(), &b.manifest, Some(DecoderBackend::Native)).unwrap())];
    if with_tract {
        models
            .push(("tract", DecoderModel::load_backend(b.origin(), &b.manifest, Some(DecoderBackend::Tract)).unwrap()));
    }
    let mut states: Vec<_> = models.iter().map(|(_, m)| m.new_state()).collect();
    let mut out = vec![0f32; models[0].1.chunk_len()];
    let mut times = vec![Vec::new(); models.len()];
    for i in 0..chunks + 10 {
        for (k, (_, m)) in models.iter().enumerate() {
            let t = Instant::now();
            m.decode(&mut states[k], tokens(i), &mut out).unwrap();
            if i >= 10 {
                times[k].push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
    }
    for ((name, _), t) in models.iter().zip(times) {
        let min = t.iter().cloned().fold(f64::INFINITY, f64::min);
        println!("{name:>7}: median {:.3} ms, min {min:.3} ms (n = {chunks})", median(t));
    }
}

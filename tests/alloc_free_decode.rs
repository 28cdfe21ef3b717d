//! The native decoder's hot path allocates nothing: `DecoderModel::decode` (and `reset`)
//! work in the buffers `new_state` made. Counted by a global allocator in this test binary
//! only (tests/alloc_counter), on the bundle `COMGRASP_PARITY_BUNDLE` names (default
//! models/tiny), which must carry `decoder.native`.
mod alloc_counter;
mod bundle_support;

use alloc_counter::count_allocs;
use bundle_support::tiny_dir;
use comgrasp::bundle::N_STREAMS;
use comgrasp::config::RuntimeOptions;
use comgrasp::model::{DecoderBackend, DecoderModel};
use comgrasp::Bundle;

#[test]
fn native_decode_allocates_nothing_on_one_thread_or_two() {
    let dir = tiny_dir();
    let b = Bundle::load(&dir).unwrap_or_else(|e| panic!("loading {}: {e}", dir.display()));
    let books = b.manifest.codebook_sizes();
    let tokens =
        |i: usize| -> [i64; N_STREAMS] { std::array::from_fn(|s| ((i * 7919 + s * 104_729) % books[s]) as i64) };
    let chunks = 200;
    let mut frames = Vec::new();
    // 2: the helper-thread split even for a small model.
    for threads in [1, 2] {
        let options = RuntimeOptions {
            decoder_backend: Some(DecoderBackend::Native),
            decoder_threads: Some(threads),
            ..Default::default()
        };
        let model = DecoderModel::load(b.origin(), &b.manifest, &options)
            .unwrap_or_else(|e| panic!("{} needs decoder.native weights: {e}", dir.display()));
        let mut st = model.new_state();
        let mut out = vec![0f32; model.chunk_len()];
        let mut all = Vec::with_capacity(chunks * out.len());
        let (res, n) = count_allocs(|| {
            for i in 0..chunks {
                model.decode(&mut st, tokens(i), &mut out)?;
                all.extend_from_slice(&out); // within capacity
                if i == chunks / 2 {
                    st.reset()?;
                }
            }
            Ok::<(), comgrasp::Error>(())
        });
        res.unwrap();
        assert_eq!(
            n, 0,
            "{n} allocations in {chunks} native decode calls ({threads} threads, first chunk included) and a reset"
        );
        assert!(all.iter().all(|v| v.is_finite()));
        frames.push(all);
    }
    // The split changes who computes a component, not how: the same frames up to the
    // rounding of two separately loaded copies of the weights (the GEMV kernels align
    // their loads to where the allocator put each row, which moves the summation order).
    let worst = frames[0].iter().zip(&frames[1]).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
    assert!(worst <= 1e-5, "one thread and two threads decode differently: max|diff| {worst:e}");
}

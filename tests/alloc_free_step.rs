//! `StepModel::step` on the native path allocates nothing once its state exists: a counting
//! global allocator watches whole generations (every cache slot, resets, going back to an
//! earlier position) on models/tiny and models/default.
mod alloc_counter;
mod bundle_support;

use std::path::Path;

use alloc_counter::allocations_in;
use bundle_support::tiny_dir;
use comgrasp::bundle::{Bundle, BundleSource};
use comgrasp::model::{StepBackend, StepModel};

fn check(dir: &Path) {
    let b = Bundle::load(dir).unwrap_or_else(|e| panic!("loading {}: {e}", dir.display()));
    let step = StepModel::load_with(&BundleSource::dir(dir), &b.manifest, StepBackend::Native).unwrap();
    let emb = b.text.embed("pick up the mug").unwrap();
    let pad = b.manifest.pad_ids();
    let vocab = b.manifest.vocab_sizes();
    let slots = step.cache_slots();
    let mut st = step.new_state();
    // The first step, outside the count (nothing is lazily allocated, but the test only
    // promises "after the first").
    step.step(&mut st, pad, 0, &emb).unwrap();
    let mut checksum = 0f32;
    let n = allocations_in(|| {
        for round in 0..3 {
            st.reset().unwrap();
            let mut tokens = pad;
            for k in 0..slots {
                let logits = step.step(&mut st, tokens, k, &emb).unwrap();
                checksum += logits[0][0];
                tokens = std::array::from_fn(|s| ((k * 7 + s + round) % (vocab[s] - 2)) as i64);
            }
            // back to an earlier position and on from there
            for k in 3..10 {
                step.step(&mut st, tokens, k, &emb).unwrap();
            }
        }
    });
    assert!(checksum.is_finite());
    assert_eq!(n, 0, "{}: native step allocated {n} times over {} steps", dir.display(), 3 * (slots + 7));
}

#[test]
fn native_step_does_not_allocate() {
    // The counter works.
    assert!(allocations_in(|| drop(std::hint::black_box(Vec::<u8>::with_capacity(10)))) >= 1);
    check(&tiny_dir());
    check(&Path::new(env!("CARGO_MANIFEST_DIR")).join("models").join("default"));
}

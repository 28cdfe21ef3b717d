//! `StepModel::step` on the native path allocates nothing once its state exists: a counting
//! global allocator watches whole generations (every cache slot, resets, going back to an
//! earlier position) on models/tiny and models/default, on two threads
//! (`COMGRASP_STEP_THREADS=2`: the caller and the model's helper thread; on Linux the test
//! checks that the helper exists and ran) and on one.
mod alloc_counter;
mod bundle_support;

use std::path::Path;

use alloc_counter::{allocations_in, count_allocs_all_threads};
use bundle_support::tiny_dir;
use comgrasp::bundle::BundleSource;
use comgrasp::config::RuntimeOptions;
use comgrasp::model::{StepBackend, StepModel};
use comgrasp::Bundle;

/// Voluntary + involuntary context switches of this process's threads named `name`
/// (`None` where /proc is missing or no thread has that name).
fn switches_of(name: &str) -> Option<u64> {
    let mut total = None;
    for e in std::fs::read_dir("/proc/self/task").ok()?.flatten() {
        if std::fs::read_to_string(e.path().join("comm")).ok()?.trim() != name {
            continue;
        }
        let status = std::fs::read_to_string(e.path().join("status")).ok()?;
        let n: u64 = status
            .lines()
            .filter(|l| l.contains("ctxt_switches"))
            .filter_map(|l| l.split_whitespace().last()?.parse::<u64>().ok())
            .sum();
        total = Some(total.unwrap_or(0) + n);
    }
    total
}

fn check(dir: &Path, threads: &str) {
    let b = Bundle::load(dir).unwrap_or_else(|e| panic!("loading {}: {e}", dir.display()));
    let options = RuntimeOptions {
        step_backend: StepBackend::Native,
        step_threads: Some(threads.parse().unwrap()),
        ..Default::default()
    };
    let step = StepModel::load(&BundleSource::dir(dir), &b.manifest, &options).unwrap();
    let emb = b.text.embed("pick up the mug").unwrap();
    let pad = b.manifest.pad_ids();
    let vocab = b.manifest.vocab_sizes();
    let slots = step.cache_slots();
    let mut st = step.new_state();
    // The first step, outside the count (nothing is lazily allocated, but the test only
    // promises "after the first").
    step.step(&mut st, pad, 0, &emb).unwrap();
    let helper_before = switches_of("comgrasp-step");
    let mut checksum = 0f32;
    // Every thread's allocations (the helper's too): this is the binary's only test.
    let ((), n) = count_allocs_all_threads(|| {
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
    assert_eq!(
        n,
        0,
        "{}, {threads} thread(s): native step allocated {n} times over {} steps",
        dir.display(),
        3 * (slots + 7)
    );
    if threads == "2" && cfg!(target_os = "linux") {
        // The helper thread exists and was woken for the steps (it sleeps between them). On a
        // loaded machine the caller may finish a tiny model's steps before the woken helper
        // gets a core, so it is given a moment to show its switch.
        let before = helper_before.expect("no comgrasp-step thread");
        let t0 = std::time::Instant::now();
        let mut after = switches_of("comgrasp-step").unwrap();
        while after <= before && t0.elapsed() < std::time::Duration::from_secs(5) {
            std::thread::sleep(std::time::Duration::from_millis(10));
            after = switches_of("comgrasp-step").unwrap();
        }
        assert!(after > before, "{}: the step's helper thread did not run", dir.display());
    }
}

#[test]
fn native_step_does_not_allocate() {
    // The counters work, on this thread and on others.
    assert!(allocations_in(|| drop(std::hint::black_box(Vec::<u8>::with_capacity(10)))) >= 1);
    let ((), n) = count_allocs_all_threads(|| {
        std::thread::scope(|s| s.spawn(|| drop(std::hint::black_box(Vec::<u8>::with_capacity(10)))).join().unwrap());
    });
    assert!(n >= 1);
    for threads in ["2", "1"] {
        check(&tiny_dir(), threads);
        check(&Path::new(env!("CARGO_MANIFEST_DIR")).join("models").join("default"), threads);
    }
}

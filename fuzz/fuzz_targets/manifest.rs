//! The bundle manifest parser and its consistency checks on arbitrary bytes:
//! `verify::parse_manifest` (UTF-8, JSON, format/version, the version 1 schema), then for a
//! parsed manifest `verify::check_manifest` (every cross-field rule) and
//! `verify::check_files` against an empty in-memory file set (the files-table rules: safe
//! relative paths, hex digests; then "missing"). Asserted: no panic (an arithmetic overflow
//! or an out-of-bounds index on hostile numbers is a panic under cargo fuzz's debug
//! assertions), no abort on a huge allocation, and every failure is an `Error::Bundle`
//! naming manifest.json or a listed file.
#![no_main]

use std::path::Path;

use comgrasp::bundle::{verify, BundleSource};
use comgrasp::Error;
use libfuzzer_sys::fuzz_target;

static NO_FILES: &[(&str, &[u8])] = &[];

fn check(r: comgrasp::Result<()>) {
    match r {
        Ok(()) => {}
        Err(Error::Bundle { path, msg }) => assert!(!msg.is_empty() && !path.as_os_str().is_empty()),
        Err(other) => panic!("not an Error::Bundle: {other:?}"),
    }
}

fuzz_target!(|data: &[u8]| {
    let path = Path::new("<fuzz>/manifest.json");
    let m = match verify::parse_manifest(path, data) {
        Ok(m) => m,
        Err(Error::Bundle { path: p, .. }) => {
            assert_eq!(p, path);
            return;
        }
        Err(other) => panic!("not an Error::Bundle: {other:?}"),
    };
    let src = BundleSource::memory(NO_FILES);
    let consistent = verify::check_manifest(&src, &m);
    let ok = consistent.is_ok();
    check(consistent);
    if ok {
        // Only meaningful on a consistent manifest (the loader's order).
        check(verify::check_files(&src, &m));
        let _ = (m.codebook_sizes(), m.vocab_sizes(), m.end_ids(), m.pad_ids());
    }
    let _ = m.find_object("mug");
});

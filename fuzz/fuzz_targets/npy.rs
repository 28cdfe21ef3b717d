//! The `.npy` reader (the bundle's parity vectors, also read by `check_parity_index` at
//! load time) on arbitrary bytes: header parsing, size arithmetic, every conversion.
//! Asserted: no panic, every failure an `Error::Bundle`, and a parsed array's conversions
//! give exactly `len()` values.
#![no_main]

use std::path::Path;

use comgrasp::bundle::npy;
use comgrasp::Error;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = Path::new("<fuzz>/x.npy");
    match npy::parse_header(path, data) {
        Ok(h) => assert!(h.data_offset <= data.len()),
        Err(Error::Bundle { .. }) => {}
        Err(other) => panic!("not an Error::Bundle: {other:?}"),
    }
    match npy::parse(path, data.to_vec()) {
        Ok(a) => {
            let n = a.len();
            assert_eq!(a.to_f64().len(), n);
            if let Ok(v) = a.to_f32(path) {
                assert_eq!(v.len(), n);
            }
            if let Ok(v) = a.to_i64(path) {
                assert_eq!(v.len(), n);
            }
            if let Ok(v) = a.to_u64(path) {
                assert_eq!(v.len(), n);
            }
        }
        Err(Error::Bundle { .. }) => {}
        Err(other) => panic!("not an Error::Bundle: {other:?}"),
    }
});

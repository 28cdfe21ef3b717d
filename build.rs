//! Generates the C header with cbindgen. The header is always written to `$OUT_DIR` (the
//! `header_is_current` test compares it with the committed `include/comgrasp.h`); outside CI
//! it is also written to `include/comgrasp.h`, so a developer's build keeps it current and CI
//! catches a header that was not committed.
//!
//! With feature `embedded-default` it also embeds `models/default` (see `build/embed.rs`),
//! and it writes the pkg-config file and CMake package next to the libraries in
//! `target/<profile>/` (see `build/packaging.rs`).
use std::{env, fs, path::PathBuf};

#[path = "build/embed.rs"]
mod embed;
#[path = "build/packaging.rs"]
mod packaging;

fn main() {
    let crate_dir = PathBuf::from(env::var("CARGO_MANIFEST_DIR").unwrap());
    let out_dir = PathBuf::from(env::var("OUT_DIR").unwrap());
    embed::generate(&crate_dir, &out_dir);
    packaging::generate(&crate_dir, &out_dir);
    let out = out_dir.join("comgrasp.h");
    println!("cargo:rerun-if-changed=src");
    println!("cargo:rerun-if-changed=cbindgen.toml");
    println!("cargo:rerun-if-env-changed=CI");
    let config = cbindgen::Config::from_file(crate_dir.join("cbindgen.toml")).expect("cbindgen.toml");
    match cbindgen::Builder::new().with_crate(&crate_dir).with_config(config).generate() {
        Ok(bindings) => {
            bindings.write_to_file(&out);
            if env::var_os("CI").is_none() {
                let committed = crate_dir.join("include").join("comgrasp.h");
                let new = fs::read(&out).unwrap();
                if fs::read(&committed).ok().as_deref() != Some(&new[..]) {
                    fs::create_dir_all(committed.parent().unwrap()).unwrap();
                    fs::write(&committed, new).unwrap();
                }
            }
        }
        // A syntax error is reported by rustc itself with a better message.
        Err(e) => println!("cargo:warning=cbindgen: {e}"),
    }
}

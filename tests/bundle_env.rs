//! Bundle selection with no path (`bundle::select`): `COMGRASP_BUNDLE`, then the embedded
//! default, then a clear error; an explicit path always wins. The environment is
//! process-global, so these tests live in their own binary and take a lock around every
//! change to it.
mod bundle_support;

use std::ffi::CStr;
use std::path::Path;
use std::ptr::null_mut;

use bundle_support::tiny_dir;
use comgrasp::bundle::select::BUNDLE_ENV;
use comgrasp::ffi::*;
use comgrasp::{Engine, EngineConfig, Error};
use parking_lot::{Mutex, MutexGuard};

static ENV: Mutex<()> = Mutex::new(());

/// Holds the lock with `COMGRASP_BUNDLE` set to `value` (or unset); unsets it on drop.
struct EnvGuard(#[allow(dead_code)] MutexGuard<'static, ()>);

fn with_env(value: Option<&str>) -> EnvGuard {
    let guard = ENV.lock();
    match value {
        Some(v) => std::env::set_var(BUNDLE_ENV, v),
        None => std::env::remove_var(BUNDLE_ENV),
    }
    EnvGuard(guard)
}

impl Drop for EnvGuard {
    fn drop(&mut self) {
        std::env::remove_var(BUNDLE_ENV);
    }
}

fn bundle_error(config: EngineConfig) -> (std::path::PathBuf, String) {
    match Engine::new(config) {
        Ok(_) => panic!("engine creation succeeded, expected a bundle error"),
        Err(Error::Bundle { path, msg }) => (path, msg),
        Err(e) => panic!("expected Error::Bundle, got {e:?}"),
    }
}

#[test]
fn env_var_selects_a_directory() {
    let tiny = tiny_dir();
    let _env = with_env(Some(tiny.to_str().unwrap()));
    let e = Engine::new(EngineConfig::default()).unwrap_or_else(|e| panic!("{e}"));
    let origin = e.bundle().unwrap().origin();
    assert_eq!(origin.directory(), Some(tiny.as_path()), "loaded {origin}");
    assert!(!origin.is_embedded());
}

#[test]
fn env_var_naming_a_missing_directory_is_an_error_not_a_fallback() {
    let missing = "/nonexistent/comgrasp-bundle";
    let _env = with_env(Some(missing));
    let (path, msg) = bundle_error(EngineConfig::default());
    assert_eq!(path, Path::new(missing));
    assert!(msg.contains("not a directory") && msg.contains(BUNDLE_ENV), "{msg}");

    // The same through the C ABI, with the message as the last error.
    let mut cfg = cg_engine_config::default();
    let mut out: *mut cg_engine = null_mut();
    unsafe {
        assert_eq!(cg_engine_config_init_sized(&mut cfg, std::mem::size_of::<cg_engine_config>()), cg_status::CG_OK);
        assert_eq!(cg_engine_create(&cfg, &mut out), cg_status::CG_ERR_BUNDLE);
        assert!(out.is_null());
        let last = CStr::from_ptr(cg_last_error()).to_string_lossy().into_owned();
        assert!(last.contains(missing) && last.contains(BUNDLE_ENV), "{last}");
    }
}

#[test]
fn env_var_set_but_empty_is_an_error() {
    let _env = with_env(Some(""));
    let (path, msg) = bundle_error(EngineConfig::default());
    assert_eq!(path, Path::new(""));
    assert!(msg.contains(BUNDLE_ENV) && msg.contains("set but empty"), "{msg}");
}

#[test]
fn explicit_path_wins_over_the_env_var() {
    let _env = with_env(Some("/nonexistent/comgrasp-bundle"));
    let tiny = tiny_dir();
    let e = Engine::new(EngineConfig { bundle_path: Some(tiny.clone()), ..Default::default() }).unwrap();
    assert_eq!(e.bundle().unwrap().origin().directory(), Some(tiny.as_path()));
}

#[cfg(feature = "embedded-default")]
#[test]
fn unset_env_var_means_the_embedded_bundle() {
    let _env = with_env(None);
    let e = Engine::new(EngineConfig::default()).unwrap_or_else(|e| panic!("{e}"));
    assert!(e.bundle().unwrap().origin().is_embedded());
}

#[cfg(not(feature = "embedded-default"))]
#[test]
fn without_the_feature_no_path_is_a_clear_error() {
    let _env = with_env(None);
    assert!(comgrasp::bundle::BundleSource::embedded().is_none());
    let (path, msg) = bundle_error(EngineConfig::default());
    assert_eq!(path, Path::new(""));
    assert!(msg.contains("no bundle_path given") && msg.contains("embedded-default"), "{msg}");
    let shown = Error::Bundle { path, msg }.to_string();
    assert!(shown.starts_with("bundle: no bundle_path given"), "{shown}");
}

//! The committed C header must equal the one build.rs generates from the current source.
//! Outside CI, build.rs refreshes `include/comgrasp.h` itself, so this fails only when the
//! refreshed header was not committed (CI sets `CI`, and build.rs then leaves it alone).

const GENERATED: &str = include_str!(concat!(env!("OUT_DIR"), "/comgrasp.h"));

#[test]
fn header_is_current() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/include/comgrasp.h");
    let committed = std::fs::read_to_string(path).unwrap_or_default();
    assert!(
        committed == GENERATED,
        "include/comgrasp.h is stale: build outside CI (cargo build) to regenerate it, then commit it"
    );
}

#[test]
fn header_declares_and_documents_every_function() {
    for f in [
        "cg_abi_version",
        "cg_version_string",
        "cg_frame_size",
        "cg_status_string",
        "cg_last_error",
        "cg_last_error_message",
        "cg_last_error_status",
        "cg_engine_config_init",
        "cg_engine_config_init_sized",
        "cg_stream_config_init",
        "cg_engine_create",
        "cg_engine_destroy",
        "cg_engine_stream_count",
        "cg_start",
        "cg_start_utf8",
        "cg_poll_frame",
        "cg_stream_wait",
        "cg_cancel",
        "cg_stream_destroy",
        "cg_stream_id",
    ] {
        let at = [format!(" {f}("), format!("*{f}(")]
            .iter()
            .find_map(|d| GENERATED.find(d.as_str()))
            .unwrap_or_else(|| panic!("{f} missing from the header"));
        // The line before the declaration must be a doc comment line.
        let before = GENERATED[..at].trim_end_matches(|c| c != '\n').trim_end();
        let last_line = before.lines().last().unwrap_or("");
        let prev_line = before.lines().rev().nth(1).unwrap_or("");
        assert!(
            last_line.trim_start().starts_with("//") || prev_line.trim_start().starts_with("//"),
            "{f} has no doc comment in the header"
        );
    }
    for s in ["CG_OK", "CG_PENDING", "CG_END", "CG_CANCELLED", "CG_ERR_INVALID_HANDLE", "CG_ERR_PANIC"] {
        assert!(GENERATED.contains(s), "{s} missing from the header");
    }
}

#[test]
fn header_exports_only_the_c_api_namespace() {
    // Internal constants leaking into a host's namespace (e.g. `VERSION`) would clash.
    for line in GENERATED.lines() {
        let l = line.trim_start();
        let name = if let Some(rest) = l.strip_prefix("#define ") {
            rest.split_whitespace().next()
        } else if let Some(rest) = l.strip_prefix("typedef ") {
            rest.trim_end_matches(['{', ';', ' ']).split_whitespace().last().map(|n| n.trim_start_matches('*'))
        } else {
            None
        };
        if let Some(n) = name {
            let n = n.split('[').next().unwrap_or(n);
            assert!(
                n == "COMGRASP_H" || n.starts_with("cg_") || n.starts_with("CG_"),
                "non-API name `{n}` exported in the header: add it to cbindgen.toml's exclude list"
            );
        }
    }
}

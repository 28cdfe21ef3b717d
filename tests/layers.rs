//! The crate's floors (src/lib.rs): every `crate::<module>` path in a module's files names
//! a module on a lower floor, or the module itself. Reads the sources, so a new upward
//! import fails here before it becomes a cycle.
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// Bottom up; a module may use those before it.
const FLOORS: [&str; 19] = [
    "error",
    "frame",
    "config",
    "bundle",
    "sampler",
    "skeleton",
    "assemble",
    "feet",
    "contact",
    "anchor",
    "retarget",
    "bvh",
    "model",
    "generator",
    "stream",
    "crowd",
    "shm",
    "engine",
    "ffi",
];

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The `crate::<name>` roots a file refers to, comments left out.
fn crate_refs(text: &str) -> BTreeSet<String> {
    let mut refs = BTreeSet::new();
    for line in text.lines() {
        let code = line.split("//").next().unwrap();
        let mut rest = code;
        while let Some(i) = rest.find("crate::") {
            let after = &rest[i + "crate::".len()..];
            let name: String = after.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
            // `crate::{a, b}` groups: every name inside.
            if name.is_empty() && after.starts_with('{') {
                let group = &after[1..after.find('}').unwrap_or(after.len())];
                refs.extend(group.split(',').map(|n| n.trim().split("::").next().unwrap().to_string()));
            } else {
                refs.insert(name);
            }
            rest = after;
        }
    }
    refs
}

#[test]
fn no_module_imports_from_a_floor_above_its_own() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut violations = Vec::new();
    let mut seen = BTreeSet::new();
    for f in &files {
        let rel = f.strip_prefix(&src).unwrap();
        let first = rel.components().next().unwrap().as_os_str().to_str().unwrap();
        if rel == Path::new("lib.rs") {
            continue; // the root re-exports
        }
        let module = first.trim_end_matches(".rs");
        let floor = FLOORS.iter().position(|m| *m == module).unwrap_or_else(|| {
            panic!("src/{} belongs to module {module}, which has no floor in FLOORS", rel.display())
        });
        seen.insert(module.to_string());
        for r in crate_refs(&std::fs::read_to_string(f).unwrap()) {
            if r.is_empty() || r == module {
                continue;
            }
            // The root's re-exports of the error types (`crate::Result`) are the error floor;
            // any other root item would hide its floor, so it must be named by its module.
            let r = if r == "Error" || r == "Result" { "error".to_string() } else { r };
            match FLOORS.iter().position(|m| *m == r) {
                Some(to) if to < floor => {}
                Some(_) => violations.push(format!("src/{} ({module}) uses crate::{r}", rel.display())),
                None => violations.push(format!("src/{} uses crate::{r}, which has no floor", rel.display())),
            }
        }
    }
    assert!(violations.is_empty(), "imports from a floor above:\n{}", violations.join("\n"));
    assert_eq!(seen.len(), FLOORS.len(), "a floor without files: {seen:?}");
}

#[test]
fn the_reader_sees_grouped_and_nested_paths() {
    let refs = crate_refs("use crate::{engine::Engine, frame};\nlet x = crate::model::text::f(); // crate::ffi");
    assert_eq!(refs, ["engine", "frame", "model"].iter().map(|s| s.to_string()).collect());
}

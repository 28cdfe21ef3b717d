//! Packaging files for native hosts, written next to `libcomgrasp.{so,a}` in the profile
//! folder (`target/<profile>/`, found as `$OUT_DIR/../../..`):
//!
//! * `comgrasp.pc`: pkg-config (`PKG_CONFIG_PATH=target/release pkg-config --cflags --libs comgrasp`);
//! * `comgrasp-config.cmake` + `comgrasp-config-version.cmake`: a CMake package
//!   (`cmake -DCMAKE_PREFIX_PATH=target/release`, then `find_package(comgrasp CONFIG REQUIRED)`),
//!   imported targets `comgrasp::comgrasp` (shared) and `comgrasp::comgrasp_static`.
//!
//! They work in place: the libraries are found relative to the files themselves
//! (`${pcfiledir}`, `${CMAKE_CURRENT_LIST_DIR}`), the headers by absolute path in this source
//! tree (`include/comgrasp.h`, and `bindings/cpp/comgrasp.hpp` for C++). `scripts/install.sh`
//! copies everything into a prefix and rewrites exactly the lines marked here as "install.sh
//! rewrites", so keep those lines' shape when editing the templates.
//!
//! Only Linux and macOS targets get the files (the libraries' names and the static
//! library's system dependencies are per platform); other targets get none.
use std::path::{Path, PathBuf};
use std::{env, fs};

/// The static library's system link dependencies, as `cargo rustc --lib --crate-type
/// staticlib -- --print native-static-libs` prints them ("-l" dropped). All of them come
/// from std: every dependency of this crate links its C parts statically (onig, tract's
/// kernels). Re-check with that command after adding a dependency with a native library.
fn native_static_libs(os: &str, target_env: &str) -> Option<&'static [&'static str]> {
    match (os, target_env) {
        ("linux", "musl") => Some(&["c"]),
        ("linux", _) => Some(&["gcc_s", "util", "rt", "pthread", "m", "dl", "c"]),
        // Not verified in CI (no macOS runner): what rustc prints for std there.
        ("macos", _) => Some(&["System", "c", "m"]),
        _ => None,
    }
}

/// Linker options for a program linking the static library. GNU ld: tract's assembly
/// kernels carry no `.note.GNU-stack`, so without `-z noexecstack` the program would get an
/// executable stack (and a linker warning); the shared library is linked with it by rustc.
fn static_link_options(os: &str) -> &'static [&'static str] {
    if os == "linux" {
        &["-z", "noexecstack"]
    } else {
        &[]
    }
}

pub fn generate(crate_dir: &Path, out_dir: &Path) {
    let os = env::var("CARGO_CFG_TARGET_OS").unwrap_or_default();
    let target_env = env::var("CARGO_CFG_TARGET_ENV").unwrap_or_default();
    let Some(static_libs) = native_static_libs(&os, &target_env) else { return };
    let link_opts = static_link_options(&os);
    let shared = if os == "macos" { "libcomgrasp.dylib" } else { "libcomgrasp.so" };
    let Some(profile_dir) = profile_dir(out_dir) else {
        println!(
            "cargo:warning=packaging: {} is not <target>/<profile>/build/<pkg>/out; comgrasp.pc and the CMake package are not written",
            out_dir.display()
        );
        return;
    };
    let version = env::var("CARGO_PKG_VERSION").unwrap();
    let abi = abi_version(crate_dir);
    let include = crate_dir.join("include");
    let cpp_include = crate_dir.join("bindings").join("cpp");

    write_if_changed(&profile_dir.join("comgrasp.pc"), &pc_file(&version, abi, crate_dir, static_libs, link_opts));
    write_if_changed(
        &profile_dir.join("comgrasp-config.cmake"),
        &cmake_config(&version, abi, shared, &include, &cpp_include, static_libs, link_opts),
    );
    write_if_changed(&profile_dir.join("comgrasp-config-version.cmake"), &cmake_version(&version));
}

/// `target/<profile>` from `target/<profile>/build/comgrasp-<hash>/out`, checking the shape
/// (a custom `build-dir` puts `OUT_DIR` elsewhere; then nothing is written).
fn profile_dir(out_dir: &Path) -> Option<PathBuf> {
    let build = out_dir.parent()?.parent()?;
    (build.file_name()? == "build").then(|| build.parent().map(Path::to_path_buf)).flatten()
}

/// `CG_ABI_VERSION` from src/ffi (the header is generated from it after this runs).
fn abi_version(crate_dir: &Path) -> u32 {
    let dir = crate_dir.join("src").join("ffi");
    let mut files: Vec<PathBuf> =
        fs::read_dir(&dir).map(|d| d.flatten().map(|e| e.path()).collect()).unwrap_or_default();
    files.sort();
    for f in files {
        let Ok(text) = fs::read_to_string(&f) else { continue };
        for line in text.lines() {
            if let Some(rest) = line.trim().strip_prefix("pub const CG_ABI_VERSION: u32 = ") {
                if let Ok(v) = rest.trim_end_matches(';').trim().parse() {
                    return v;
                }
            }
        }
    }
    panic!("packaging: `pub const CG_ABI_VERSION: u32 = N;` not found in {}", dir.display());
}

fn utf8(p: &Path) -> &str {
    p.to_str().unwrap_or_else(|| panic!("packaging: {} is not a UTF-8 path", p.display()))
}

/// A pkg-config value: spaces escaped (pkg-config splits on them).
fn pc_path(p: &Path) -> String {
    utf8(p).replace('\\', "\\\\").replace(' ', "\\ ")
}

/// A quoted CMake string literal.
fn cmake_str(p: &Path) -> String {
    format!("\"{}\"", utf8(p).replace('\\', "\\\\").replace('"', "\\\"").replace('$', "\\$").replace(';', "\\;"))
}

fn pc_file(version: &str, abi: u32, crate_dir: &Path, static_libs: &[&str], link_opts: &[&str]) -> String {
    let mut private: Vec<String> = static_libs.iter().map(|l| format!("-l{l}")).collect();
    if !link_opts.is_empty() {
        private.push(format!("-Wl,{}", link_opts.join(",")));
    }
    format!(
        "# comgrasp.pc: generated by build/packaging.rs (cargo build); do not edit.\n\
         # In place, libdir is this file's folder (target/<profile>/) and the headers are in the\n\
         # source tree (prefix); scripts/install.sh rewrites the prefix, libdir and cppincludedir lines.\n\
         # Static linking: `pkg-config --static --libs comgrasp` adds the system libraries, and\n\
         # `pkg-config --variable=staticlib comgrasp` is the archive's path.\n\
         prefix={prefix}\n\
         libdir=${{pcfiledir}}\n\
         includedir=${{prefix}}/include\n\
         cppincludedir=${{prefix}}/bindings/cpp\n\
         staticlib=${{libdir}}/libcomgrasp.a\n\
         abi_version={abi}\n\
         \n\
         Name: comgrasp\n\
         Description: ComGrasp Engine: real-time streaming text-to-grasp motion (C ABI; C++ wrapper comgrasp.hpp)\n\
         Version: {version}\n\
         Libs: -L${{libdir}} -lcomgrasp\n\
         Libs.private: {private}\n\
         Cflags: -I${{includedir}} -I${{cppincludedir}}\n",
        prefix = pc_path(crate_dir),
        private = private.join(" "),
    )
}

fn cmake_config(
    version: &str,
    abi: u32,
    shared: &str,
    include: &Path,
    cpp_include: &Path,
    static_libs: &[&str],
    link_opts: &[&str],
) -> String {
    let link_opts = if link_opts.is_empty() { String::new() } else { format!("LINKER:{}", link_opts.join(",")) };
    format!(
        r#"# comgrasp-config.cmake: generated by build/packaging.rs (cargo build); do not edit.
#
#   find_package(comgrasp CONFIG REQUIRED)   # -DCMAKE_PREFIX_PATH=/path/to/target/release
#   target_link_libraries(app PRIVATE comgrasp::comgrasp)          # libcomgrasp shared
#   target_link_libraries(app PRIVATE comgrasp::comgrasp_static)   # libcomgrasp.a + system libs
#
# Both targets carry the include directories of comgrasp.h (C) and comgrasp.hpp (C++17
# wrapper). Also sets comgrasp_VERSION, comgrasp_ABI_VERSION (CG_ABI_VERSION of the header),
# comgrasp_INCLUDE_DIRS, comgrasp_LIBRARY and comgrasp_STATIC_LIBRARY.
if(CMAKE_VERSION VERSION_LESS 3.13)
  message(FATAL_ERROR "comgrasp's CMake package needs CMake 3.13 or newer")
endif()
cmake_policy(PUSH)
cmake_policy(VERSION 3.13...3.28)

# In place the libraries sit next to this file (target/<profile>/) and the headers in the
# source tree. scripts/install.sh rewrites these two lines (keep each on one line).
set(_comgrasp_libdir "${{CMAKE_CURRENT_LIST_DIR}}")
set(_comgrasp_include_dirs {include} {cpp})

get_filename_component(_comgrasp_libdir "${{_comgrasp_libdir}}" ABSOLUTE)
set(comgrasp_INCLUDE_DIRS "")
foreach(_comgrasp_dir IN LISTS _comgrasp_include_dirs)
  get_filename_component(_comgrasp_dir "${{_comgrasp_dir}}" ABSOLUTE)
  list(APPEND comgrasp_INCLUDE_DIRS "${{_comgrasp_dir}}")
endforeach()
set(comgrasp_LIBRARY "${{_comgrasp_libdir}}/{shared}")
set(comgrasp_STATIC_LIBRARY "${{_comgrasp_libdir}}/libcomgrasp.a")
set(comgrasp_ABI_VERSION {abi})

set(_comgrasp_missing "")
foreach(_comgrasp_file "${{comgrasp_LIBRARY}}" "${{comgrasp_STATIC_LIBRARY}}")
  if(NOT EXISTS "${{_comgrasp_file}}")
    list(APPEND _comgrasp_missing "${{_comgrasp_file}}")
  endif()
endforeach()
list(GET comgrasp_INCLUDE_DIRS 0 _comgrasp_dir)
if(NOT EXISTS "${{_comgrasp_dir}}/comgrasp.h")
  list(APPEND _comgrasp_missing "${{_comgrasp_dir}}/comgrasp.h")
endif()

if(_comgrasp_missing)
  set(comgrasp_FOUND FALSE)
  set(comgrasp_NOT_FOUND_MESSAGE "comgrasp {version}: missing ${{_comgrasp_missing}} (run `cargo build --release` in the comgrasp source tree)")
else()
  if(NOT TARGET comgrasp::comgrasp)
    add_library(comgrasp::comgrasp SHARED IMPORTED)
    set_target_properties(comgrasp::comgrasp PROPERTIES
      IMPORTED_LOCATION "${{comgrasp_LIBRARY}}"
      # Rust's cdylib has no soname: link with -L/-l so the binary records "libcomgrasp.so".
      IMPORTED_NO_SONAME TRUE
      INTERFACE_INCLUDE_DIRECTORIES "${{comgrasp_INCLUDE_DIRS}}")
  endif()
  if(NOT TARGET comgrasp::comgrasp_static)
    add_library(comgrasp::comgrasp_static STATIC IMPORTED)
    set_target_properties(comgrasp::comgrasp_static PROPERTIES
      IMPORTED_LOCATION "${{comgrasp_STATIC_LIBRARY}}"
      IMPORTED_LINK_INTERFACE_LANGUAGES "C"
      INTERFACE_INCLUDE_DIRECTORIES "${{comgrasp_INCLUDE_DIRS}}"
      # cargo rustc --lib --crate-type staticlib -- --print native-static-libs
      INTERFACE_LINK_LIBRARIES "{static_libs}"
      # tract's assembly kernels lack .note.GNU-stack: keep the program's stack non-executable.
      INTERFACE_LINK_OPTIONS "{link_opts}")
  endif()
  set(comgrasp_FOUND TRUE)
endif()

unset(_comgrasp_file)
unset(_comgrasp_dir)
unset(_comgrasp_missing)
unset(_comgrasp_libdir)
unset(_comgrasp_include_dirs)
cmake_policy(POP)
"#,
        include = cmake_str(include),
        cpp = cmake_str(cpp_include),
        static_libs = static_libs.join(";"),
    )
}

/// Compatible when the requested version is not newer and has the same major version
/// (the same major.minor while the major version is 0, as in semver); 64-bit only.
fn cmake_version(version: &str) -> String {
    format!(
        r#"# comgrasp-config-version.cmake: generated by build/packaging.rs (cargo build); do not edit.
set(PACKAGE_VERSION "{version}")
if(PACKAGE_FIND_VERSION_RANGE)
  if((PACKAGE_FIND_VERSION_RANGE_MIN STREQUAL "INCLUDE" AND PACKAGE_VERSION VERSION_LESS PACKAGE_FIND_VERSION_MIN)
     OR (PACKAGE_FIND_VERSION_RANGE_MIN STREQUAL "EXCLUDE" AND PACKAGE_VERSION VERSION_LESS_EQUAL PACKAGE_FIND_VERSION_MIN)
     OR (PACKAGE_FIND_VERSION_RANGE_MAX STREQUAL "INCLUDE" AND PACKAGE_VERSION VERSION_GREATER PACKAGE_FIND_VERSION_MAX)
     OR (PACKAGE_FIND_VERSION_RANGE_MAX STREQUAL "EXCLUDE" AND PACKAGE_VERSION VERSION_GREATER_EQUAL PACKAGE_FIND_VERSION_MAX))
    set(PACKAGE_VERSION_COMPATIBLE FALSE)
  else()
    set(PACKAGE_VERSION_COMPATIBLE TRUE)
  endif()
elseif(PACKAGE_FIND_VERSION)
  string(REGEX MATCH "^([0-9]+)\\.([0-9]+)" _comgrasp_mm "${{PACKAGE_VERSION}}")
  set(_comgrasp_major "${{CMAKE_MATCH_1}}")
  set(_comgrasp_minor "${{CMAKE_MATCH_2}}")
  if(PACKAGE_FIND_VERSION VERSION_GREATER PACKAGE_VERSION
     OR NOT PACKAGE_FIND_VERSION_MAJOR STREQUAL _comgrasp_major
     OR (_comgrasp_major STREQUAL "0" AND NOT PACKAGE_FIND_VERSION_MINOR STREQUAL _comgrasp_minor))
    set(PACKAGE_VERSION_COMPATIBLE FALSE)
  else()
    set(PACKAGE_VERSION_COMPATIBLE TRUE)
    if(PACKAGE_FIND_VERSION STREQUAL PACKAGE_VERSION)
      set(PACKAGE_VERSION_EXACT TRUE)
    endif()
  endif()
  unset(_comgrasp_mm)
  unset(_comgrasp_major)
  unset(_comgrasp_minor)
else()
  set(PACKAGE_VERSION_COMPATIBLE TRUE)
endif()
# The library is built for one architecture: refuse a project of another pointer size.
if(CMAKE_SIZEOF_VOID_P AND NOT CMAKE_SIZEOF_VOID_P STREQUAL "{ptr}")
  math(EXPR _comgrasp_bits "{ptr} * 8")
  set(PACKAGE_VERSION "${{PACKAGE_VERSION}} (${{_comgrasp_bits}}-bit)")
  set(PACKAGE_VERSION_UNSUITABLE TRUE)
  unset(_comgrasp_bits)
endif()
"#,
        ptr = env::var("CARGO_CFG_TARGET_POINTER_WIDTH").ok().and_then(|w| w.parse::<u32>().ok()).unwrap_or(64) / 8,
    )
}

/// Writes only when the content differs, so the files' times mean something.
fn write_if_changed(path: &Path, content: &str) {
    if fs::read_to_string(path).ok().as_deref() != Some(content) {
        if let Err(e) = fs::write(path, content) {
            println!("cargo:warning=packaging: cannot write {}: {e}", path.display());
        }
    }
}

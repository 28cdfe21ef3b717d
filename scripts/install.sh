#!/usr/bin/env bash
# Installs the built library for native hosts into a conventional prefix layout:
#   PREFIX/lib/libcomgrasp.so (.dylib on macOS) and libcomgrasp.a
#   PREFIX/include/comgrasp.h and comgrasp.hpp (the C++17 wrapper)
#   PREFIX/lib/pkgconfig/comgrasp.pc
#   PREFIX/lib/cmake/comgrasp/comgrasp-config.cmake and comgrasp-config-version.cmake
#   PREFIX/share/comgrasp/valgrind.supp (a host's own valgrind run needs it: tract and rayon
#     trip two known false positives, each explained in the file)
#
#   cargo build --release && scripts/install.sh /usr/local      [PROFILE_DIR]
#
# PROFILE_DIR is the cargo output folder holding the libraries and the packaging files that
# build/packaging.rs generates (default: $CARGO_TARGET_DIR/release, else target/release).
# The copies get their paths rewritten for PREFIX: comgrasp.pc names PREFIX, the CMake
# package is relocatable (paths relative to its own folder).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
if [ $# -lt 1 ] || [ $# -gt 2 ] || [ -z "$1" ]; then
  echo "usage: $0 PREFIX [PROFILE_DIR]" >&2
  exit 2
fi
src=${2:-${CARGO_TARGET_DIR:-$root/target}/release}
case "$(uname -s)" in
  Darwin) shared=libcomgrasp.dylib ;;
  *) shared=libcomgrasp.so ;;
esac
for f in "$shared" libcomgrasp.a comgrasp.pc comgrasp-config.cmake comgrasp-config-version.cmake; do
  if [ ! -f "$src/$f" ]; then
    echo "install.sh: $src/$f is missing; run \`cargo build --release\` first (or pass the PROFILE_DIR that has it)" >&2
    exit 1
  fi
done

mkdir -p "$1"
prefix=$(cd "$1" && pwd)
lib="$prefix/lib"
mkdir -p "$lib/pkgconfig" "$lib/cmake/comgrasp" "$prefix/include" "$prefix/share/comgrasp"

install -m 755 "$src/$shared" "$lib/$shared"
install -m 644 "$src/libcomgrasp.a" "$lib/libcomgrasp.a"
install -m 644 "$root/include/comgrasp.h" "$root/bindings/cpp/comgrasp.hpp" "$prefix/include/"
install -m 644 "$root/scripts/valgrind.supp" "$prefix/share/comgrasp/valgrind.supp"

# Rewrites with sed and checks that each marked line was there, so a change of the
# templates in build/packaging.rs cannot silently produce a package pointing at the tree.
rewrite() { # SRC DEST SED_SCRIPT EXPECTED_LINE...
  local from=$1 to=$2 script=$3
  shift 3
  sed -e "$script" "$from" >"$to.tmp"
  for want in "$@"; do
    if ! grep -qxF -- "$want" "$to.tmp"; then
      rm -f "$to.tmp"
      echo "install.sh: rewriting $from did not give the line: $want (template changed?)" >&2
      exit 1
    fi
  done
  chmod 644 "$to.tmp"
  mv "$to.tmp" "$to"
}

# pkg-config: spaces escaped; for sed, escape \ & and the | delimiter.
pc_prefix=$(printf '%s' "$prefix" | sed -e 's/\\/\\\\/g; s/ /\\ /g')
sed_prefix=$(printf '%s' "$pc_prefix" | sed -e 's/[\\&|]/\\&/g')
rewrite "$src/comgrasp.pc" "$lib/pkgconfig/comgrasp.pc" \
  "s|^prefix=.*|prefix=$sed_prefix|; s|^libdir=.*|libdir=\${prefix}/lib|; s|^cppincludedir=.*|cppincludedir=\${includedir}|; s|^Cflags: .*|Cflags: -I\${includedir}|" \
  "prefix=$pc_prefix" 'libdir=${prefix}/lib' 'includedir=${prefix}/include' 'Cflags: -I${includedir}'

cm_lib='set(_comgrasp_libdir "${CMAKE_CURRENT_LIST_DIR}/../..")'
cm_inc='set(_comgrasp_include_dirs "${CMAKE_CURRENT_LIST_DIR}/../../../include")'
rewrite "$src/comgrasp-config.cmake" "$lib/cmake/comgrasp/comgrasp-config.cmake" \
  "s|^set(_comgrasp_libdir .*|$cm_lib|; s|^set(_comgrasp_include_dirs .*|$cm_inc|" \
  "$cm_lib" "$cm_inc"
install -m 644 "$src/comgrasp-config-version.cmake" "$lib/cmake/comgrasp/comgrasp-config-version.cmake"

echo "installed comgrasp into $prefix:"
echo "  pkg-config: PKG_CONFIG_PATH=$lib/pkgconfig pkg-config --cflags --libs comgrasp"
echo "  CMake:      -DCMAKE_PREFIX_PATH=$prefix, find_package(comgrasp CONFIG REQUIRED)"
echo "  valgrind:   --suppressions=$prefix/share/comgrasp/valgrind.supp"

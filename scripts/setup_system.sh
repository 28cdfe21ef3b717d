#!/usr/bin/env bash
# Install the system tools the host-binding tests need, with apt, only when missing:
#   cmake, pkg-config     tests/cmake_package.rs (CMake package + pkg-config file)
#   mcs, mono             tests/csharp_binding.rs (bindings/unity, the Unity package's C#)
#   python3               tests/python_binding.rs (bindings/python, stdlib ctypes only)
#   cc, c++, readelf      tests/c_example.rs, tests/cmake_package.rs
#   valgrind              scripts/sanitize.sh (memcheck on the C example and C-ABI tests);
#                         its ASan step uses gcc's libasan, which Debian's gcc depends on
#   libclang              building the library at all: iceoryx2's platform layer runs
#                         bindgen over the system headers (libclang-dev)
# Idempotent: does nothing (and needs no network) when every tool is already there.
# Works as root (apt-get directly) or as a user with sudo.
set -euo pipefail

# tool -> Debian package
declare -A PKG=(
  [cmake]=cmake
  [pkg-config]=pkg-config
  [mcs]=mono-mcs
  [mono]=mono-runtime
  [python3]=python3
  [cc]=gcc
  [c++]=g++
  [make]=make
  [readelf]=binutils
  [valgrind]=valgrind
)
missing=()
# --build-only: just what building the library needs (README command 1).
tools=(cmake pkg-config mcs mono python3 cc c++ make readelf valgrind)
[ "${1:-}" = "--build-only" ] && tools=(cc)
for tool in "${tools[@]}"; do
  command -v "$tool" >/dev/null 2>&1 || missing+=("${PKG[$tool]}")
done
# A library, not a command: bindgen finds it through LIBCLANG_PATH or llvm-config's paths.
if [ -z "${LIBCLANG_PATH:-}" ] && ! compgen -G "/usr/lib/llvm-*/lib/libclang*.so*" >/dev/null \
    && ! compgen -G "/usr/lib/*/libclang*.so*" >/dev/null; then
  missing+=(libclang-dev)
fi
[ ${#missing[@]} -eq 0 ] && exit 0

if [ "$(id -u)" -eq 0 ]; then
  SUDO=()
elif command -v sudo >/dev/null 2>&1; then
  SUDO=(sudo)
else
  echo "setup_system: missing ${missing[*]}, and not root and no sudo to install them with apt" >&2
  exit 1
fi
command -v apt-get >/dev/null 2>&1 || {
  echo "setup_system: missing ${missing[*]}; apt-get is not available, install them by hand" >&2
  exit 1
}
echo "setup_system: installing ${missing[*]}" >&2
export DEBIAN_FRONTEND=noninteractive
"${SUDO[@]}" apt-get update -qq
"${SUDO[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null

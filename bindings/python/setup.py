"""Build step of the `comgrasp` package (pyproject.toml has the metadata): the wheel carries
the native library, so `pip install bindings/python` gives a package that runs on its own.

The library copied in: $COMGRASP_LIB if set, else the newest of ../../target/release and
../../target/debug (build it first: `cargo build --release`). Without one the build fails
with that message instead of making a package that cannot load.
"""

import os
import shutil
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

NAME = {"darwin": "libcomgrasp.dylib", "win32": "comgrasp.dll"}.get(sys.platform, "libcomgrasp.so")


def native_library() -> Path:
    env = os.environ.get("COMGRASP_LIB")
    if env:
        if not Path(env).is_file():
            raise SystemExit(f"COMGRASP_LIB={env} is not a file")
        return Path(env)
    target = Path(__file__).resolve().parent.parent.parent / "target"
    found = [p for p in (target / "release" / NAME, target / "debug" / NAME) if p.is_file()]
    if not found:
        raise SystemExit(f"{NAME} not found in {target}/release or debug: run `cargo build --release` "
                         "in the repository first, or set COMGRASP_LIB to the library's path")
    return max(found, key=lambda p: p.stat().st_mtime)


class BuildPyWithLibrary(build_py):
    def run(self):
        super().run()
        dest = Path(self.build_lib) / "comgrasp_ctypes" / NAME
        shutil.copyfile(native_library(), dest)


setup(cmdclass={"build_py": BuildPyWithLibrary})

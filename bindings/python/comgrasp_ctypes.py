"""comgrasp_ctypes: Python binding of the ComGrasp C ABI (include/comgrasp.h) with ctypes.

Standard library only (no numpy, no compiler). Copy this one file next to your code.

    from comgrasp_ctypes import Engine, Coords

    with Engine("models/tiny", coords=Coords.GLTF) as engine:
        with engine.start("A woman drinks from the mug", seed=42) as stream:
            for frame in stream:                     # blocks on a worker thread's frames
                print(frame.frame_index, list(frame.root_translation))

The library is found, in order: ``$COMGRASP_LIB`` (the path of the shared library file),
``libcomgrasp.so`` (``.dylib``, ``comgrasp.dll``) next to this module, then the newest of
``target/release`` and ``target/debug`` of the source tree this file sits in
(``bindings/python/../../target``). ``load(path)`` loads a given file instead.

Errors are raised as :class:`ComgraspError` with ``.status`` (a :class:`Status`) and
``.message`` (the library's thread-local message, read right after the failing call).
Thread rules are the C ABI's: an engine may be used from any thread; a stream from one
thread at a time, except :meth:`Stream.cancel`, which any thread may call at any time
(ctypes releases the GIL during the calls, so a blocking :meth:`Stream.wait` in one thread
does not stop others).
"""

from __future__ import annotations

import ctypes
import enum
import os
import sys
from pathlib import Path
from typing import Iterator, List, Optional, Union

__all__ = [
    "ABI_VERSION", "FRAME_SIZE", "MAX_TEXT_BYTES", "BODY_JOINTS", "HAND_JOINTS", "NUM_JOINTS",
    "Status", "Coords", "CgFrame", "CgEngineConfig", "CgStreamConfig", "ComgraspError",
    "Engine", "Stream", "load", "find_library", "version",
]

#: CG_ABI_VERSION of the header this module mirrors.
ABI_VERSION = 1
#: sizeof(cg_frame) documented by the header (checked at import and against the library).
FRAME_SIZE = 1608
#: CG_MAX_TEXT_BYTES: longest accepted prompt in UTF-8 bytes.
MAX_TEXT_BYTES = 4096
BODY_JOINTS = 21
HAND_JOINTS = 15
NUM_JOINTS = 55

USE_DEFAULT_SEED = 1 << 0
USE_DEFAULT_TEMPERATURE = 1 << 1
USE_DEFAULT_TOP_K = 1 << 2
USE_DEFAULT_MIN_LEN = 1 << 3
USE_DEFAULT_MAX_LEN = 1 << 4
USE_DEFAULT_ALL = 31


class Status(enum.IntEnum):
    """enum cg_status: non-negative values are normal outcomes, negative ones errors."""

    OK = 0
    PENDING = 1
    END = 2
    CANCELLED = 3
    ERR_NULL_POINTER = -1
    ERR_INVALID_UTF8 = -2
    ERR_INVALID_ARGUMENT = -3
    ERR_INVALID_HANDLE = -4
    ERR_WRONG_STATE = -5
    ERR_BUNDLE = -6
    ERR_INFERENCE = -7
    ERR_IO = -8
    ERR_LIMIT = -9
    ERR_PANIC = -10


class Coords(enum.IntEnum):
    """enum cg_coordinate_system."""

    NATIVE = 0  # z up, right-handed, metres
    GLTF = 1  # y up, right-handed, metres
    UNITY = 2  # y up, left-handed, metres
    UNREAL = 3  # z up, left-handed, centimetres


_f = ctypes.c_float


class CgFrame(ctypes.Structure):
    """struct cg_frame, field for field (arrays are ctypes arrays: ``list(f.root_rotation)``,
    ``f.body_rotations[j][k]``)."""

    _fields_ = [
        ("stream_id", ctypes.c_uint64),
        ("frame_index", ctypes.c_uint64),
        ("time_s", ctypes.c_double),
        ("root_translation", _f * 3),
        ("root_rotation", _f * 4),
        ("body_rotations", (_f * 4) * BODY_JOINTS),
        ("left_hand_rotations", (_f * 4) * HAND_JOINTS),
        ("right_hand_rotations", (_f * 4) * HAND_JOINTS),
        ("object_translation", _f * 3),
        ("object_rotation", _f * 4),
        ("object_centre", _f * 3),
        ("left_wrist_to_object", _f * 3),
        ("right_wrist_to_object", _f * 3),
        ("contact_probability", _f * 2),
        ("contact", ctypes.c_uint8 * 2),
        ("is_last", ctypes.c_uint8),
        ("has_joint_positions", ctypes.c_uint8),
        ("reserved", ctypes.c_uint8 * 4),
        ("joint_positions", (_f * 3) * NUM_JOINTS),
    ]

    def to_dict(self) -> dict:
        """The frame as plain Python values (nested lists), e.g. for JSON."""

        def plain(v):
            return [plain(x) for x in v] if isinstance(v, ctypes.Array) else v

        return {name: plain(getattr(self, name)) for name, _ in self._fields_ if name != "reserved"}

    def __repr__(self) -> str:
        return (f"CgFrame(stream_id={self.stream_id}, frame_index={self.frame_index}, "
                f"time_s={self.time_s:.3f}, is_last={self.is_last})")


class CgEngineConfig(ctypes.Structure):
    """struct cg_engine_config (fill with cg_engine_config_init first)."""

    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("coordinate_system", ctypes.c_int),
        ("bundle_path", ctypes.c_char_p),
        ("enable_fk", ctypes.c_uint32),
        ("ring_capacity", ctypes.c_uint32),
        ("max_streams", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
    ]


class CgStreamConfig(ctypes.Structure):
    """struct cg_stream_config (fill with cg_stream_config_init first; to override a field set
    it and clear its USE_DEFAULT_* bit)."""

    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("use_defaults", ctypes.c_uint32),
        ("seed", ctypes.c_uint64),
        ("temperature", ctypes.c_double),
        ("top_k", ctypes.c_uint32),
        ("min_len", ctypes.c_uint32),
        ("max_len", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
    ]


if ctypes.sizeof(CgFrame) != FRAME_SIZE:  # pragma: no cover - a broken copy of this file
    raise ImportError(f"comgrasp_ctypes: sizeof(CgFrame) is {ctypes.sizeof(CgFrame)}, "
                      f"the header's cg_frame is {FRAME_SIZE} bytes")


class ComgraspError(Exception):
    """A failed cg_* call: ``status`` (a :class:`Status`), ``message`` (the library's), ``call``."""

    def __init__(self, call: str, status: int, message: str):
        try:
            status = Status(status)
        except ValueError:
            pass
        super().__init__(f"{call}: {getattr(status, 'name', status)}: {message}")
        self.call = call
        self.status = status
        self.message = message


def _lib_name() -> str:
    if sys.platform == "darwin":
        return "libcomgrasp.dylib"
    if os.name == "nt":
        return "comgrasp.dll"
    return "libcomgrasp.so"


def find_library() -> Path:
    """The shared library this module loads by default (see the module docstring)."""
    env = os.environ.get("COMGRASP_LIB")
    if env:
        p = Path(env)
        if not p.is_file():
            raise FileNotFoundError(f"COMGRASP_LIB={env} is not a file")
        return p
    here = Path(__file__).resolve().parent
    name = _lib_name()
    if (here / name).is_file():
        return here / name
    target = here.parent.parent / "target"
    found = [target / prof / name for prof in ("release", "debug") if (target / prof / name).is_file()]
    if not found:
        raise FileNotFoundError(
            f"{name} not found: set COMGRASP_LIB to its path, put it next to {Path(__file__).name}, "
            f"or run `cargo build --release` in {here.parent.parent}")
    return max(found, key=lambda p: p.stat().st_mtime)


_lib: Optional[ctypes.CDLL] = None


def _declare(lib: ctypes.CDLL) -> None:
    P = ctypes.POINTER
    vp, st, u32, u64, sz = ctypes.c_void_p, ctypes.c_int32, ctypes.c_uint32, ctypes.c_uint64, ctypes.c_size_t
    sigs = {
        "cg_abi_version": (u32, []),
        "cg_version_string": (ctypes.c_char_p, []),
        "cg_frame_size": (sz, []),
        "cg_status_string": (ctypes.c_char_p, [ctypes.c_int32]),
        "cg_last_error": (ctypes.c_char_p, []),
        "cg_last_error_message": (sz, [ctypes.c_char_p, sz]),
        "cg_last_error_status": (st, []),
        "cg_engine_config_init": (st, [P(CgEngineConfig)]),
        "cg_stream_config_init": (st, [P(CgStreamConfig)]),
        "cg_engine_create": (st, [P(CgEngineConfig), P(vp)]),
        "cg_engine_destroy": (st, [vp]),
        "cg_engine_stream_count": (st, [vp, P(u32)]),
        "cg_start": (st, [vp, ctypes.c_char_p, P(CgStreamConfig), P(vp)]),
        "cg_start_utf8": (st, [vp, ctypes.c_char_p, sz, P(CgStreamConfig), P(vp)]),
        "cg_poll_frame": (st, [vp, P(CgFrame)]),
        "cg_stream_wait": (st, [vp, u32, P(CgFrame)]),
        "cg_cancel": (st, [vp]),
        "cg_stream_destroy": (st, [vp]),
        "cg_stream_id": (st, [vp, P(u64)]),
    }
    for name, (res, args) in sigs.items():
        fn = getattr(lib, name)
        fn.restype = res
        fn.argtypes = args


def load(path: Union[str, os.PathLike, None] = None) -> ctypes.CDLL:
    """Loads (once) and checks the library: ABI version and frame size must match this module.
    Returns the ctypes handle with every cg_* function declared (the raw API)."""
    global _lib
    if _lib is not None and path is None:
        return _lib
    lib = ctypes.CDLL(str(path if path is not None else find_library()))
    _declare(lib)
    abi, size = lib.cg_abi_version(), lib.cg_frame_size()
    if abi != ABI_VERSION or size != ctypes.sizeof(CgFrame):
        raise ImportError(f"comgrasp library {getattr(lib, '_name', '?')}: ABI {abi} / frame size {size} "
                          f"does not match comgrasp_ctypes (ABI {ABI_VERSION}, frame {ctypes.sizeof(CgFrame)})")
    _lib = lib
    return lib


def version() -> str:
    """The library's version, "MAJOR.MINOR.PATCH"."""
    return load().cg_version_string().decode()


def _check(lib: ctypes.CDLL, call: str, status: int) -> Status:
    if status < 0:
        raise ComgraspError(call, status, lib.cg_last_error().decode("utf-8", "replace"))
    return Status(status)


class _Owned:
    """A C handle this object owns: ``handle`` while open, ``close()`` (idempotent, also on
    leaving a ``with`` block or on garbage collection) calls the C destroy function once."""

    _kind = "handle"
    _destroy = ""

    _lib: ctypes.CDLL
    _h: Optional[ctypes.c_void_p]

    @property
    def handle(self) -> ctypes.c_void_p:
        """The raw C pointer (for the functions of :func:`load`)."""
        if self._h is None:
            raise ValueError(f"the {self._kind} is closed")
        return self._h

    def close(self) -> None:
        h, self._h = self._h, None
        if h is not None:
            getattr(self._lib, self._destroy)(h)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


class Stream(_Owned):
    """One generation (cg_stream). Poll it, iterate it, or wait on it; ``close()`` (or leaving
    the ``with`` block) stops the worker and frees it (cg_stream_destroy)."""

    _kind, _destroy = "stream", "cg_stream_destroy"

    def __init__(self, lib: ctypes.CDLL, handle: ctypes.c_void_p):
        self._lib = lib
        self._h = handle
        v = ctypes.c_uint64()
        _check(lib, "cg_stream_id", lib.cg_stream_id(handle, ctypes.byref(v)))
        self._id = v.value
        #: The last normal outcome seen (OK, PENDING, END or CANCELLED).
        self.status = Status.PENDING

    @property
    def id(self) -> int:
        """The stream's id (unique per engine, from 1); frames carry it as ``stream_id``."""
        return self._id

    @property
    def done(self) -> bool:
        """True after END or CANCELLED."""
        return self.status in (Status.END, Status.CANCELLED)

    def poll_into(self, frame: CgFrame) -> Status:
        """cg_poll_frame into a caller-owned frame: OK (written), PENDING, END or CANCELLED.
        Never blocks. Raises ComgraspError on errors."""
        self.status = _check(self._lib, "cg_poll_frame", self._lib.cg_poll_frame(self.handle, ctypes.byref(frame)))
        return self.status

    def wait_into(self, frame: CgFrame, timeout_ms: int) -> Status:
        """cg_stream_wait: like poll_into, but blocks up to ``timeout_ms`` for a frame."""
        st = self._lib.cg_stream_wait(self.handle, max(0, min(int(timeout_ms), 0xFFFFFFFF)), ctypes.byref(frame))
        self.status = _check(self._lib, "cg_stream_wait", st)
        return self.status

    def poll(self) -> Optional[CgFrame]:
        """The next frame, or None when none is ready (check ``done`` for the end)."""
        f = CgFrame()
        return f if self.poll_into(f) == Status.OK else None

    def wait(self, timeout_ms: int = 1000) -> Optional[CgFrame]:
        """The next frame, waiting up to ``timeout_ms``; None on timeout or at the end."""
        f = CgFrame()
        return f if self.wait_into(f, timeout_ms) == Status.OK else None

    def __iter__(self) -> Iterator[CgFrame]:
        """Every remaining frame (a new CgFrame each), until END or CANCELLED (see ``status``)."""
        while True:
            f = CgFrame()
            st = self.wait_into(f, 100)
            if st == Status.OK:
                yield f
            elif st != Status.PENDING:
                return

    def frames(self) -> List[CgFrame]:
        """All remaining frames as a list (blocks until the stream ends or is cancelled)."""
        return list(self)

    def cancel(self) -> None:
        """Stops generation within about one token step; any thread, any time; idempotent."""
        _check(self._lib, "cg_cancel", self._lib.cg_cancel(self.handle))



class Engine(_Owned):
    """A loaded model bundle (cg_engine). ``bundle_path=None`` uses ``$COMGRASP_BUNDLE``, else
    the bundle embedded in the library. Closing it cancels the streams still running (their
    Stream objects stay usable and report CANCELLED)."""

    _kind, _destroy = "engine", "cg_engine_destroy"

    def __init__(self, bundle_path: Union[str, os.PathLike, None] = None, *, coords: Coords = Coords.NATIVE,
                 enable_fk: bool = False, ring_capacity: Optional[int] = None,
                 max_streams: Optional[int] = None, lib: Optional[ctypes.CDLL] = None):
        self._lib = lib or load()
        cfg = CgEngineConfig()
        self._lib.cg_engine_config_init(ctypes.byref(cfg))
        cfg.coordinate_system = int(coords)
        cfg.enable_fk = 1 if enable_fk else 0
        if ring_capacity is not None:
            cfg.ring_capacity = ring_capacity
        if max_streams is not None:
            cfg.max_streams = max_streams
        if bundle_path is not None:
            cfg.bundle_path = os.fsencode(bundle_path)
        h = ctypes.c_void_p()
        _check(self._lib, "cg_engine_create", self._lib.cg_engine_create(ctypes.byref(cfg), ctypes.byref(h)))
        self._h: Optional[ctypes.c_void_p] = h

    def start(self, text: Union[str, bytes, None], *, seed: Optional[int] = None,
              temperature: Optional[float] = None, top_k: Optional[int] = None,
              min_len: Optional[int] = None, max_len: Optional[int] = None) -> Stream:
        """Starts a stream for ``text`` (str, or UTF-8 bytes) and returns at once. Unset
        sampling options keep the bundle's defaults. ``None`` text is passed as NULL."""
        cfg = CgStreamConfig()
        self._lib.cg_stream_config_init(ctypes.byref(cfg))
        for name, value, bit in (("seed", seed, USE_DEFAULT_SEED), ("temperature", temperature, USE_DEFAULT_TEMPERATURE),
                                 ("top_k", top_k, USE_DEFAULT_TOP_K), ("min_len", min_len, USE_DEFAULT_MIN_LEN),
                                 ("max_len", max_len, USE_DEFAULT_MAX_LEN)):
            if value is not None:
                setattr(cfg, name, value)
                cfg.use_defaults &= ~bit
        data = text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text
        h = ctypes.c_void_p()
        st = self._lib.cg_start_utf8(self.handle, data, 0 if data is None else len(data), ctypes.byref(cfg), ctypes.byref(h))
        _check(self._lib, "cg_start", st)
        return Stream(self._lib, h)

    @property
    def stream_count(self) -> int:
        """Streams of this engine alive (started and not yet closed)."""
        n = ctypes.c_uint32()
        _check(self._lib, "cg_engine_stream_count", self._lib.cg_engine_stream_count(self.handle, ctypes.byref(n)))
        return n.value


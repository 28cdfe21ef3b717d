"""comgrasp_ctypes: Python binding of the ComGrasp C ABI (include/comgrasp.h) with ctypes.

Standard library only (no numpy, no compiler). Install it with the library inside
(``pip install bindings/python``: the package ``comgrasp``), or copy this one file next to
your code as ``comgrasp_ctypes.py``.

    from comgrasp_ctypes import Engine, Coords

    with Engine("models/tiny", coords=Coords.GLTF) as engine:
        with engine.start("A woman drinks from the mug", seed=42) as stream:
            for frame in stream:                     # blocks on a worker thread's frames
                print(frame.frame_index, list(frame.root_translation))

The library is found, in order: ``$COMGRASP_LIB`` (the path of the shared library file),
``libcomgrasp.so`` (``.dylib``, ``comgrasp.dll``) next to this module (where the installed
package carries it), then the newest of ``target/release`` and ``target/debug`` of the source
tree this file sits in (``bindings/python/comgrasp_ctypes/../../../target``). ``load(path)``
loads a given file instead.

Shared memory (iceoryx2): ``Engine(..., publish_name="game")`` also publishes every frame
and stream event; a :class:`Subscriber` in any process reads them without running a model:

    with Subscriber("game") as sub:
        f = CgFrame()
        while sub.receive_into(f):                   # never blocks; reuses f
            print(f.stream_id, f.frame_index)
        for ev in iter(sub.receive_event, None):     # CgStreamEvent records
            print(ev.kind, ev.frame_count, ev.text_str)

Errors are raised as :class:`ComgraspError` with ``.status`` (a :class:`Status`) and
``.message`` (the library's thread-local message, read right after the failing call).
Thread rules are the C ABI's: an engine may be used from any thread; a stream from one
thread at a time (a subscriber too), except :meth:`Stream.cancel`, which any thread may
call at any time
(ctypes releases the GIL during the calls, so a blocking :meth:`Stream.wait` in one thread
does not stop others).
"""

from __future__ import annotations

import ctypes
import enum
import os
import sys
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple, Union

__all__ = [
    "ABI_VERSION", "FRAME_SIZE", "MAX_TEXT_BYTES", "BODY_JOINTS", "HAND_JOINTS", "NUM_JOINTS",
    "MAX_PUBLISH_NAME_BYTES", "MAX_SUBSCRIBER_BUFFER", "EVENT_TEXT_BYTES", "EventKind",
    "BACKEND_AUTO", "BACKEND_NATIVE", "BACKEND_TRACT", "OVERLAP_AUTO", "OVERLAP_OFF", "OVERLAP_ON",
    "SCHEDULING_AUTO", "SCHEDULING_CROWD", "SCHEDULING_PER_STREAM", "MAX_SCHEDULER_THREADS",
    "ISA_BEST", "ISA_PORTABLE", "ISA_AVX2", "ISA_AVX512", "MAX_DECODE_GROUP",
    "Status", "Coords", "CgFrame", "CgEngineConfig", "CgStreamConfig", "CgSubscriberConfig",
    "CgStreamEvent", "CgSubscriberStats", "CgPublisherStats", "ComgraspError",
    "Engine", "Stream", "Subscriber", "load", "find_library", "version",
    "CgBoneDesc", "CgBoneMapEntry", "CgBonePose", "CgRetargetObject", "BuiltinMap", "Bone", "Retargeter", "builtin_map",
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
#: CG_MAX_PUBLISH_NAME_BYTES: longest accepted publish name.
MAX_PUBLISH_NAME_BYTES = 64
#: CG_MAX_SUBSCRIBER_BUFFER: largest (and default) subscriber buffer, in frames.
MAX_SUBSCRIBER_BUFFER = 256
#: CG_EVENT_TEXT_BYTES: bytes of cg_stream_event.text, the terminating NUL included.
EVENT_TEXT_BYTES = 256

USE_DEFAULT_SEED = 1 << 0
USE_DEFAULT_TEMPERATURE = 1 << 1
USE_DEFAULT_TOP_K = 1 << 2
USE_DEFAULT_MIN_LEN = 1 << 3
USE_DEFAULT_MAX_LEN = 1 << 4
USE_DEFAULT_GUIDANCE = 1 << 5
USE_DEFAULT_ALL = 63
# cg_stream_config.flags
STREAM_RAW_OUTPUT = 1 << 0
STREAM_NO_GRASP_PLACEMENT = 1 << 1
STREAM_FREE_FEET = 1 << 2
#: A position (x, y, z) and a unit quaternion (x, y, z, w) for scene anchoring.
Placement = Tuple[Sequence[float], Sequence[float]]
# cg_stream_config.anchor
ANCHOR_CHARACTER = 1 << 0
ANCHOR_OBJECT = 1 << 1
ANCHOR_PLACE_CHARACTER = 1 << 2
OBJECT_NAME_MAX = 63  # CG_OBJECT_NAME_MAX


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
    ERR_SHM = -11


class EventKind(enum.IntEnum):
    """cg_stream_event.kind (CG_STREAM_EVENT_*)."""

    STARTED = 1
    ENDED = 2
    CANCELLED = 3
    FAILED = 4


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
        ("publish_name", ctypes.c_char_p),  # library 0.2 (an older one's init sets struct_size 32)
        # Runtime options, library 0.3 (an older one's init sets struct_size 40); 0 = automatic.
        ("step_backend", ctypes.c_uint32),  # CG_BACKEND_AUTO / _NATIVE / _TRACT (0, 1, 2)
        ("decoder_backend", ctypes.c_uint32),
        ("step_threads", ctypes.c_uint32),  # 1 or 2
        ("decoder_threads", ctypes.c_uint32),
        ("decode_group", ctypes.c_uint32),  # 1..8 tokens per decode
        ("overlap", ctypes.c_uint32),  # CG_OVERLAP_AUTO / _OFF / _ON (0, 1, 2)
        ("max_isa", ctypes.c_uint32),  # CG_ISA_BEST / _PORTABLE / _AVX2 / _AVX512 (0..3), process-wide
        ("reserved2", ctypes.c_uint32),
        # Library 0.4 (an older one's init sets struct_size 72).
        ("scheduling", ctypes.c_uint32),  # CG_SCHEDULING_AUTO / _CROWD / _PER_STREAM (0, 1, 2)
        ("scheduler_threads", ctypes.c_uint32),  # crowd scheduler threads, 1..64; 0: cores minus one
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
        ("flags", ctypes.c_uint32),
        ("anchor", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
        ("character_position", ctypes.c_float * 3),
        ("character_rotation", ctypes.c_float * 4),
        ("object_position", ctypes.c_float * 3),
        ("object_rotation", ctypes.c_float * 4),
        ("continue_from", ctypes.c_uint64),
        ("guidance", ctypes.c_double),
    ]


class CgStreamInfo(ctypes.Structure):
    """struct cg_stream_info: what a stream is about (``cg_stream_get_info``)."""

    _fields_ = [
        ("stream_id", ctypes.c_uint64),
        ("object_index", ctypes.c_uint32),
        ("object_named", ctypes.c_uint32),
        ("object_name", ctypes.c_char * (OBJECT_NAME_MAX + 1)),
    ]


class CgBoneDesc(ctypes.Structure):
    """struct cg_bone_desc: one bone of a host skeleton (docs/retargeting.md)."""

    _fields_ = [
        ("name", ctypes.c_char_p),
        ("parent", ctypes.c_int32),
        ("rest_translation", _f * 3),
        ("rest_rotation", _f * 4),
    ]


class CgBoneMapEntry(ctypes.Structure):
    """struct cg_bone_map_entry: which bone follows which SMPL-X joint."""

    _fields_ = [("smplx_joint", ctypes.c_char_p), ("bone", ctypes.c_char_p)]


class CgBonePose(ctypes.Structure):
    """struct cg_bone_pose: one bone's local and world transform in a retargeted frame."""

    _fields_ = [
        ("local_translation", _f * 3),
        ("local_rotation", _f * 4),
        ("world_position", _f * 3),
        ("world_rotation", _f * 4),
    ]


class CgRetargetObject(ctypes.Structure):
    """struct cg_retarget_object: the object in the world and in each hand bone's frame."""

    _fields_ = [
        ("world_position", _f * 3),
        ("world_rotation", _f * 4),
        ("in_hand_position", (_f * 3) * 2),
        ("in_hand_rotation", (_f * 4) * 2),
        ("hand_bone", ctypes.c_int32 * 2),
        ("contact", ctypes.c_uint8 * 2),
        ("reserved", ctypes.c_uint8 * 6),
    ]


class BuiltinMap(enum.IntEnum):
    """enum cg_builtin_map: the ready SMPL-X-to-rig maps."""

    UNITY_HUMANOID = 1
    UE5_MANNEQUIN = 2
    MIXAMO = 3


class CgSubscriberConfig(ctypes.Structure):
    """struct cg_subscriber_config (fill with cg_subscriber_config_init first)."""

    _fields_ = [
        ("struct_size", ctypes.c_uint32),
        ("buffer_frames", ctypes.c_uint32),
        ("reserved", ctypes.c_uint64),
    ]


class CgStreamEvent(ctypes.Structure):
    """struct cg_stream_event: a stream's lifecycle record (``kind`` is an :class:`EventKind`
    value; ``text_str`` is the prompt)."""

    _fields_ = [
        ("stream_id", ctypes.c_uint64),
        ("frame_count", ctypes.c_uint64),
        ("kind", ctypes.c_uint32),
        ("fps", ctypes.c_float),
        ("text", ctypes.c_uint8 * EVENT_TEXT_BYTES),
    ]

    @property
    def text_str(self) -> str:
        """The prompt (the bytes up to the first NUL, as UTF-8)."""
        raw = bytes(self.text)
        return raw.split(b"\0", 1)[0].decode("utf-8", "replace")

    def __repr__(self) -> str:
        try:
            kind = EventKind(self.kind).name
        except ValueError:
            kind = str(self.kind)
        return (f"CgStreamEvent(stream_id={self.stream_id}, kind={kind}, frame_count={self.frame_count}, "
                f"fps={self.fps:g}, text={self.text_str!r})")


class _Counters(ctypes.Structure):
    def to_dict(self) -> dict:
        return {name: getattr(self, name) for name, _ in self._fields_}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v}' for k, v in self.to_dict().items())})"


class CgSubscriberStats(_Counters):
    """struct cg_subscriber_stats: a subscriber's counters since it was opened."""

    _fields_ = [(n, ctypes.c_uint64) for n in ("frames_received", "frames_dropped", "events_received",
                                                "events_dropped", "publisher_changes", "publishers")]


class CgPublisherStats(_Counters):
    """struct cg_publisher_stats: an engine's shared-memory publisher counters."""

    _fields_ = [(n, ctypes.c_uint64) for n in ("frames_published", "frames_skipped", "events_published",
                                                "events_skipped", "subscribers")]


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
    # a source tree: this file is bindings/python/comgrasp_ctypes/__init__.py
    tree = here.parents[2] if len(here.parents) > 2 else here
    target = tree / "target"
    found = [target / prof / name for prof in ("release", "debug") if (target / prof / name).is_file()]
    if not found:
        raise FileNotFoundError(
            f"{name} not found: set COMGRASP_LIB to its path, put it next to {Path(__file__).name}, "
            f"or run `cargo build --release` in {tree}")
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
        "cg_engine_config_init_sized": (st, [P(CgEngineConfig), ctypes.c_size_t]),
        "cg_stream_config_init": (st, [P(CgStreamConfig)]),
        "cg_stream_config_init_sized": (st, [P(CgStreamConfig), ctypes.c_size_t]),
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
        "cg_stream_get_info": (st, [vp, P(CgStreamInfo)]),
    }
    # Shared memory (library 0.2); an older library simply lacks them (Subscriber then fails).
    shm = {
        "cg_subscriber_config_init": (st, [P(CgSubscriberConfig)]),
        "cg_subscriber_open": (st, [ctypes.c_char_p, P(CgSubscriberConfig), P(vp)]),
        "cg_subscriber_receive": (st, [vp, P(CgFrame)]),
        "cg_subscriber_receive_event": (st, [vp, P(CgStreamEvent)]),
        "cg_subscriber_get_stats": (st, [vp, P(CgSubscriberStats)]),
        "cg_subscriber_close": (st, [vp]),
        "cg_engine_publisher_stats": (st, [vp, P(CgPublisherStats)]),
    }
    # Retargeting (library 0.4).
    retarget = {
        "cg_engine_get_rest_joints": (st, [vp, P(_f), sz]),
        "cg_builtin_map_size": (st, [ctypes.c_int32, P(sz)]),
        "cg_builtin_map_entry": (st, [ctypes.c_int32, sz, P(ctypes.c_char_p), P(ctypes.c_char_p)]),
        "cg_retargeter_create": (st, [vp, P(CgBoneDesc), sz, P(CgBoneMapEntry), sz, P(vp)]),
        "cg_retargeter_create_builtin": (st, [vp, P(CgBoneDesc), sz, ctypes.c_int32, P(vp)]),
        "cg_retargeter_destroy": (st, [vp]),
        "cg_retargeter_bone_count": (st, [vp, P(sz)]),
        "cg_retarget_frame": (st, [vp, P(CgFrame), P(CgBonePose), sz, P(CgRetargetObject)]),
        "cg_engine_write_bvh": (st, [vp, P(CgFrame), sz, ctypes.c_char_p, ctypes.c_char_p]),
    }
    optional = list(shm.items()) + list(retarget.items())
    for name, (res, args) in list(sigs.items()) + [kv for kv in optional if hasattr(lib, kv[0])]:
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


def _name_bytes(call: str, name: Union[str, bytes, None]) -> Optional[bytes]:
    """A publish name as the bytes of a C string (None stays None: NULL). An embedded NUL
    would silently cut the name short in C, so it is refused here."""
    data = name.encode("utf-8", "surrogatepass") if isinstance(name, str) else name
    if data is not None and b"\0" in data:
        raise ComgraspError(call, Status.ERR_INVALID_ARGUMENT, f"the publish name {name!r} contains a NUL byte")
    return data


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
    def object(self) -> tuple[str, bool]:
        """(catalogue name, named): the object the frames pose, and whether the prompt named
        it (False: it names no catalogue object and the catalogue's first stands in)."""
        info = CgStreamInfo()
        _check(self._lib, "cg_stream_get_info", self._lib.cg_stream_get_info(self.handle, ctypes.byref(info)))
        return info.object_name.decode("utf-8"), bool(info.object_named)

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
        """Stops generation within one generator call (~8 ms, default bundle); any thread, any time; idempotent."""
        _check(self._lib, "cg_cancel", self._lib.cg_cancel(self.handle))



# cg_engine_config's runtime options (0 = automatic), for Engine(runtime={...}).
BACKEND_AUTO, BACKEND_NATIVE, BACKEND_TRACT = 0, 1, 2
OVERLAP_AUTO, OVERLAP_OFF, OVERLAP_ON = 0, 1, 2
ISA_BEST, ISA_PORTABLE, ISA_AVX2, ISA_AVX512 = 0, 1, 2, 3
MAX_DECODE_GROUP = 8
SCHEDULING_AUTO, SCHEDULING_CROWD, SCHEDULING_PER_STREAM = 0, 1, 2
MAX_SCHEDULER_THREADS = 64
_RUNTIME_FIELDS = ("step_backend", "decoder_backend", "step_threads", "decoder_threads", "decode_group",
                   "overlap", "max_isa", "scheduling", "scheduler_threads")


class Engine(_Owned):
    """A loaded model bundle (cg_engine). ``bundle_path=None`` uses ``$COMGRASP_BUNDLE``, else
    the bundle embedded in the library. ``publish_name`` (1..64 ASCII letters, digits, '_',
    '-', '.') also publishes every frame and stream event over shared memory for
    :class:`Subscriber` s in any process. ``runtime`` sets cg_engine_config's runtime options
    by field name, e.g. ``{"step_threads": 1, "decode_group": 8}`` (values as in comgrasp.h:
    BACKEND_*, OVERLAP_*, ISA_* here); they change how frames are computed, never which.
    Closing it cancels the streams still running (their Stream objects stay usable and report
    CANCELLED)."""

    _kind, _destroy = "engine", "cg_engine_destroy"

    def __init__(self, bundle_path: Union[str, os.PathLike, None] = None, *, coords: Coords = Coords.NATIVE,
                 enable_fk: bool = False, ring_capacity: Optional[int] = None,
                 max_streams: Optional[int] = None, publish_name: Union[str, bytes, None] = None,
                 runtime: Optional[Dict[str, int]] = None, lib: Optional[ctypes.CDLL] = None):
        self._lib = lib or load()
        cfg = CgEngineConfig()
        self._lib.cg_engine_config_init_sized(ctypes.byref(cfg), ctypes.sizeof(cfg))
        cfg.coordinate_system = int(coords)
        cfg.enable_fk = 1 if enable_fk else 0
        if ring_capacity is not None:
            cfg.ring_capacity = ring_capacity
        if max_streams is not None:
            cfg.max_streams = max_streams
        if bundle_path is not None:
            cfg.bundle_path = os.fsencode(bundle_path)
        if publish_name is not None:
            if cfg.struct_size < CgEngineConfig.publish_name.offset + ctypes.sizeof(ctypes.c_char_p):
                raise ComgraspError("cg_engine_create", Status.ERR_INVALID_ARGUMENT,
                                    "this library predates cg_engine_config.publish_name (library 0.2)")
            # Kept referenced by cfg until cg_engine_create returns (the library copies it).
            cfg.publish_name = _name_bytes("cg_engine_create", publish_name)
        for field, value in (runtime or {}).items():
            if field not in _RUNTIME_FIELDS:
                raise ComgraspError("cg_engine_create", Status.ERR_INVALID_ARGUMENT,
                                    f"unknown runtime option {field!r}; one of {_RUNTIME_FIELDS}")
            if cfg.struct_size < getattr(CgEngineConfig, field).offset + 4:
                raise ComgraspError("cg_engine_create", Status.ERR_INVALID_ARGUMENT,
                                    f"this library predates the runtime option {field!r}")
            setattr(cfg, field, value)
        h = ctypes.c_void_p()
        _check(self._lib, "cg_engine_create", self._lib.cg_engine_create(ctypes.byref(cfg), ctypes.byref(h)))
        self._h: Optional[ctypes.c_void_p] = h

    def start(self, text: Union[str, bytes, None], *, seed: Optional[int] = None,
              temperature: Optional[float] = None, top_k: Optional[int] = None,
              min_len: Optional[int] = None, max_len: Optional[int] = None, raw_output: bool = False,
              grasp_placement: bool = True, foot_lock: bool = True,
              character: Optional[Placement] = None, object: Optional[Placement] = None,
              place_character: bool = False, continue_from: Optional[int] = None,
              guidance: Optional[float] = None) -> Stream:
        """Starts a stream for ``text`` (str, or UTF-8 bytes) and returns at once. Unset
        sampling options keep the bundle's defaults. ``None`` text is passed as NULL.
        ``raw_output``: the model's frames without the contact-consistency stage.
        ``grasp_placement=False``: the resting object stays where the model put it instead of
        where the model's hand first closes on it.
        ``foot_lock=False``: the model's legs as they are (its feet may slide) instead of a
        foot it stands on staying planted.
        Scene anchoring, each a ``(position xyz, rotation xyzw)`` pair in the engine's
        coordinate system: ``character`` (ground point and heading), ``object`` (start pose;
        reached for), ``place_character`` (with ``object`` only: the character comes to it).
        ``continue_from``: the id of an ended stream to continue from (its pose, place and object).
        ``guidance``: classifier-free guidance scale (1: the prompt alone)."""
        cfg = CgStreamConfig()
        self._lib.cg_stream_config_init_sized(ctypes.byref(cfg), ctypes.sizeof(cfg))
        for name, value, bit in (("seed", seed, USE_DEFAULT_SEED), ("temperature", temperature, USE_DEFAULT_TEMPERATURE),
                                 ("top_k", top_k, USE_DEFAULT_TOP_K), ("min_len", min_len, USE_DEFAULT_MIN_LEN),
                                 ("max_len", max_len, USE_DEFAULT_MAX_LEN), ("guidance", guidance, USE_DEFAULT_GUIDANCE)):
            if value is not None:
                setattr(cfg, name, value)
                cfg.use_defaults &= ~bit
        if raw_output:
            cfg.flags |= STREAM_RAW_OUTPUT
        if not grasp_placement:
            cfg.flags |= STREAM_NO_GRASP_PLACEMENT
        if not foot_lock:
            cfg.flags |= STREAM_FREE_FEET
        for bit, placement, fields in ((ANCHOR_CHARACTER, character, ("character_position", "character_rotation")),
                                       (ANCHOR_OBJECT, object, ("object_position", "object_rotation"))):
            if placement is not None:
                cfg.anchor |= bit
                for field, values in zip(fields, placement):
                    getattr(cfg, field)[:] = list(values)
        if place_character:
            cfg.anchor |= ANCHOR_PLACE_CHARACTER
        if continue_from is not None:
            cfg.continue_from = continue_from
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

    def rest_joints(self) -> List[Tuple[float, float, float]]:
        """The bundle's rest skeleton (55 SMPL-X joints) in this engine's coordinate system and
        units (cg_engine_get_rest_joints): the rest pose the frames' rotations are relative to."""
        buf = (_f * (NUM_JOINTS * 3))()
        st = self._lib.cg_engine_get_rest_joints(self.handle, buf, NUM_JOINTS)
        _check(self._lib, "cg_engine_get_rest_joints", st)
        return [tuple(buf[3 * j:3 * j + 3]) for j in range(NUM_JOINTS)]

    def write_bvh(self, frames: Sequence[CgFrame], path: Union[str, os.PathLike],
                  object_path: Union[str, os.PathLike, None] = None) -> None:
        """Writes this engine's ``frames`` as BVH (cg_engine_write_bvh): the body (SMPL-X skeleton
        with fingers, y up, centimetres, ZXY channels, the bundle's fps) to ``path`` and the
        object's track to ``object_path`` when given. Frames from any coordinate system."""
        arr = (CgFrame * max(1, len(frames)))()
        for i, f in enumerate(frames):
            arr[i] = f
        enc = [None if p is None else os.fsencode(p) for p in (path, object_path)]
        st = self._lib.cg_engine_write_bvh(self.handle, arr, len(frames), enc[0], enc[1])
        _check(self._lib, "cg_engine_write_bvh", st)

    def retargeter(self, bones: Sequence[Bone], map: Optional[Sequence[Tuple[str, str]]] = None,
                   builtin: Optional[BuiltinMap] = None) -> Retargeter:
        """A :class:`Retargeter` onto ``bones`` for this engine's frames."""
        return Retargeter(self, bones, map, builtin)

    def publisher_stats(self) -> CgPublisherStats:
        """Counters of the shared-memory publisher (cg_engine_publisher_stats); ERR_WRONG_STATE
        when the engine was created without ``publish_name``."""
        s = CgPublisherStats()
        _check(self._lib, "cg_engine_publisher_stats", self._lib.cg_engine_publisher_stats(self.handle, ctypes.byref(s)))
        return s


def builtin_map(which: BuiltinMap, *, lib: Optional[ctypes.CDLL] = None) -> List[Tuple[str, str]]:
    """A ready map's (SMPL-X joint, bone) pairs (cg_builtin_map_entry)."""
    lib = lib or load()
    n = ctypes.c_size_t()
    _check(lib, "cg_builtin_map_size", lib.cg_builtin_map_size(int(which), ctypes.byref(n)))
    out = []
    j, b = ctypes.c_char_p(), ctypes.c_char_p()
    for i in range(n.value):
        _check(lib, "cg_builtin_map_entry", lib.cg_builtin_map_entry(int(which), i, ctypes.byref(j), ctypes.byref(b)))
        out.append((j.value.decode(), b.value.decode()))
    return out


Bone = Tuple[str, int, Sequence[float], Sequence[float]]
"""A host bone: (name, parent index or -1, rest translation xyz, rest rotation xyzw), relative
to the parent, in the engine's coordinate system and units."""


class Retargeter(_Owned):
    """The engine's frames on a host skeleton (cg_retargeter; docs/retargeting.md). ``bones``:
    :data:`Bone` tuples; ``map``: (SMPL-X joint, bone name) pairs, or ``builtin``: a
    :class:`BuiltinMap` (entries whose bone the skeleton lacks are skipped). ``retarget``
    poses every bone for a frame; ``close()`` frees it."""

    _kind, _destroy = "retargeter", "cg_retargeter_destroy"

    def __init__(self, engine: Engine, bones: Sequence[Bone], map: Optional[Sequence[Tuple[str, str]]] = None,
                 builtin: Optional[BuiltinMap] = None):
        self._lib = engine._lib
        self._h = None
        if (map is None) == (builtin is None):
            raise ComgraspError("cg_retargeter_create", Status.ERR_INVALID_ARGUMENT, "give exactly one of map or builtin")
        names = [n.encode("utf-8", "surrogatepass") if isinstance(n, str) else n for n, *_ in bones]
        descs = (CgBoneDesc * max(1, len(bones)))()
        for d, (name, (_, parent, t, r)) in zip(descs, zip(names, bones)):
            d.name, d.parent = name, parent
            d.rest_translation[:] = list(t)
            d.rest_rotation[:] = list(r)
        h = ctypes.c_void_p()
        if builtin is not None:
            st = self._lib.cg_retargeter_create_builtin(engine.handle, descs, len(bones), int(builtin), ctypes.byref(h))
            _check(self._lib, "cg_retargeter_create_builtin", st)
        else:
            pairs = [(j.encode(), b.encode("utf-8", "surrogatepass")) for j, b in map]
            entries = (CgBoneMapEntry * max(1, len(pairs)))(*[CgBoneMapEntry(j, b) for j, b in pairs])
            st = self._lib.cg_retargeter_create(engine.handle, descs, len(bones), entries, len(pairs), ctypes.byref(h))
            _check(self._lib, "cg_retargeter_create", st)
        self._h = h
        n = ctypes.c_size_t()
        _check(self._lib, "cg_retargeter_bone_count", self._lib.cg_retargeter_bone_count(h, ctypes.byref(n)))
        self.bone_count = n.value
        self._poses = (CgBonePose * self.bone_count)()

    def retarget(self, frame: CgFrame, with_object: bool = True) -> Tuple[ctypes.Array[CgBonePose], Optional[CgRetargetObject]]:
        """Every bone's pose for ``frame`` (an array reused by the next call: copy what you
        keep) and, with ``with_object``, the object (a new CgRetargetObject)."""
        obj = CgRetargetObject() if with_object else None
        st = self._lib.cg_retarget_frame(self.handle, ctypes.byref(frame), self._poses, self.bone_count,
                                         ctypes.byref(obj) if obj is not None else None)
        _check(self._lib, "cg_retarget_frame", st)
        return self._poses, obj


class Subscriber(_Owned):
    """A shared-memory subscriber (cg_subscriber) on the frames and stream events an engine
    publishes under ``name`` (its ``publish_name``), in this or another process. Works before
    the publisher exists and across its restarts; frames arrive from opening on (no history).
    ``buffer_frames`` (1..256) unread frames are kept; beyond that the oldest are overwritten
    and counted in ``stats().frames_dropped``. Receiving never blocks. One thread at a time;
    ``close()`` (or leaving the ``with`` block) frees it."""

    _kind, _destroy = "subscriber", "cg_subscriber_close"

    def __init__(self, name: Union[str, bytes, None], buffer_frames: int = MAX_SUBSCRIBER_BUFFER, *,
                 lib: Optional[ctypes.CDLL] = None):
        self._lib = lib or load()
        self._h = None
        cfg = CgSubscriberConfig()
        _check(self._lib, "cg_subscriber_config_init", self._lib.cg_subscriber_config_init(ctypes.byref(cfg)))
        cfg.buffer_frames = max(0, min(int(buffer_frames), 0xFFFFFFFF))
        data = _name_bytes("cg_subscriber_open", name)
        h = ctypes.c_void_p()
        _check(self._lib, "cg_subscriber_open", self._lib.cg_subscriber_open(data, ctypes.byref(cfg), ctypes.byref(h)))
        self._h = h

    def receive_into(self, frame: CgFrame) -> bool:
        """Copies the oldest unread frame into ``frame`` and returns True, or returns False when
        there is none (``frame`` untouched). Frames of all the publisher's streams arrive
        interleaved: tell them apart by ``stream_id``."""
        st = self._lib.cg_subscriber_receive(self.handle, ctypes.byref(frame))
        return _check(self._lib, "cg_subscriber_receive", st) == Status.OK

    def receive(self) -> Optional[CgFrame]:
        """The oldest unread frame (a new CgFrame), or None."""
        f = CgFrame()
        return f if self.receive_into(f) else None

    def receive_event_into(self, event: CgStreamEvent) -> bool:
        """Like receive_into, for the stream events (a separate queue: a stream's ENDED event
        may arrive before its last frames)."""
        st = self._lib.cg_subscriber_receive_event(self.handle, ctypes.byref(event))
        return _check(self._lib, "cg_subscriber_receive_event", st) == Status.OK

    def receive_event(self) -> Optional[CgStreamEvent]:
        """The oldest unread stream event (a new CgStreamEvent), or None."""
        e = CgStreamEvent()
        return e if self.receive_event_into(e) else None

    def stats(self) -> CgSubscriberStats:
        """Counters since opening (cg_subscriber_get_stats)."""
        s = CgSubscriberStats()
        _check(self._lib, "cg_subscriber_get_stats", self._lib.cg_subscriber_get_stats(self.handle, ctypes.byref(s)))
        return s


"""Tests of the installed comgrasp_ctypes package against the real library: plain asserts,
runnable either way, with the package installed (`pip install bindings/python`):

    python3 bindings/python/tests/test_comgrasp_ctypes.py    # runs every test_* function
    python3 -m pytest bindings/python/tests/test_comgrasp_ctypes.py

The package is imported as installed (this file puts nothing on sys.path).
Environment: COMGRASP_LIB (the library; default: comgrasp_ctypes.find_library(), which
finds the one the package carries), COMGRASP_TEST_BUNDLE (default: models/tiny of this
source tree), COMGRASP_C_LAYOUT (the output of tests/host_support/layout.c: the C compiler's
struct layout; without it the layout is checked against the sizes documented in
comgrasp.h), COMGRASP_BVH_CHECK (cli/tests/bvh_check.py: the BVH read-back check; needs
numpy and the PyPI `bvh` package). tests/python_binding.rs sets all of them but
COMGRASP_LIB. The shared-memory tests publish under names with this process's id.
"""

import ctypes
import json
import os
import sys
import threading
import time
from pathlib import Path

import comgrasp_ctypes as cg
from comgrasp_ctypes import CgFrame, CgStreamEvent, ComgraspError, Coords, Engine, EventKind, Status, Subscriber

HERE = Path(__file__).resolve().parent
BUNDLE = os.environ.get("COMGRASP_TEST_BUNDLE", str(HERE.parents[2] / "models" / "tiny"))
PROMPT = "A woman drinks from the mug"


def raises(fn, *args, **kwargs) -> ComgraspError:
    try:
        fn(*args, **kwargs)
    except ComgraspError as e:
        return e
    raise AssertionError(f"{fn.__name__}{args} raised no ComgraspError")


def engine(**kw) -> Engine:
    return Engine(BUNDLE, **kw)


def test_layout_matches_c():
    assert ctypes.sizeof(CgFrame) == cg.FRAME_SIZE == 1608
    lib = cg.load()
    assert lib.cg_frame_size() == ctypes.sizeof(CgFrame)
    assert ctypes.sizeof(cg.CgStreamConfig) == 120
    assert ctypes.sizeof(cg.CgEngineConfig) == (80 if ctypes.sizeof(ctypes.c_void_p) == 8 else 72)
    assert cg.CgEngineConfig.scheduling.offset == (72 if ctypes.sizeof(ctypes.c_void_p) == 8 else 64)
    assert cg.CgEngineConfig.publish_name.offset == (32 if ctypes.sizeof(ctypes.c_void_p) == 8 else 28)
    assert cg.CgEngineConfig.step_backend.offset == (40 if ctypes.sizeof(ctypes.c_void_p) == 8 else 32)
    assert ctypes.sizeof(cg.CgSubscriberConfig) == 16 and ctypes.sizeof(CgStreamEvent) == 280
    assert ctypes.sizeof(cg.CgSubscriberStats) == 48 and ctypes.sizeof(cg.CgPublisherStats) == 40
    assert ctypes.sizeof(cg.CgStreamInfo) == 80
    assert CgFrame.contact.offset == 940 and CgFrame.joint_positions.offset == 948
    ec = cg.CgEngineConfig()
    assert lib.cg_engine_config_init_sized(ctypes.byref(ec), ctypes.sizeof(ec)) == Status.OK
    assert ec.struct_size == ctypes.sizeof(ec) and ec.publish_name is None
    sc = cg.CgSubscriberConfig()
    assert lib.cg_subscriber_config_init(ctypes.byref(sc)) == Status.OK
    assert sc.struct_size == ctypes.sizeof(sc) and sc.buffer_frames == cg.MAX_SUBSCRIBER_BUFFER
    path = os.environ.get("COMGRASP_C_LAYOUT")
    if not path:
        return
    types = {"cg_frame": CgFrame, "cg_engine_config": cg.CgEngineConfig, "cg_stream_config": cg.CgStreamConfig,
             "cg_subscriber_config": cg.CgSubscriberConfig, "cg_stream_event": CgStreamEvent,
             "cg_subscriber_stats": cg.CgSubscriberStats, "cg_publisher_stats": cg.CgPublisherStats,
             "cg_stream_info": cg.CgStreamInfo, "cg_bone_desc": cg.CgBoneDesc, "cg_bone_map_entry": cg.CgBoneMapEntry,
             "cg_bone_pose": cg.CgBonePose, "cg_retarget_object": cg.CgRetargetObject}
    seen = {t: 0 for t in types.values()}
    sized = set()
    for line in Path(path).read_text().splitlines():
        w = line.split()
        if w[0] == "size":
            assert ctypes.sizeof(types[w[1]]) == int(w[2]), line
            sized.add(types[w[1]])
        elif w[0] == "offset":
            t = types[w[1]]
            assert getattr(t, w[2]).offset == int(w[3]), f"{line}: ctypes has {getattr(t, w[2]).offset}"
            seen[t] += 1
    for t, n in seen.items():
        assert n == len(t._fields_), f"{t.__name__}: C has {n} fields, ctypes {len(t._fields_)}"
    assert sized == set(types.values()), f"sizes missing from the layout file: {set(types.values()) - sized}"


def test_version():
    lib = cg.load()
    assert lib.cg_abi_version() == cg.ABI_VERSION
    major, minor, patch = cg.version().split(".")[:3]
    assert major.isdigit() and minor.isdigit()
    assert lib.cg_status_string(-3) and lib.cg_status_string(12345) == b"unknown cg_status value"


def test_stream_to_end():
    with engine(coords=Coords.UNITY, enable_fk=True) as e, e.start(PROMPT, seed=7) as s:
        assert s.id >= 1 and e.stream_count == 1
        frames = []
        f = CgFrame()
        deadline = time.monotonic() + 120
        while True:
            st = s.poll_into(f)
            assert time.monotonic() < deadline
            if st == Status.PENDING:
                time.sleep(0.001)
                continue
            if st != Status.OK:
                break
            frames.append(CgFrame.from_buffer_copy(f))
        assert st == Status.END and s.done
        assert len(frames) > 0 and len(frames) % 16 == 0, len(frames)
        for i, fr in enumerate(frames):
            assert fr.frame_index == i and fr.stream_id == s.id
            assert fr.is_last == (1 if i == len(frames) - 1 else 0)
            assert abs(fr.time_s - i / 30.0) < 1e-9
            assert fr.has_joint_positions == 1
            q = list(fr.root_rotation)
            assert abs(sum(x * x for x in q) - 1) < 1e-3 and q[3] >= 0
            for h in range(2):
                assert 0 <= fr.contact_probability[h] <= 1 and fr.contact[h] in (0, 1)
            assert list(fr.reserved) == [0, 0, 0, 0]
        assert s.poll_into(f) == Status.END and s.poll() is None
        d = frames[-1].to_dict()
        assert len(d["body_rotations"]) == 21 and len(d["joint_positions"][54]) == 3 and d["is_last"] == 1
        s.close()
        assert e.stream_count == 0


def test_iteration_ids_and_determinism():
    with engine(coords=Coords.GLTF) as e:
        opts = dict(seed=3, temperature=0.9, top_k=4, min_len=2, max_len=6)
        with e.start("The man lifts a small cube.", **opts) as a, e.start(b"The man lifts a small cube.", **opts) as b:
            assert a.id != b.id
            fa, fb = list(a), b.frames()
            assert a.status == b.status == Status.END
            assert 32 <= len(fa) == len(fb) <= 96
            for x, y in zip(fa, fb):
                assert x.stream_id == a.id and y.stream_id == b.id
                assert bytes(x)[8:] == bytes(y)[8:]  # all but the stream id
        with e.start("The man lifts a small cube.", guidance=2.0, **opts) as g:  # classifier-free guidance
            assert [bytes(x)[8:] for x in g] != [bytes(x)[8:] for x in fa]


def test_raw_output_flag():
    """Raw frames: contact = probability > 0.5, the object goes where the model put it. The
    default (the contact-consistency stage): an object no hand holds stays put or falls."""
    opts = dict(seed=5, min_len=6, max_len=6)
    with engine() as e:
        with e.start(PROMPT, raw_output=True, **opts) as s:
            raw = s.frames()
        with e.start(PROMPT, **opts) as s:
            consistent = s.frames()
        with e.start(PROMPT, grasp_placement=False, **opts) as s:
            kept = s.frames()
        with e.start(PROMPT, foot_lock=False, **opts) as s:
            free = s.frames()
        cfg = cg.CgStreamConfig()
        e._lib.cg_stream_config_init(ctypes.byref(cfg))
        cfg.flags = 1 << 6
        h = ctypes.c_void_p()
        st = e._lib.cg_start_utf8(e.handle, b"a mug", 5, ctypes.byref(cfg), ctypes.byref(h))
        assert st == Status.ERR_INVALID_ARGUMENT and b"flags" in e._lib.cg_last_error()
    assert len(raw) == len(consistent) == len(kept) == 96
    # without placement from the grasp the resting object starts where the model put it over
    # the ground (its height is the model's raised by the stream's ground lift, and an object
    # that then starts in the ground rises out of it)
    assert list(kept[0].object_translation)[:2] == list(raw[0].object_translation)[:2]
    # free feet: the legs are the model's (but where the speed limit holds a token seam
    # back); planted feet move them
    def hip(f):
        return [list(r) for r in f.body_rotations[:1]]
    assert sum(hip(a) == hip(b) for a, b in zip(free, raw)) * 4 >= len(raw) * 3
    assert any(hip(a) != hip(b) for a, b in zip(free, consistent))
    with engine() as e:
        with e.start("Lift the small cube", min_len=1, max_len=1) as s:
            assert s.object == ("cubesmall", True)
        with e.start("Hebe die Tasse", min_len=1, max_len=1) as s:
            assert s.object == ("mug", False)  # names nothing: the first catalogue object
        # Scene anchoring: the mug starts at the host's pose; out of reach is an error.
        mug = ((0.1, 0.55, 0.8), (0.0, 0.0, 0.0, 1.0))
        with e.start(PROMPT, min_len=1, max_len=1, character=((0, 0, 0), (0, 0, 0, 1)), object=mug) as s:
            assert [round(v, 5) for v in s.frames()[0].object_translation] == [0.1, 0.55, 0.8]
        err = raises(e.start, PROMPT, object=((5.0, 0.0, 0.8), (0, 0, 0, 1)))
        assert err.status == Status.ERR_INVALID_ARGUMENT and "out of reach" in err.message
        err = raises(e.start, PROMPT, object=((0.1, 0.5, 0.8), (0, 0, 0.5, 0.5)))
        assert "unit quaternion" in err.message
        # Chaining: the next stream starts where an ended one left off.
        with e.start(PROMPT, min_len=2, max_len=2, seed=1) as a:
            first = a.frames()
            with e.start("Drink from it", min_len=2, max_len=2, continue_from=a.id) as b:
                second = b.frames()
                assert b.object == ("mug", True)  # the earlier stream's object
        gap = max(abs(x - y) for x, y in zip(first[-1].root_translation, second[0].root_translation))
        assert gap < 0.05, gap
        assert "has not ended" in raises(e.start, PROMPT, continue_from=999).message
    for fr in raw:
        assert all(fr.contact[h] == (1 if fr.contact_probability[h] > 0.5 else 0) for h in range(2))
    for a, b in zip(consistent, consistent[1:]):
        if not any(a.contact) and not any(b.contact):
            assert list(a.object_translation)[:2] == list(b.object_translation)[:2]
            assert b.object_translation[2] <= a.object_translation[2] + 0.011
    assert any(list(a.object_translation) != list(b.object_translation) for a, b in zip(raw, consistent))


def test_runtime_options_change_how_not_what():
    opts = dict(seed=5, min_len=2, max_len=4)
    with engine() as e, e.start(PROMPT, **opts) as s:
        auto = s.frames()
    runtime = dict(step_backend=cg.BACKEND_NATIVE, step_threads=1, decoder_threads=1, decode_group=1,
                   overlap=cg.OVERLAP_OFF, max_isa=cg.ISA_BEST, scheduling=cg.SCHEDULING_PER_STREAM,
                   scheduler_threads=1)
    with engine(runtime=runtime) as e, e.start(PROMPT, **opts) as s:
        manual = s.frames()
    assert len(auto) == len(manual) > 0
    assert all(bytes(x)[8:] == bytes(y)[8:] for x, y in zip(auto, manual))
    for field, bad in (("step_threads", 3), ("decode_group", cg.MAX_DECODE_GROUP + 1), ("overlap", 3),
                       ("scheduling", 3), ("scheduler_threads", cg.MAX_SCHEDULER_THREADS + 1)):
        err = raises(engine, runtime={field: bad})
        assert err.status == Status.ERR_INVALID_ARGUMENT and field in err.message, err
    err = raises(engine, runtime={"threads": 1})
    assert err.status == Status.ERR_INVALID_ARGUMENT and "threads" in err.message


def test_errors():
    e = raises(Engine, "/nonexistent/bundle")
    assert e.status == Status.ERR_BUNDLE and "/nonexistent/bundle" in e.message
    assert str(e).startswith("cg_engine_create: ERR_BUNDLE: ")
    assert cg.load().cg_last_error_status() == Status.ERR_BUNDLE
    assert raises(engine, ring_capacity=0).status == Status.ERR_INVALID_ARGUMENT

    with engine(max_streams=2) as eng:
        e = raises(eng.start, None)
        assert e.status == Status.ERR_NULL_POINTER and "text" in e.message
        e = raises(eng.start, "")
        assert e.status == Status.ERR_INVALID_ARGUMENT and e.message
        e = raises(eng.start, " \t ")
        assert e.status == Status.ERR_INVALID_ARGUMENT and "whitespace" in e.message
        assert raises(eng.start, b"A\xff\xfe").status == Status.ERR_INVALID_UTF8
        assert raises(eng.start, "lone \udc80 surrogate").status == Status.ERR_INVALID_UTF8
        assert raises(eng.start, "a\0b").status == Status.ERR_INVALID_ARGUMENT
        e = raises(eng.start, "a" * (cg.MAX_TEXT_BYTES + 1))
        assert e.status == Status.ERR_INVALID_ARGUMENT and "4096" in e.message
        assert raises(eng.start, "a mug", max_len=0).status == Status.ERR_INVALID_ARGUMENT
        for g in (-1.0, float("nan"), float("inf")):
            e = raises(eng.start, "a mug", guidance=g)
            assert e.status == Status.ERR_INVALID_ARGUMENT and "guidance" in e.message

        lib = cg.load()
        msg = lib.cg_last_error()
        assert lib.cg_last_error_message(None, 0) == len(msg) + 1
        buf = ctypes.create_string_buffer(8)
        lib.cg_last_error_message(buf, 8)
        assert buf.raw[7] == 0 and buf.value == msg[:7]

        with eng.start("a mug"), eng.start("a mug"):
            assert raises(eng.start, "a mug").status == Status.ERR_LIMIT

        f = CgFrame()
        assert lib.cg_poll_frame(None, ctypes.byref(f)) == Status.ERR_NULL_POINTER
        s = eng.start("a mug")
        h = s.handle
        assert lib.cg_poll_frame(h, None) == Status.ERR_NULL_POINTER
        s.close()
        s.close()  # idempotent
        assert lib.cg_stream_id(h, ctypes.byref(ctypes.c_uint64())) == Status.ERR_INVALID_HANDLE
        assert lib.cg_stream_destroy(h) == Status.ERR_INVALID_HANDLE
        assert lib.cg_last_error()
        try:
            s.poll()
            raise AssertionError("poll on a closed stream")
        except ValueError:
            pass


def test_last_error_is_per_thread():
    with engine() as e:
        raises(e.start, "   ")
        lib = cg.load()
        mine = lib.cg_last_error()
        other = []
        t = threading.Thread(target=lambda: other.append(raises(e.start, None).status))
        t.start()
        t.join()
        assert other == [Status.ERR_NULL_POINTER]
        assert lib.cg_last_error() == mine and lib.cg_last_error_status() == Status.ERR_INVALID_ARGUMENT


def test_cancel():
    # 64 frames through a 16-frame ring: the stream cannot finish before it is drained.
    with engine(ring_capacity=16) as e, e.start(PROMPT, min_len=4, max_len=4) as s:
        assert s.wait(30000) is not None
        s.cancel()
        s.cancel()
        f = CgFrame()
        assert s.poll_into(f) == Status.CANCELLED and s.done
        assert s.wait_into(f, 10) == Status.CANCELLED
        assert list(s) == [] and s.status == Status.CANCELLED
        assert e.stream_count == 1


def test_cancel_from_another_thread():
    with engine(ring_capacity=16) as e, e.start(PROMPT, min_len=18, max_len=18) as s:
        first = threading.Event()
        t = threading.Thread(target=lambda: (first.wait(), s.cancel()))
        t.start()
        n = 0
        for _ in s:
            n += 1
            first.set()
        t.join()
        assert s.status == Status.CANCELLED and 0 < n < 18 * 16


def test_engine_close_cancels_streams():
    e = engine(ring_capacity=16)
    s = e.start(PROMPT, min_len=4, max_len=4)
    assert s.wait(30000) is not None
    e.close()
    assert s.poll() is None and s.status == Status.CANCELLED
    try:
        e.start("a mug")
        raise AssertionError("start on a closed engine")
    except ValueError:
        pass
    s.close()


_names = iter(range(1, 1 << 30))


def unique_name(tag: str) -> str:
    """A publish name no other process (test run) uses."""
    return f"py-{os.getpid()}-{tag}-{next(_names)}"


def test_shm_subscriber_receives_the_polled_frames():
    name = unique_name("sub")
    with engine(publish_name=name) as e, Subscriber(name, 256) as sub:
        assert e.publisher_stats().subscribers == 1 and sub.stats().publishers == 1
        assert sub.receive() is None and sub.receive_event() is None  # nothing before the stream
        polled, received, events = [], [], []
        f, r = CgFrame(), CgFrame()
        with e.start(PROMPT, seed=5) as s:
            deadline = time.monotonic() + 120
            while True:
                assert time.monotonic() < deadline
                st = s.wait_into(f, 5)
                if st == Status.OK:
                    polled.append(CgFrame.from_buffer_copy(f))
                while sub.receive_into(r):  # the same frame object, reused
                    received.append(CgFrame.from_buffer_copy(r))
                events.extend(iter(sub.receive_event, None))
                if st == Status.END:
                    break
            # Every frame and the ENDED event were published before the stream reported END.
            deadline = time.monotonic() + 5
            while (len(received) < len(polled) or len(events) < 2) and time.monotonic() < deadline:
                got = sub.receive()
                if got is not None:
                    received.append(got)
                events.extend(iter(sub.receive_event, None))
                if got is None:
                    time.sleep(0.001)
            n = len(polled)
            assert n > 0 and n % 16 == 0, n
            assert len(received) == n, f"received {len(received)} of {n} frames"
            assert sub.receive() is None
            for i, (a, b) in enumerate(zip(polled, received)):
                assert (b.stream_id, b.frame_index) == (s.id, i), (i, b)
                assert (b.stream_id, b.frame_index, b.time_s, b.is_last) == (a.stream_id, a.frame_index, a.time_s, a.is_last)
                assert bytes(b.root_translation) == bytes(a.root_translation)
                assert bytes(b.body_rotations) == bytes(a.body_rotations)
                assert bytes(b) == bytes(a), f"frame {i} differs"
            assert received[-1].is_last == 1

            assert [ev.kind for ev in events] == [EventKind.STARTED, EventKind.ENDED], events
            assert all(ev.stream_id == s.id and ev.fps == 30.0 and ev.text_str == PROMPT for ev in events), events
            assert (events[0].frame_count, events[1].frame_count) == (0, n)

            st = sub.stats()
            assert (st.frames_received, st.frames_dropped, st.events_received, st.events_dropped) == (n, 0, 2, 0), st
            assert (st.publisher_changes, st.publishers) == (0, 1), st
            p = e.publisher_stats()
            assert (p.frames_published, p.frames_skipped, p.events_published, p.events_skipped) == (n, 0, 2, 0), p
            assert p.subscribers == 1 and p.to_dict()["frames_published"] == n
        h = sub.handle
        sub.close()
        sub.close()  # idempotent
        lib = cg.load()
        assert lib.cg_subscriber_close(h) == Status.ERR_INVALID_HANDLE  # double close
        assert lib.cg_subscriber_receive(h, ctypes.byref(f)) == Status.ERR_INVALID_HANDLE
        try:
            sub.receive()
            raise AssertionError("receive on a closed subscriber")
        except ValueError:
            pass
        assert e.publisher_stats().subscribers == 0


def test_shm_errors():
    with engine() as e:
        assert raises(e.publisher_stats).status == Status.ERR_WRONG_STATE
    for bad in ["", "a/b", "with space", "..", "\u00e9", "n" * (cg.MAX_PUBLISH_NAME_BYTES + 1)]:
        assert raises(engine, publish_name=bad).status == Status.ERR_INVALID_ARGUMENT, bad
        assert raises(Subscriber, bad).status == Status.ERR_INVALID_ARGUMENT, bad
    assert raises(Subscriber, "ok\0hidden").status == Status.ERR_INVALID_ARGUMENT
    assert raises(engine, publish_name="ok\0hidden").status == Status.ERR_INVALID_ARGUMENT
    assert raises(Subscriber, None).status == Status.ERR_NULL_POINTER
    name = unique_name("err")
    for frames in (0, cg.MAX_SUBSCRIBER_BUFFER + 1):
        err = raises(Subscriber, name, frames)
        assert err.status == Status.ERR_INVALID_ARGUMENT and "buffer_frames" in err.message, err
    longest = (name + "x" * cg.MAX_PUBLISH_NAME_BYTES)[: cg.MAX_PUBLISH_NAME_BYTES]
    lib = cg.load()
    with Subscriber(longest.encode(), 1) as sub:
        assert sub.receive() is None and sub.receive_event() is None and sub.stats().publishers == 0
        assert lib.cg_subscriber_receive(sub.handle, None) == Status.ERR_NULL_POINTER
        assert lib.cg_subscriber_receive_event(sub.handle, None) == Status.ERR_NULL_POINTER
        assert lib.cg_subscriber_get_stats(sub.handle, None) == Status.ERR_NULL_POINTER
    assert lib.cg_subscriber_close(None) == Status.OK
    with engine() as e:
        assert lib.cg_subscriber_receive(e.handle, ctypes.byref(CgFrame())) == Status.ERR_INVALID_HANDLE


SMPLX_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
                 20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
                 21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53)


def test_retarget_onto_a_unity_named_skeleton():
    """The engine's own skeleton with its bones named as Unity's HumanBodyBones (jaw and
    eyes unmapped), in Unity coordinates: the retargeted world positions are the frames'
    FK joint positions; bad input raises with the library's message."""
    mapping = dict(cg.builtin_map(cg.BuiltinMap.UNITY_HUMANOID))
    assert len(mapping) == 52 and mapping["left_wrist"] == "LeftHand" and mapping["right_thumb3"] == "RightThumbDistal"
    assert cg.builtin_map(cg.BuiltinMap.MIXAMO)[0] == ("pelvis", "mixamorig:Hips")
    with engine(coords=Coords.UNITY, enable_fk=True) as e:
        rest = e.rest_joints()
        joints = json.loads((Path(BUNDLE) / "manifest.json").read_text())["skeleton"]["joint_names"]
        names = [mapping.get(j, j) for j in joints]
        bones = []
        for j, p in enumerate(SMPLX_PARENTS):
            t = rest[j] if p < 0 else tuple(a - b for a, b in zip(rest[j], rest[p]))
            bones.append((names[j], p, t, (0.0, 0.0, 0.0, 1.0)))
        with e.retargeter(bones, builtin=cg.BuiltinMap.UNITY_HUMANOID) as r, e.start(PROMPT, seed=3) as s:
            assert r.bone_count == 55
            n = 0
            for f in s:
                poses, obj = r.retarget(f)
                for j in range(55):
                    d = sum((poses[j].world_position[i] - f.joint_positions[j][i]) ** 2 for i in range(3)) ** 0.5
                    assert d < 1e-3, (n, j, d)
                assert list(obj.hand_bone) == [20, 21] and list(obj.contact) == list(f.contact)
                n += 1
            assert n > 0
        bad = list(bones)
        bad[3] = (bones[0][0],) + bones[3][1:]
        err = raises(e.retargeter, bad, builtin=cg.BuiltinMap.UNITY_HUMANOID)
        assert err.status == Status.ERR_INVALID_ARGUMENT and "both named" in err.message
        err = raises(e.retargeter, bones, map=[("tail", names[0])])
        assert "not an SMPL-X joint" in err.message
        err = raises(cg.builtin_map, 7)
        assert err.status == Status.ERR_INVALID_ARGUMENT



def test_installed_package_carries_its_library():
    """Imported from the installed package, which loads the library it carries."""
    here = Path(cg.__file__).resolve().parent
    assert here != HERE.parent / "comgrasp_ctypes", f"imported from the source tree: {here}"
    if "COMGRASP_LIB" not in os.environ:
        assert cg.find_library().parent == here, cg.find_library()


def test_write_bvh_from_any_coordinate_system():
    """The same motion from a glTF and a Unity engine gives the same BVH; read back by a BVH
    parser from PyPI, its forward kinematics lands on the engine's joints (bvh_check.py)."""
    import importlib.util
    import tempfile

    import numpy as np

    spec = importlib.util.spec_from_file_location("bvh_check", os.environ["COMGRASP_BVH_CHECK"])
    check = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(check)
    out = Path(tempfile.mkdtemp(prefix="comgrasp-bvh-"))
    texts = {}
    for coords in (Coords.GLTF, Coords.UNITY):
        with engine(coords=coords, enable_fk=True) as e:
            with e.start("Someone lifts the mug with both hands", seed=4, min_len=3, max_len=3) as s:
                frames = s.frames()
            body, obj = out / f"{coords.name}.bvh", out / f"{coords.name}.object.bvh"
            e.write_bvh(frames, body, obj)
            texts[coords] = (body.read_text(), obj.read_text())
            if coords == Coords.GLTF:
                np.savez(out / "frames.npz",
                         joint_positions=np.array([[list(j) for j in f.joint_positions] for f in frames], np.float32),
                         object_translation=np.array([list(f.object_translation) for f in frames], np.float32),
                         object_rotation=np.array([list(f.object_rotation) for f in frames], np.float32))
                assert check.main(body, obj, out / "frames.npz", BUNDLE) == 0, "BVH FK off the engine's joints"
                # frames=0 is a valid file; a NaN frame or a bad path is an error, nothing written
                e.write_bvh([], out / "empty.bvh")
                assert "Frames: 0" in (out / "empty.bvh").read_text()
                bad = CgFrame()
                ctypes.memmove(ctypes.byref(bad), ctypes.byref(frames[0]), ctypes.sizeof(CgFrame))
                bad.root_rotation[0] = float("nan")
                err = raises(e.write_bvh, [bad], out / "nan.bvh")
                assert err.status == Status.ERR_INVALID_ARGUMENT and "non-finite" in err.message
                assert not (out / "nan.bvh").exists()
                err = raises(e.write_bvh, frames, out / "missing-dir" / "x.bvh")
                assert err.status == Status.ERR_IO, err
    def numbers(t):
        return np.array([float(v) for v in t.split("MOTION", 1)[1].split()[5:]])
    for i in range(2):
        a, b = texts[Coords.GLTF][i], texts[Coords.UNITY][i]
        assert a.split("MOTION")[0] == b.split("MOTION")[0], "the same hierarchy"
        assert np.abs(numbers(a) - numbers(b)).max() < 1e-3, "glTF and Unity frames give the same BVH"


def main() -> int:
    tests = [(n, f) for n, f in sorted(globals().items()) if n.startswith("test_") and callable(f)]
    failed = 0
    for name, fn in tests:
        try:
            fn()
            print(f"ok {name}")
        except Exception as e:
            import traceback

            failed += 1
            print(f"FAILED {name}: {e!r}")
            traceback.print_exc()
    print(f"python: {len(tests) - failed} passed, {failed} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

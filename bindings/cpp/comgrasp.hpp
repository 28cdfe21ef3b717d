// comgrasp.hpp: header-only C++17 wrapper over the ComGrasp C ABI (include/comgrasp.h).
//
// Why a wrapper: the C API is handle + status based; in C++ the natural shape is RAII
// (a handle is destroyed exactly once, by its owner's destructor) and exceptions for
// failures that are not part of the normal flow. What stays C-like on purpose:
//   * frames are the C struct `cg_frame` (alias `comgrasp::Frame`), written into a
//     caller-owned object, so polling never allocates;
//   * `Stream::poll_status` is `noexcept` and returns the raw status, for hot loops and
//     code built without exceptions in mind (game engines);
//   * exceptions carry the status and copy `cg_last_error()` at the throw site (the C
//     message is thread-local and overwritten by the next failing call).
//
//   comgrasp::Engine engine(comgrasp::EngineConfig().bundle_path("models/tiny"));
//   comgrasp::Stream stream = engine.start("A woman drinks from the mug");
//   comgrasp::Frame f;
//   while (stream.wait(f, std::chrono::milliseconds(100)) != comgrasp::Poll::End) { ... }
//
// Shared memory (iceoryx2): an engine configured with `.publish_name("game")` also publishes
// every frame and stream event; a `comgrasp::Subscriber` in any process reads them:
//
//   comgrasp::Subscriber sub("game");
//   comgrasp::Frame f;
//   while (sub.receive(f)) { ... f.stream_id, f.frame_index ... }    // never blocks
//
// Thread rules are the C ABI's: an Engine may be used from any thread at once; a Stream or
// a Subscriber from one thread at a time, except `Stream::cancel()`, which any thread may
// call at any time.
#ifndef COMGRASP_HPP
#define COMGRASP_HPP

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "comgrasp.h"

namespace comgrasp {

using Frame = cg_frame;
using Status = cg_status;
using StreamEvent = cg_stream_event;
using SubscriberStats = cg_subscriber_stats;
using PublisherStats = cg_publisher_stats;

/// Coordinate system of an engine's frames (see `cg_coordinate_system`).
enum class Coords : int {
    Native = CG_COORDS_NATIVE,
    Gltf = CG_COORDS_GLTF,
    Unity = CG_COORDS_UNITY,
    Unreal = CG_COORDS_UNREAL,
};

/// The normal outcomes of a poll; errors are thrown (or returned by `poll_status`).
enum class Poll : int {
    Frame = CG_OK,          ///< a frame was written
    Pending = CG_PENDING,   ///< nothing yet, poll again later
    End = CG_END,           ///< finished, every frame delivered
    Cancelled = CG_CANCELLED,
};

/// The library's version ("MAJOR.MINOR.PATCH"; a static string).
inline const char *version() noexcept { return cg_version_string(); }

/// The name and description of a status code (a static string; any value is safe).
inline const char *status_string(Status status) noexcept {
    return cg_status_string(static_cast<int32_t>(status));
}

/// A failed `cg_*` call: its status plus the library's message, copied when thrown.
class Error : public std::runtime_error {
public:
    Error(const char *call, Status status) : Error(call, status, cg_last_error()) {}
    /// The `CG_ERR_*` code.
    Status status() const noexcept { return status_; }
    /// The library's message alone (`what()` also names the call and the status).
    const std::string &native_message() const noexcept { return message_; }

private:
    Error(const char *call, Status status, std::string message)
        : std::runtime_error(std::string(call) + ": " + cg_status_string(status) + ": " + message),
          status_(status), message_(std::move(message)) {}
    Status status_;
    std::string message_;
};

namespace detail {
/// Throws for errors (negative codes); passes the normal outcomes (>= 0) through.
inline Status check(const char *call, Status st) {
    if (static_cast<int32_t>(st) < 0) throw Error(call, st);
    return st;
}
}  // namespace detail

/// Throws `std::runtime_error` if the loaded library was built from a different header
/// (the usual failure when a stale shared library is picked up). Engine's constructor
/// calls it, so hosts rarely need to.
inline void check_abi() {
    if (cg_abi_version() != CG_ABI_VERSION || cg_frame_size() != sizeof(cg_frame))
        throw std::runtime_error("comgrasp: library ABI " + std::to_string(cg_abi_version()) +
                                 " / frame size " + std::to_string(cg_frame_size()) +
                                 " does not match comgrasp.h");
}

/// Engine settings; a builder over `cg_engine_config` (defaults from `cg_engine_config_init`).
class EngineConfig {
public:
    EngineConfig() { cg_engine_config_init(&raw_); }
    EngineConfig &bundle_path(std::string path) { path_ = std::move(path); return *this; }
    EngineConfig &coordinate_system(Coords c) {
        raw_.coordinate_system = static_cast<cg_coordinate_system>(c);
        return *this;
    }
    EngineConfig &enable_fk(bool on = true) { raw_.enable_fk = on ? 1u : 0u; return *this; }
    EngineConfig &ring_capacity(uint32_t frames) { raw_.ring_capacity = frames; return *this; }
    EngineConfig &max_streams(uint32_t n) { raw_.max_streams = n; return *this; }
    /// Runtime options (0 = automatic; see `cg_engine_config`): `CG_BACKEND_*` values,
    /// 1 or 2 threads, 1..`CG_MAX_DECODE_GROUP` tokens per decode, `CG_OVERLAP_*`, `CG_ISA_*`.
    EngineConfig &step_backend(uint32_t b) { raw_.step_backend = b; return *this; }
    EngineConfig &decoder_backend(uint32_t b) { raw_.decoder_backend = b; return *this; }
    EngineConfig &step_threads(uint32_t n) { raw_.step_threads = n; return *this; }
    EngineConfig &decoder_threads(uint32_t n) { raw_.decoder_threads = n; return *this; }
    EngineConfig &decode_group(uint32_t tokens) { raw_.decode_group = tokens; return *this; }
    EngineConfig &overlap(uint32_t mode) { raw_.overlap = mode; return *this; }
    EngineConfig &max_isa(uint32_t isa) { raw_.max_isa = isa; return *this; }
    /// How streams are driven: `CG_SCHEDULING_*` (default: the crowd scheduler), and its
    /// threads (0 = cores minus one).
    EngineConfig &scheduling(uint32_t mode) { raw_.scheduling = mode; return *this; }
    EngineConfig &scheduler_threads(uint32_t n) { raw_.scheduler_threads = n; return *this; }
    /// Also publish every frame and stream event over shared memory under `name` (1..64
    /// ASCII letters, digits, '_', '-', '.'), for `Subscriber`s in any process.
    EngineConfig &publish_name(std::string name) {
        publish_ = std::move(name);
        has_publish_ = true;
        return *this;
    }

    /// The C struct, its `bundle_path` and `publish_name` pointing into this object: valid
    /// while it lives unchanged. (The strings are std::strings so copies of the builder stay
    /// valid.)
    cg_engine_config raw() const {
        cg_engine_config c = raw_;
        c.bundle_path = path_.empty() ? nullptr : path_.c_str();
        c.publish_name = has_publish_ ? publish_.c_str() : nullptr;
        return c;
    }

private:
    cg_engine_config raw_{};
    std::string path_;
    std::string publish_;
    bool has_publish_ = false;
};

/// Per-stream sampling overrides; a builder over `cg_stream_config`. Each setter also
/// clears the field's `CG_USE_DEFAULT_*` bit, so unset fields keep the bundle's defaults.
class StreamConfig {
public:
    StreamConfig() { cg_stream_config_init(&raw_); }
    StreamConfig &seed(uint64_t v) { raw_.seed = v; return use(CG_USE_DEFAULT_SEED); }
    StreamConfig &temperature(double v) { raw_.temperature = v; return use(CG_USE_DEFAULT_TEMPERATURE); }
    StreamConfig &top_k(uint32_t v) { raw_.top_k = v; return use(CG_USE_DEFAULT_TOP_K); }
    StreamConfig &min_len(uint32_t v) { raw_.min_len = v; return use(CG_USE_DEFAULT_MIN_LEN); }
    StreamConfig &max_len(uint32_t v) { raw_.max_len = v; return use(CG_USE_DEFAULT_MAX_LEN); }
    /// Classifier-free guidance scale, >= 0 (1: the prompt alone).
    StreamConfig &guidance(double v) { raw_.guidance = v; return use(CG_USE_DEFAULT_GUIDANCE); }
    /// Scene anchoring (engine coordinates): the character's ground point and heading.
    StreamConfig &character(const float (&position)[3], const float (&rotation)[4]) {
        std::copy(position, position + 3, raw_.character_position);
        std::copy(rotation, rotation + 4, raw_.character_rotation);
        raw_.anchor |= CG_ANCHOR_CHARACTER;
        return *this;
    }
    /// Scene anchoring: where the object starts (the character reaches for it, or comes to
    /// it with `place_character()`).
    StreamConfig &object(const float (&position)[3], const float (&rotation)[4]) {
        std::copy(position, position + 3, raw_.object_position);
        std::copy(rotation, rotation + 4, raw_.object_rotation);
        raw_.anchor |= CG_ANCHOR_OBJECT;
        return *this;
    }
    StreamConfig &place_character() {
        raw_.anchor |= CG_ANCHOR_PLACE_CHARACTER;
        return *this;
    }
    /// Start where the ended stream `id` left off (its pose, place and object).
    StreamConfig &continue_from(uint64_t id) {
        raw_.continue_from = id;
        return *this;
    }
    /// The model's raw frames, without the contact-consistency stage.
    StreamConfig &raw_output(bool on) {
        raw_.flags = on ? (raw_.flags | CG_STREAM_RAW_OUTPUT) : (raw_.flags & ~CG_STREAM_RAW_OUTPUT);
        return *this;
    }
    /// Off: the resting object stays where the model put it, not where its hand first
    /// closes on it (which holds the first frame back until that grasp).
    StreamConfig &grasp_placement(bool on) {
        raw_.flags = on ? (raw_.flags & ~CG_STREAM_NO_GRASP_PLACEMENT) : (raw_.flags | CG_STREAM_NO_GRASP_PLACEMENT);
        return *this;
    }
    /// Off: the model's legs are left as they are (its feet may slide), for a host that
    /// runs its own foot IK; on (the default), a foot the model stands on stays planted.
    StreamConfig &foot_lock(bool on) {
        raw_.flags = on ? (raw_.flags & ~CG_STREAM_FREE_FEET) : (raw_.flags | CG_STREAM_FREE_FEET);
        return *this;
    }
    const cg_stream_config &raw() const noexcept { return raw_; }

private:
    StreamConfig &use(uint32_t bit) { raw_.use_defaults &= ~bit; return *this; }
    cg_stream_config raw_{};
};

/// One generation. Move-only; the destructor stops the worker and frees the stream.
class Stream {
public:
    Stream() noexcept = default;
    /// Takes ownership of a handle from `cg_start` (NULL gives an empty Stream).
    explicit Stream(cg_stream *h) noexcept : h_(h) {}
    Stream(Stream &&o) noexcept : h_(std::exchange(o.h_, nullptr)) {}
    Stream &operator=(Stream &&o) noexcept {
        if (this != &o) { reset(); h_ = std::exchange(o.h_, nullptr); }
        return *this;
    }
    Stream(const Stream &) = delete;
    Stream &operator=(const Stream &) = delete;
    ~Stream() { reset(); }

    /// Never blocks, never allocates, never throws: the raw `cg_poll_frame` status.
    Status poll_status(Frame &out) noexcept { return cg_poll_frame(h_, &out); }

    /// `cg_poll_frame`; throws `Error` for errors (including the worker's, e.g. inference).
    Poll poll(Frame &out) { return static_cast<Poll>(detail::check("cg_poll_frame", cg_poll_frame(h_, &out))); }

    /// `cg_stream_wait`: blocks up to `timeout` for a frame (never on a game's main thread).
    Poll wait(Frame &out, std::chrono::milliseconds timeout) {
        return static_cast<Poll>(detail::check("cg_stream_wait", cg_stream_wait(h_, clamp_ms(timeout), &out)));
    }

    /// Never throws: the raw `cg_stream_wait` status (for a consumer thread without exceptions).
    Status wait_status(Frame &out, std::chrono::milliseconds timeout) noexcept {
        return cg_stream_wait(h_, clamp_ms(timeout), &out);
    }

    /// Stops generation within one generator call (~8 ms, default bundle); any thread, also while another
    /// thread polls this stream. Idempotent.
    void cancel() const { detail::check("cg_cancel", cg_cancel(h_)); }

    /// The stream's id (frames carry it as `stream_id`).
    uint64_t id() const {
        uint64_t v = 0;
        detail::check("cg_stream_id", cg_stream_id(h_, &v));
        return v;
    }

    /// What the stream is about: the catalogue object its frames pose (`object_name`), and
    /// whether the prompt named it (`object_named`; 0: the first catalogue object stands in).
    cg_stream_info info() const {
        cg_stream_info v{};
        detail::check("cg_stream_get_info", cg_stream_get_info(h_, &v));
        return v;
    }

    /// Destroys the stream now (as the destructor would); the object becomes empty.
    void reset() noexcept {
        if (h_) cg_stream_destroy(std::exchange(h_, nullptr));
    }
    cg_stream *get() const noexcept { return h_; }
    explicit operator bool() const noexcept { return h_ != nullptr; }

private:
    static uint32_t clamp_ms(std::chrono::milliseconds t) noexcept {
        auto ms = t.count();
        return static_cast<uint32_t>(ms < 0 ? 0 : ms > static_cast<decltype(ms)>(UINT32_MAX) ? UINT32_MAX : ms);
    }
    cg_stream *h_ = nullptr;
};

/// A loaded model bundle. Move-only; the destructor cancels its running streams (their
/// Stream objects stay valid and report `Poll::Cancelled`) and frees the model.
class Engine {
public:
    /// Loads and verifies the bundle (a fraction of a second: do it once).
    explicit Engine(const EngineConfig &cfg) {
        check_abi();
        cg_engine_config c = cfg.raw();
        detail::check("cg_engine_create", cg_engine_create(&c, &h_));
    }
    Engine(Engine &&o) noexcept : h_(std::exchange(o.h_, nullptr)) {}
    Engine &operator=(Engine &&o) noexcept {
        if (this != &o) { reset(); h_ = std::exchange(o.h_, nullptr); }
        return *this;
    }
    Engine(const Engine &) = delete;
    Engine &operator=(const Engine &) = delete;
    ~Engine() { reset(); }

    /// Starts a stream (returns at once; the motion is generated on a worker thread).
    /// `text` is UTF-8 and need not be NUL-terminated.
    Stream start(std::string_view text, const StreamConfig &cfg = StreamConfig()) {
        cg_stream *s = nullptr;
        // A default string_view has a NULL data(); pass "" so it reads as empty text
        // (CG_ERR_INVALID_ARGUMENT), not as a NULL pointer.
        const char *p = text.data() ? text.data() : "";
        detail::check("cg_start", cg_start_utf8(h_, reinterpret_cast<const uint8_t *>(p),
                                                text.size(), &cfg.raw(), &s));
        return Stream(s);
    }

    /// Streams alive (started and not yet destroyed).
    uint32_t stream_count() const {
        uint32_t n = 0;
        detail::check("cg_engine_stream_count", cg_engine_stream_count(h_, &n));
        return n;
    }

    /// Writes frames polled from this engine as BVH: the body to `body_path` and, unless
    /// empty, the object's track to `object_path` (cg_engine_write_bvh).
    void write_bvh(const std::vector<Frame> &frames, const std::string &body_path,
                   const std::string &object_path = std::string()) const {
        detail::check("cg_engine_write_bvh",
                      cg_engine_write_bvh(h_, frames.data(), frames.size(), body_path.c_str(),
                                          object_path.empty() ? nullptr : object_path.c_str()));
    }

    /// Counters of the shared-memory publisher; throws `Error` (`CG_ERR_WRONG_STATE`) when the
    /// engine was created without a publish name.
    PublisherStats publisher_stats() const {
        PublisherStats s{};
        detail::check("cg_engine_publisher_stats", cg_engine_publisher_stats(h_, &s));
        return s;
    }

    void reset() noexcept {
        if (h_) cg_engine_destroy(std::exchange(h_, nullptr));
    }
    cg_engine *get() const noexcept { return h_; }

private:
    cg_engine *h_ = nullptr;
};

/// The prompt of a stream event (its `text` up to the NUL; a view into `ev`).
inline std::string_view event_text(const StreamEvent &ev) noexcept {
    const void *end = std::memchr(ev.text, 0, sizeof ev.text);
    size_t n = end ? static_cast<size_t>(static_cast<const uint8_t *>(end) - ev.text) : sizeof ev.text;
    return std::string_view(reinterpret_cast<const char *>(ev.text), n);
}

/// A shared-memory subscriber on the frames and stream events an engine publishes under a
/// name (its `publish_name`), in this or another process. Works before the publisher exists
/// and across its restarts; frames arrive from opening on (no history). Receiving never
/// blocks and never allocates. Move-only; the destructor closes it. One thread at a time.
class Subscriber {
public:
    Subscriber() noexcept = default;
    /// Opens a subscriber keeping up to `buffer_frames` (1..`CG_MAX_SUBSCRIBER_BUFFER`) unread
    /// frames; beyond that the oldest are overwritten (counted in `stats().frames_dropped`).
    /// Throws `Error`: `CG_ERR_INVALID_ARGUMENT` (bad name or buffer), `CG_ERR_LIMIT`
    /// (the name has 8 subscribers), `CG_ERR_SHM`.
    explicit Subscriber(const std::string &name, uint32_t buffer_frames = CG_MAX_SUBSCRIBER_BUFFER) {
        cg_subscriber_config cfg{};
        detail::check("cg_subscriber_config_init", cg_subscriber_config_init(&cfg));
        cfg.buffer_frames = buffer_frames;
        detail::check("cg_subscriber_open", cg_subscriber_open(name.c_str(), &cfg, &h_));
    }
    /// Takes ownership of a handle from `cg_subscriber_open` (NULL gives an empty Subscriber).
    explicit Subscriber(cg_subscriber *h) noexcept : h_(h) {}
    Subscriber(Subscriber &&o) noexcept : h_(std::exchange(o.h_, nullptr)) {}
    Subscriber &operator=(Subscriber &&o) noexcept {
        if (this != &o) { reset(); h_ = std::exchange(o.h_, nullptr); }
        return *this;
    }
    Subscriber(const Subscriber &) = delete;
    Subscriber &operator=(const Subscriber &) = delete;
    ~Subscriber() { reset(); }

    /// Copies the oldest unread frame into `out` and returns true, or returns false when there
    /// is none (`out` untouched). Frames of all the publisher's streams arrive interleaved;
    /// tell them apart by `stream_id`. Throws `Error` on errors.
    bool receive(Frame &out) {
        return detail::check("cg_subscriber_receive", cg_subscriber_receive(h_, &out)) == CG_OK;
    }

    /// Never throws: the raw `cg_subscriber_receive` status (`CG_OK`, `CG_PENDING` or an error).
    Status receive_status(Frame &out) noexcept { return cg_subscriber_receive(h_, &out); }

    /// Like `receive`, for the stream events (a separate queue: a stream's ENDED event may
    /// arrive before its last frames). `event_text(ev)` is the prompt.
    bool receive_event(StreamEvent &out) {
        return detail::check("cg_subscriber_receive_event", cg_subscriber_receive_event(h_, &out)) == CG_OK;
    }

    /// Counters since opening (received, dropped, publishers connected).
    SubscriberStats stats() const {
        SubscriberStats s{};
        detail::check("cg_subscriber_get_stats", cg_subscriber_get_stats(h_, &s));
        return s;
    }

    /// Closes the subscriber now (as the destructor would); the object becomes empty.
    void reset() noexcept {
        if (h_) cg_subscriber_close(std::exchange(h_, nullptr));
    }
    cg_subscriber *get() const noexcept { return h_; }
    explicit operator bool() const noexcept { return h_ != nullptr; }

private:
    cg_subscriber *h_ = nullptr;
};

/// A host bone: name, parent index (-1: root), rest translation and rotation (x, y, z, w)
/// relative to the parent, in the engine's coordinate system and units.
struct Bone {
    std::string name;
    int32_t parent = -1;
    float rest_translation[3] = {0, 0, 0};
    float rest_rotation[4] = {0, 0, 0, 1};
};

using BonePose = cg_bone_pose;
using RetargetObject = cg_retarget_object;

/// The engine's frames on your character's skeleton (`cg_retargeter`; docs/retargeting.md):
///
///   comgrasp::Retargeter rt(engine, bones, CG_MAP_UE5_MANNEQUIN);
///   std::vector<comgrasp::BonePose> pose(rt.bone_count());
///   comgrasp::RetargetObject obj;
///   rt.retarget(frame, pose.data(), &obj);   // no allocation; pose[i] for bones[i]
class Retargeter {
public:
    /// With a ready map (entries whose bone the skeleton lacks are skipped).
    Retargeter(const Engine &engine, const std::vector<Bone> &bones, cg_builtin_map map) {
        std::vector<cg_bone_desc> d = descs(bones);
        detail::check("cg_retargeter_create_builtin",
                      cg_retargeter_create_builtin(engine.get(), d.data(), d.size(), static_cast<int32_t>(map), &h_));
        n_ = bones.size();
    }
    /// With your own map: (SMPL-X joint, bone name) pairs.
    Retargeter(const Engine &engine, const std::vector<Bone> &bones,
               const std::vector<std::pair<std::string, std::string>> &map) {
        std::vector<cg_bone_desc> d = descs(bones);
        std::vector<cg_bone_map_entry> m;
        m.reserve(map.size());
        for (const auto &e : map) m.push_back(cg_bone_map_entry{e.first.c_str(), e.second.c_str()});
        detail::check("cg_retargeter_create",
                      cg_retargeter_create(engine.get(), d.data(), d.size(), m.data(), m.size(), &h_));
        n_ = bones.size();
    }
    Retargeter(Retargeter &&o) noexcept : h_(std::exchange(o.h_, nullptr)), n_(o.n_) {}
    Retargeter &operator=(Retargeter &&o) noexcept {
        if (this != &o) { reset(); h_ = std::exchange(o.h_, nullptr); n_ = o.n_; }
        return *this;
    }
    Retargeter(const Retargeter &) = delete;
    Retargeter &operator=(const Retargeter &) = delete;
    ~Retargeter() { reset(); }

    size_t bone_count() const noexcept { return n_; }
    /// Fills `out[0..bone_count())` and, when not null, `*object`. No allocation.
    void retarget(const Frame &frame, BonePose *out, RetargetObject *object = nullptr) const {
        detail::check("cg_retarget_frame", cg_retarget_frame(h_, &frame, out, n_, object));
    }
    /// Never throws: the raw `cg_retarget_frame` status.
    Status retarget_status(const Frame &frame, BonePose *out, RetargetObject *object = nullptr) const noexcept {
        return cg_retarget_frame(h_, &frame, out, n_, object);
    }

    void reset() noexcept {
        if (h_) cg_retargeter_destroy(std::exchange(h_, nullptr));
    }
    cg_retargeter *get() const noexcept { return h_; }
    explicit operator bool() const noexcept { return h_ != nullptr; }

private:
    static std::vector<cg_bone_desc> descs(const std::vector<Bone> &bones) {
        std::vector<cg_bone_desc> d(bones.size());
        for (size_t i = 0; i < bones.size(); ++i) {
            d[i].name = bones[i].name.c_str();
            d[i].parent = bones[i].parent;
            std::copy(bones[i].rest_translation, bones[i].rest_translation + 3, d[i].rest_translation);
            std::copy(bones[i].rest_rotation, bones[i].rest_rotation + 4, d[i].rest_rotation);
        }
        return d;
    }
    cg_retargeter *h_ = nullptr;
    size_t n_ = 0;
};

/// A ready map's (SMPL-X joint, bone) pairs.
inline std::vector<std::pair<std::string, std::string>> builtin_map(cg_builtin_map which) {
    size_t n = 0;
    detail::check("cg_builtin_map_size", cg_builtin_map_size(static_cast<int32_t>(which), &n));
    std::vector<std::pair<std::string, std::string>> out;
    for (size_t i = 0; i < n; ++i) {
        const char *j = nullptr, *b = nullptr;
        detail::check("cg_builtin_map_entry", cg_builtin_map_entry(static_cast<int32_t>(which), i, &j, &b));
        out.emplace_back(j, b);
    }
    return out;
}

}  // namespace comgrasp

#endif  // COMGRASP_HPP

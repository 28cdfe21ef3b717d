// ComGraspPoseDriver.h: the engine-facing part of the Unreal plugin's skeletal-mesh component,
// in plain C++17 on the C ABI (no Unreal types, no exceptions: Unreal builds without them),
// so the engine's CI compiles and tests it (tests/unreal_driver.rs runs
// bindings/unreal/tests/pose_driver_test.cpp). UComGraspSkeletalComponent is the thin Unreal
// adapter around it.
//
// A PoseDriver owns one stream and one retargeter onto a host skeleton (bone names, parents,
// rest pose relative to the parent, in the engine's coordinate system: CG_COORDS_UNREAL for
// Unreal, centimetres, z up, left-handed). Each tick it takes the frames that are due (or
// every frame available), and when a new one arrived it poses every bone (local and world
// transforms, in the motion's space) and the object. Allocation-free after construction.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "comgrasp.h"

namespace comgrasp_unreal {

/// One host bone at rest: name, parent index (-1: root), translation and rotation
/// (x, y, z, w) relative to the parent.
struct BoneRest {
    std::string name;
    int32_t parent = -1;
    float translation[3] = {0, 0, 0};
    float rotation[4] = {0, 0, 0, 1};
};

/// What a tick did.
enum class TickResult {
    Idle,      ///< no stream, or no new frame due
    NewPose,   ///< a new frame was taken: poses() and object() changed
    Ended,     ///< the stream ended (every frame taken); the last pose stays
    Failed,    ///< the stream was cancelled or failed: error()
};

class PoseDriver {
public:
    /// A driver for `bones` on `engine` with a ready map (CG_MAP_UE5_MANNEQUIN by default) or
    /// the host's own map (pairs of SMPL-X joint and bone name). On failure ok() is false and
    /// error() says why (e.g. a duplicate bone name).
    PoseDriver(cg_engine *engine, const std::vector<BoneRest> &bones, int32_t builtin_map = CG_MAP_UE5_MANNEQUIN,
               const std::vector<std::pair<std::string, std::string>> *own_map = nullptr)
        : engine_(engine) {
        std::vector<cg_bone_desc> descs(bones.size());
        for (size_t i = 0; i < bones.size(); ++i) {
            descs[i].name = bones[i].name.c_str();
            descs[i].parent = bones[i].parent;
            for (int k = 0; k < 3; ++k) descs[i].rest_translation[k] = bones[i].translation[k];
            for (int k = 0; k < 4; ++k) descs[i].rest_rotation[k] = bones[i].rotation[k];
        }
        cg_status st;
        if (own_map) {
            std::vector<cg_bone_map_entry> map(own_map->size());
            for (size_t i = 0; i < map.size(); ++i) {
                map[i].smplx_joint = (*own_map)[i].first.c_str();
                map[i].bone = (*own_map)[i].second.c_str();
            }
            st = cg_retargeter_create(engine, descs.data(), descs.size(), map.data(), map.size(), &retargeter_);
        } else {
            st = cg_retargeter_create_builtin(engine, descs.data(), descs.size(), builtin_map, &retargeter_);
        }
        if (st != CG_OK) {
            fail("cg_retargeter_create", st);
            retargeter_ = nullptr;
            return;
        }
        poses_.resize(bones.size());
        object_ = cg_retarget_object{};
    }

    PoseDriver(const PoseDriver &) = delete;
    PoseDriver &operator=(const PoseDriver &) = delete;
    ~PoseDriver() {
        stop();
        if (retargeter_) cg_retargeter_destroy(retargeter_);
    }

    bool ok() const { return retargeter_ != nullptr; }
    const std::string &error() const { return error_; }

    /// Starts a stream for `prompt` (UTF-8), stopping one that runs; `config` may be NULL
    /// (the bundle's defaults). With `chain`, it continues from the last stream that ended.
    bool start(const std::string &prompt, const cg_stream_config *config = nullptr, bool chain = false) {
        stop();
        if (!ok()) return false;
        cg_stream_config cfg;
        if (config) {
            cfg = *config;
        } else {
            cg_stream_config_init(&cfg);
        }
        if (chain && last_ended_ != 0) cfg.continue_from = last_ended_;
        const cg_status st = cg_start_utf8(engine_, reinterpret_cast<const uint8_t *>(prompt.data()), prompt.size(), &cfg,
                                           &stream_);
        if (st != CG_OK) {
            stream_ = nullptr;
            return fail("cg_start", st);
        }
        clock_ = 0.0;
        held_ = false;
        return true;
    }

    /// Cancels the stream that runs (the last pose stays).
    void stop() {
        if (stream_) {
            cg_cancel(stream_);
            cg_stream_destroy(stream_);
            stream_ = nullptr;
        }
    }

    /// Advances the motion clock by `dt` seconds and takes the frames due: in real time the
    /// ones whose time has come, otherwise every one available. Never blocks.
    TickResult tick(double dt, bool real_time = true) {
        if (!stream_) return TickResult::Idle;
        clock_ += dt;
        bool fresh = false;
        for (;;) {
            // The next frame goes to the other buffer: the current one is posed below.
            cg_frame &next = frames_[1 - current_];
            if (!held_) {
                const cg_status st = cg_poll_frame(stream_, &next);
                if (st == CG_PENDING) break;
                if (st != CG_OK) {
                    uint64_t id = 0;
                    cg_stream_id(stream_, &id);
                    cg_stream_destroy(stream_);
                    stream_ = nullptr;
                    if (st == CG_END) {
                        last_ended_ = id;
                        if (fresh && !pose()) return TickResult::Failed;
                        return fresh ? TickResult::NewPose : TickResult::Ended;
                    }
                    fail("cg_poll_frame", st);
                    return TickResult::Failed;
                }
                held_ = true;
            }
            if (real_time && next.time_s > clock_) break;
            current_ = 1 - current_;
            held_ = false;
            fresh = true;
        }
        if (!fresh) return TickResult::Idle;
        return pose() ? TickResult::NewPose : TickResult::Failed;
    }

    /// Per bone of the skeleton given at construction: local (relative to the parent) and
    /// world (the motion's space) transforms of the newest pose.
    const std::vector<cg_bone_pose> &poses() const { return poses_; }
    /// The object in the motion's space and in each hand bone's frame, with contacts.
    const cg_retarget_object &object() const { return object_; }
    /// The newest frame taken (its time_s, contacts, ...).
    const cg_frame &frame() const { return frames_[current_]; }
    bool playing() const { return stream_ != nullptr; }
    /// The id of the last stream that ended (what `start(..., chain = true)` continues).
    uint64_t last_ended() const { return last_ended_; }

private:
    bool pose() {
        const cg_status st = cg_retarget_frame(retargeter_, &frames_[current_], poses_.data(), poses_.size(), &object_);
        return st == CG_OK || fail("cg_retarget_frame", st);
    }

    bool fail(const char *call, cg_status st) {
        error_ = std::string(call) + ": " + cg_status_string(st) + ": " + cg_last_error();
        return false;
    }

    cg_engine *engine_ = nullptr;
    cg_retargeter *retargeter_ = nullptr;
    cg_stream *stream_ = nullptr;
    cg_frame frames_[2] = {};  // the newest frame taken, and the next one polled
    int current_ = 0;
    bool held_ = false;  // the next frame was polled and waits for its time
    double clock_ = 0.0;
    uint64_t last_ended_ = 0;
    std::vector<cg_bone_pose> poses_;
    cg_retarget_object object_{};
    std::string error_;
};

}  // namespace comgrasp_unreal

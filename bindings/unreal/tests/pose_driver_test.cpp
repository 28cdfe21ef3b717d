// Test of ComGraspPoseDriver.h (the Unreal component's engine-facing C++) against the real
// library, built without exceptions and RTTI as Unreal builds: tests/unreal_driver.rs.
//
//   pose_driver_test BUNDLE_DIR
//
// A skeleton with the UE5 Mannequin's bone names for the SMPL-X joints and the engine's rest
// joints (CG_COORDS_UNREAL: cm, z up) is posed frame by frame: world positions land on the
// frames' joint positions; real-time ticks take only the frames due; chaining continues from
// the last motion; bad skeletons and prompts are errors, not crashes. Prints "ok".
#include <cmath>
#include <cstdio>
#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "ComGraspPoseDriver.h"

using comgrasp_unreal::BoneRest;
using comgrasp_unreal::PoseDriver;
using comgrasp_unreal::TickResult;

static int failures = 0;
#define CHECK(cond, ...)                                          \
    do {                                                          \
        if (!(cond)) {                                            \
            std::fprintf(stderr, "FAILED %s: ", #cond);           \
            std::fprintf(stderr, __VA_ARGS__);                    \
            std::fprintf(stderr, "\n");                           \
            ++failures;                                           \
        }                                                         \
    } while (0)

static const int kParents[CG_NUM_JOINTS] = {-1, 0,  0,  0,  1,  2,  3,  4,  5,  6,  7,  8,  9,  9,  9,  12, 13, 14, 16,
                                            17, 18, 19, 15, 15, 15, 20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20,
                                            37, 38, 21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53};

int main(int argc, char **argv) {
    if (argc < 2) {
        std::fprintf(stderr, "usage: %s BUNDLE_DIR\n", argv[0]);
        return 2;
    }
    cg_engine_config ec;
    cg_engine_config_init(&ec);
    ec.bundle_path = argv[1];
    ec.coordinate_system = CG_COORDS_UNREAL;
    ec.enable_fk = 1;
    cg_engine *engine = nullptr;
    if (cg_engine_create(&ec, &engine) != CG_OK) {
        std::fprintf(stderr, "engine: %s\n", cg_last_error());
        return 1;
    }
    float rest[CG_NUM_JOINTS][3];
    CHECK(cg_engine_get_rest_joints(engine, rest, CG_NUM_JOINTS) == CG_OK, "%s", cg_last_error());

    // The ready Mannequin map lists the body first (SMPL-X joints 0..21), then the fingers.
    std::vector<BoneRest> bones(CG_NUM_JOINTS);
    size_t n_map = 0;
    cg_builtin_map_size(CG_MAP_UE5_MANNEQUIN, &n_map);
    for (int j = 0; j < CG_NUM_JOINTS; ++j) {
        bones[j].name = "unmapped_" + std::to_string(j);
        bones[j].parent = kParents[j];
        for (int k = 0; k < 3; ++k) bones[j].translation[k] = rest[j][k] - (kParents[j] < 0 ? 0.0f : rest[kParents[j]][k]);
    }
    for (size_t i = 0; i < n_map; ++i) {
        const char *joint = nullptr, *bone = nullptr;
        cg_builtin_map_entry(CG_MAP_UE5_MANNEQUIN, i, &joint, &bone);
        const int j = i < 22 ? static_cast<int>(i) : static_cast<int>(i) + 3;  // fingers start at joint 25
        bones[j].name = bone;
    }

    {
        PoseDriver driver(engine, bones);
        CHECK(driver.ok(), "%s", driver.error().c_str());
        CHECK(driver.tick(0.1) == TickResult::Idle, "no stream yet");
        CHECK(driver.start("A woman drinks from the mug"), "%s", driver.error().c_str());
        // Real time at 60 Hz: never a frame before its time.
        int poses = 0;
        double clock = 0.0, worst = 0.0;
        TickResult r = TickResult::Idle;
        // (a game's ticks: the clock runs at 60 Hz of motion per millisecond of waiting, so
        // generation, not the clock, sets the pace here)
        for (int t = 0; t < 60000 && driver.playing(); ++t) {
            std::this_thread::sleep_for(std::chrono::milliseconds(1));
            clock += 1.0 / 60.0;
            r = driver.tick(1.0 / 60.0);
            if (r == TickResult::NewPose) {
                ++poses;
                const cg_frame &f = driver.frame();
                CHECK(f.time_s <= clock + 1e-9, "frame at %.3f s shown at %.3f s", f.time_s, clock);
                for (int j = 0; j < CG_NUM_JOINTS; ++j)
                    for (int k = 0; k < 3; ++k)
                        worst = std::fmax(worst, std::fabs(driver.poses()[j].world_position[k] - f.joint_positions[j][k]));
            }
            CHECK(r != TickResult::Failed, "%s", driver.error().c_str());
        }
        CHECK(!driver.playing() && driver.frame().is_last == 1, "played to the end");
        CHECK(poses > 10, "%d poses", poses);
        CHECK(worst < 0.1, "worst joint %.4f cm off", worst);  // 1 mm, in centimetres
        CHECK(driver.object().hand_bone[0] == 20 && driver.object().hand_bone[1] == 21, "hand bones %d %d",
              driver.object().hand_bone[0], driver.object().hand_bone[1]);
        const uint64_t first = driver.last_ended();
        CHECK(first != 0, "the ended stream's id");
        std::printf("posed %d frames at 60 Hz, worst joint %.4f cm\n", poses, worst);

        // Chained, drained as fast as generated: the first pose starts where the last ended.
        const float end_pelvis[3] = {driver.poses()[0].world_position[0], driver.poses()[0].world_position[1],
                                     driver.poses()[0].world_position[2]};
        CHECK(driver.start("She puts the mug down", nullptr, true), "%s", driver.error().c_str());
        bool first_pose = true;
        for (int t = 0; t < 60000 && driver.playing(); ++t) {
            std::this_thread::sleep_for(std::chrono::milliseconds(1));
            if (driver.tick(0.0, false) == TickResult::NewPose && first_pose) {
                first_pose = false;
                float d = 0;
                for (int k = 0; k < 3; ++k) d = std::fmax(d, std::fabs(driver.poses()[0].world_position[k] - end_pelvis[k]));
                CHECK(d < 10.0f, "chained motion starts %.1f cm from where the last ended", d);
            }
        }
        CHECK(!first_pose && driver.last_ended() != first, "the chained stream played");

        // Cancel: the pose stays, nothing plays.
        CHECK(driver.start("A man lifts the cube"), "%s", driver.error().c_str());
        driver.stop();
        CHECK(!driver.playing() && driver.tick(1.0) == TickResult::Idle, "stopped");
        CHECK(!driver.start("   "), "a blank prompt starts nothing");
        CHECK(driver.error().find("CG_ERR_INVALID_ARGUMENT") != std::string::npos, "%s", driver.error().c_str());
    }
    {
        // The heading UComGraspSkeletalComponent anchors with. The engine's heading is where the
        // pelvis faces (its local +z, which the root rotation turns in Unreal's basis too),
        // projected to the ground: unturned it faces -y; yawed by +90 degrees (FRotator(0, 90,
        // 0)) it faces the actor's forward, +x. On the embedded default model: the test
        // bundle's random weights do not stand the pelvis upright.
        cg_engine_config dc;
        cg_engine_config_init(&dc);
        dc.coordinate_system = CG_COORDS_UNREAL;
        cg_engine *default_engine = nullptr;
        CHECK(cg_engine_create(&dc, &default_engine) == CG_OK, "%s", cg_last_error());
        for (int turned = 0; turned < 2; ++turned) {
            PoseDriver driver(default_engine, bones);
            cg_stream_config cfg;
            cg_stream_config_init(&cfg);
            cfg.anchor = CG_ANCHOR_CHARACTER;
            const float s = std::sqrt(0.5f);
            const float yaw90[4] = {0, 0, s, s}, none[4] = {0, 0, 0, 1};
            for (int k = 0; k < 4; ++k) cfg.character_rotation[k] = turned ? yaw90[k] : none[k];
            cfg.min_len = cfg.max_len = 1;
            cfg.use_defaults &= ~static_cast<uint32_t>(CG_USE_DEFAULT_MIN_LEN | CG_USE_DEFAULT_MAX_LEN);
            CHECK(driver.start("A woman drinks from the mug", &cfg), "%s", driver.error().c_str());
            TickResult r = TickResult::Idle;
            for (int t = 0; t < 60000 && r != TickResult::NewPose; ++t) {
                std::this_thread::sleep_for(std::chrono::milliseconds(1));
                r = driver.tick(0.0, false);
            }
            // v' = v + w t + q x t with t = 2 q x v, for v = (0, 0, 1)
            const float *q = driver.frame().root_rotation;
            const float tx = 2 * q[1], ty = -2 * q[0], tz = 0;
            const float fx = q[3] * tx + (q[1] * tz - q[2] * ty), fy = q[3] * ty + (q[2] * tx - q[0] * tz);
            const float n = std::sqrt(fx * fx + fy * fy);
            const bool ok = n > 0.5f && (turned ? std::fabs(fy / n) < 1e-3f && fx > 0 : std::fabs(fx / n) < 1e-3f && fy < 0);
            CHECK(ok, "%s: pelvis faces (%.3f, %.3f) on the ground", turned ? "yawed" : "unturned", fx, fy);
        }
        cg_engine_destroy(default_engine);
    }
    {
        std::vector<BoneRest> dup = bones;
        dup[3].name = dup[0].name;
        PoseDriver bad(engine, dup);
        CHECK(!bad.ok() && bad.error().find("both named") != std::string::npos, "%s", bad.error().c_str());
        CHECK(!bad.start("A mug") && bad.tick(1.0) == TickResult::Idle, "a failed driver does nothing");
        std::vector<std::pair<std::string, std::string>> own = {{"pelvis", bones[0].name}, {"left_wrist", "no_such_bone"}};
        PoseDriver unknown(engine, bones, 0, &own);
        CHECK(!unknown.ok(), "a map onto an unknown bone");
    }
    cg_engine_destroy(engine);
    if (failures) {
        std::fprintf(stderr, "%d failures\n", failures);
        return 1;
    }
    std::printf("ok\n");
    return 0;
}

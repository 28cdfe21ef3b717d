// Example and smoke test of comgrasp.hpp: streams one motion, checks that errors arrive as
// comgrasp::Error with the right status, that a cancel from another thread is seen, and that
// a shared-memory comgrasp::Subscriber receives exactly the frames an engine's stream polls.
//
//   c++ -std=c++17 -Wall -Wextra -I include -I bindings/cpp bindings/cpp/example.cpp
//       -L target/debug -lcomgrasp -pthread -o example
//   LD_LIBRARY_PATH=target/debug ./example models/tiny "The man lifts a small cube."
//
// Exit code 0 when every check passed, 1 otherwise (message on stderr).
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <string>
#include <thread>
#include <vector>

#ifdef _WIN32
#include <process.h>
static long process_id() { return static_cast<long>(_getpid()); }
#else
#include <unistd.h>
static long process_id() { return static_cast<long>(getpid()); }
#endif

#include "comgrasp.hpp"

using namespace std::chrono_literals;

// 5. Shared memory: an engine publishing under a name unique to this process, and a
// subscriber on it in this same process, opened before the stream starts. It must receive
// every polled frame (same stream id, index and bytes), STARTED and ENDED events, and drop
// nothing. Returns the number of failed checks (printed on stderr).
static int check_subscriber(const char *bundle, const char *prompt) {
    int failures = 0;
    auto fail = [&failures](const char *what) {
        std::fprintf(stderr, "subscriber check failed: %s\n", what);
        failures++;
    };
    const std::string name = "cpp-example-" + std::to_string(process_id());
    comgrasp::Engine engine(comgrasp::EngineConfig().bundle_path(bundle).publish_name(name));
    comgrasp::Subscriber sub(name);
    if (engine.publisher_stats().subscribers != 1 || sub.stats().publishers != 1) fail("not connected");

    std::vector<comgrasp::Frame> polled, received;
    std::vector<comgrasp::StreamEvent> events;
    comgrasp::Frame f{}, r{};
    comgrasp::StreamEvent ev{};
    comgrasp::Stream stream = engine.start(prompt, comgrasp::StreamConfig().seed(5));
    const uint64_t id = stream.id();
    const cg_stream_info info = stream.info();
    if (info.stream_id != id || info.object_name[0] == '\0') fail("stream info: no id or object name");
    std::printf("stream %llu: object %s (%s)\n", static_cast<unsigned long long>(id), info.object_name,
                info.object_named ? "named by the prompt" : "the prompt names none");
    auto drain = [&] {
        while (sub.receive(r)) received.push_back(r);
        while (sub.receive_event(ev)) events.push_back(ev);
    };
    const auto deadline = std::chrono::steady_clock::now() + 120s;
    comgrasp::Poll p;
    while ((p = stream.wait(f, 5ms)) != comgrasp::Poll::End) {
        if (p == comgrasp::Poll::Frame) polled.push_back(f);
        drain();
        if (std::chrono::steady_clock::now() > deadline) {
            fail("the stream did not end in time");
            return failures;
        }
    }
    // Every frame and the ENDED event were published before the stream reported End.
    const auto grace = std::chrono::steady_clock::now() + 5s;
    for (drain(); (received.size() < polled.size() || events.size() < 2) && std::chrono::steady_clock::now() < grace; drain())
        std::this_thread::sleep_for(1ms);

    std::printf("subscriber: %zu frames received, %zu polled, %zu events\n", received.size(), polled.size(),
                events.size());
    if (polled.empty() || received.size() != polled.size()) fail("frames received != frames polled");
    for (size_t i = 0; i < received.size() && i < polled.size(); i++) {
        const comgrasp::Frame &a = polled[i], &b = received[i];
        if (b.stream_id != id || b.frame_index != i) { fail("received stream_id/frame_index sequence"); break; }
        if (std::memcmp(&a, &b, sizeof a) != 0) { fail("a received frame differs from the polled one"); break; }
    }
    if (events.size() != 2 || events[0].kind != CG_STREAM_EVENT_STARTED || events[1].kind != CG_STREAM_EVENT_ENDED)
        fail("events are not STARTED, ENDED");
    else if (events[0].stream_id != id || events[1].stream_id != id || events[0].frame_count != 0 ||
             events[1].frame_count != polled.size() || comgrasp::event_text(events[0]) != prompt)
        fail("event contents");
    comgrasp::SubscriberStats ss = sub.stats();
    if (ss.frames_received != polled.size() || ss.frames_dropped != 0 || ss.events_received != 2 || ss.events_dropped != 0)
        fail("subscriber stats");
    comgrasp::PublisherStats ps = engine.publisher_stats();
    if (ps.frames_published != polled.size() || ps.frames_skipped != 0 || ps.events_published != 2) fail("publisher stats");

    // Move-only RAII: the moved-from subscriber is empty and a call on it throws.
    comgrasp::Subscriber moved = std::move(sub);
    if (sub || !moved) fail("move");
    try {
        sub.receive(r);
        fail("receive on an empty subscriber did not throw");
    } catch (const comgrasp::Error &e) {
        if (e.status() != CG_ERR_NULL_POINTER) fail("receive on an empty subscriber: wrong status");
    }
    moved.reset();
    if (engine.publisher_stats().subscribers != 0) fail("the publisher still counts the closed subscriber");
    // Bad names are errors with a status.
    try {
        comgrasp::Subscriber bad("no/slash");
        fail("a bad name was accepted");
    } catch (const comgrasp::Error &e) {
        if (e.status() != CG_ERR_INVALID_ARGUMENT) fail("bad name: wrong status");
    }
    try {
        comgrasp::Engine quiet(comgrasp::EngineConfig().bundle_path(bundle));
        quiet.publisher_stats();
        fail("publisher_stats without a publish name did not throw");
    } catch (const comgrasp::Error &e) {
        if (e.status() != CG_ERR_WRONG_STATE) fail("publisher_stats without a publish name: wrong status");
    }
    if (failures == 0)
        std::printf("subscriber received every polled frame: %zu, events STARTED ENDED, dropped 0\n", polled.size());
    return failures;
}

int main(int argc, char **argv) {
    if (argc < 2) {
        std::fprintf(stderr, "usage: %s BUNDLE_DIR [PROMPT]\n", argv[0]);
        return 2;
    }
    const char *prompt = argc > 2 ? argv[2] : "A woman drinks from the mug";
    try {
        comgrasp::Engine engine(comgrasp::EngineConfig()
                                    .bundle_path(argv[1])
                                    .coordinate_system(comgrasp::Coords::Gltf)
                                    .enable_fk());

        std::printf("comgrasp %s\n", comgrasp::version());

        // 1. A whole stream with the throwing API.
        comgrasp::Stream stream = engine.start(prompt, comgrasp::StreamConfig().seed(3).temperature(0.8));
        comgrasp::Frame f{};
        unsigned long frames = 0, contact[2] = {0, 0};
        bool last_flagged = false;
        comgrasp::Poll r;
        while ((r = stream.wait(f, 100ms)) != comgrasp::Poll::End) {
            if (r != comgrasp::Poll::Frame) continue;  // Pending: keep waiting
            frames++;
            contact[0] += f.contact[0];
            contact[1] += f.contact[1];
            last_flagged = f.is_last != 0;
        }
        std::printf("frames: %lu (last at %.2f s), last frame flagged: %s\n", frames, f.time_s,
                    last_flagged ? "yes" : "no");
        std::printf("pelvis (glTF, y up): %.3f %.3f %.3f\n", f.joint_positions[0][0],
                    f.joint_positions[0][1], f.joint_positions[0][2]);
        std::printf("contact frames: left %lu, right %lu\n", contact[0], contact[1]);
        if (frames == 0 || !last_flagged) {
            std::fprintf(stderr, "stream ended without frames or without is_last\n");
            return 1;
        }

        // 2. Errors are exceptions carrying the status.
        try {
            engine.start("   ");
            std::fprintf(stderr, "blank prompt was accepted\n");
            return 1;
        } catch (const comgrasp::Error &e) {
            if (e.status() != CG_ERR_INVALID_ARGUMENT || e.native_message().empty()) throw;
            std::printf("blank prompt rejected: %s\n", e.what());
        }

        // 2b. Scene anchoring (glTF coordinates, y up): the object starts where the host puts it;
        // one out of reach is an error.
        {
            const float here[3] = {1.0f, 0.0f, 2.0f}, facing[4] = {0, 0, 0, 1}, mug[3] = {1.1f, 0.8f, 1.45f};
            comgrasp::Stream a = engine.start(prompt, comgrasp::StreamConfig().min_len(1).max_len(1).character(here, facing).object(mug, facing));
            comgrasp::Frame g{};
            while (a.wait(g, 5ms) != comgrasp::Poll::Frame) {}
            for (int i = 0; i < 3; ++i)
                if (std::fabs(g.object_translation[i] - mug[i]) > 1e-5f) {
                    std::fprintf(stderr, "anchored object at %f %f %f\n", g.object_translation[0], g.object_translation[1], g.object_translation[2]);
                    return 1;
                }
            const float far[3] = {9.0f, 0.8f, 2.0f};
            try {
                engine.start(prompt, comgrasp::StreamConfig().character(here, facing).object(far, facing));
                std::fprintf(stderr, "an object 8 m away was within reach\n");
                return 1;
            } catch (const comgrasp::Error &e) {
                if (e.status() != CG_ERR_INVALID_ARGUMENT) throw;
            }
        }

        // 3. Cancel from another thread while this one polls with the noexcept API.
        comgrasp::Stream s2 = engine.start(prompt, comgrasp::StreamConfig().min_len(18).max_len(18));
        std::thread canceller([&s2] { s2.cancel(); });
        comgrasp::Status st;
        while ((st = s2.poll_status(f)) == CG_OK || st == CG_PENDING) std::this_thread::sleep_for(1ms);
        canceller.join();
        if (st != CG_CANCELLED && st != CG_END) {
            std::fprintf(stderr, "unexpected status after cancel: %s\n", comgrasp::status_string(st));
            return 1;
        }
        // The noexcept wait keeps reporting the final status.
        if (s2.wait_status(f, 10ms) != st) {
            std::fprintf(stderr, "wait_status after the end changed the status\n");
            return 1;
        }
        std::printf("second stream: %s, %u streams alive\n", comgrasp::status_string(st), engine.stream_count());

        // 4. Moves transfer ownership; the moved-from object is empty and destroys nothing.
        comgrasp::Stream moved = std::move(s2);
        if (s2 || !moved) return 1;
        moved.reset();
        stream.reset();
        if (engine.stream_count() != 0) {
            std::fprintf(stderr, "streams still alive after reset\n");
            return 1;
        }

        // 4b. Retargeting onto a skeleton named as the UE5 Mannequin: the engine's own
        // skeleton (its rest joints), so the mapped bones land on the frames' joints.
        {
            comgrasp::Engine fk(comgrasp::EngineConfig().bundle_path(argv[1]).enable_fk());
            float rest[CG_NUM_JOINTS][3];
            comgrasp::detail::check("cg_engine_get_rest_joints", cg_engine_get_rest_joints(fk.get(), rest, CG_NUM_JOINTS));
            static const int parents[CG_NUM_JOINTS] = {-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19,
                                                       15, 15, 15, 20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
                                                       21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53};
            const auto map = comgrasp::builtin_map(CG_MAP_UE5_MANNEQUIN);
            std::vector<comgrasp::Bone> bones(CG_NUM_JOINTS);
            for (int j = 0; j < CG_NUM_JOINTS; ++j) {
                bones[j].name = "unmapped_" + std::to_string(j);
                bones[j].parent = parents[j];
                for (int k = 0; k < 3; ++k) bones[j].rest_translation[k] = rest[j][k] - (parents[j] < 0 ? 0.0f : rest[parents[j]][k]);
            }
            // The map lists the body first, in SMPL-X joint order (0..21), then the fingers.
            static const int fingers[30] = {25, 26, 27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39,
                                            40, 41, 42, 43, 44, 45, 46, 47, 48, 49, 50, 51, 52, 53, 54};
            for (size_t i = 0; i < map.size(); ++i) bones[i < 22 ? i : fingers[i - 22]].name = map[i].second;
            comgrasp::Retargeter rt(fk, bones, CG_MAP_UE5_MANNEQUIN);
            std::vector<comgrasp::BonePose> pose(rt.bone_count());
            comgrasp::RetargetObject obj{};
            comgrasp::Stream r = fk.start(prompt, comgrasp::StreamConfig().min_len(2).max_len(2));
            comgrasp::Frame g{};
            int n = 0;
            std::vector<comgrasp::Frame> polled;
            while (r.wait(g, 100ms) != comgrasp::Poll::End) {
                polled.push_back(g);
                rt.retarget(g, pose.data(), &obj);
                for (int j = 0; j < CG_NUM_JOINTS; ++j)
                    for (int k = 0; k < 3; ++k)
                        if (std::fabs(pose[j].world_position[k] - g.joint_positions[j][k]) > 1e-3f) {
                            std::fprintf(stderr, "retargeted joint %d off by %f\n", j, pose[j].world_position[k] - g.joint_positions[j][k]);
                            return 1;
                        }
                ++n;
            }
            std::printf("retargeted %d frames onto %zu bones (%s -> %s ...)\n", n, rt.bone_count(), map[0].first.c_str(), map[0].second.c_str());
            // The same frames as a BVH file for animation tools (body only).
            const std::string bvh = (std::filesystem::temp_directory_path() /
                                     ("comgrasp_example_" + std::to_string(static_cast<unsigned long long>(r.id())) + ".bvh"))
                                        .string();
            fk.write_bvh(polled, bvh);
            std::FILE *in = std::fopen(bvh.c_str(), "r");
            char head[32] = {0};
            if (!in || std::fread(head, 1, 21, in) != 21 || std::strncmp(head, "HIERARCHY\nROOT pelvis", 21) != 0) {
                std::fprintf(stderr, "BVH file %s missing or wrong\n", bvh.c_str());
                return 1;
            }
            std::fclose(in);
            std::remove(bvh.c_str());
            std::printf("wrote BVH of %zu frames\n", polled.size());
        }

        // 5. A shared-memory subscriber in this process (see check_subscriber).
        if (check_subscriber(argv[1], prompt) != 0) return 1;
        std::printf("ok\n");
        return 0;
    } catch (const std::exception &e) {
        std::fprintf(stderr, "error: %s\n", e.what());
        return 1;
    }
}

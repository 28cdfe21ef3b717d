// Example and smoke test of comgrasp.hpp: streams one motion, checks that errors arrive as
// comgrasp::Error with the right status, and that a cancel from another thread is seen.
//
//   c++ -std=c++17 -Wall -Wextra -I include -I bindings/cpp bindings/cpp/example.cpp
//       -L target/debug -lcomgrasp -pthread -o example
//   LD_LIBRARY_PATH=target/debug ./example models/tiny "The man lifts a small cube."
//
// Exit code 0 when every check passed, 1 otherwise (message on stderr).
#include <chrono>
#include <cstdio>
#include <thread>

#include "comgrasp.hpp"

using namespace std::chrono_literals;

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
        std::printf("ok\n");
        return 0;
    } catch (const std::exception &e) {
        std::fprintf(stderr, "error: %s\n", e.what());
        return 1;
    }
}

/* Streams one generated grasp motion through the ComGrasp C ABI and prints a summary.
 *
 *   cc -std=c11 -Wall -Wextra -I include examples_c/stream.c -L target/debug -lcomgrasp -o stream
 *   LD_LIBRARY_PATH=target/debug ./stream models/tiny "A woman drinks from the mug"
 *
 * Exit code 0 when the stream ended normally (CG_END), 1 on any error (message on stderr).
 * The loop is the one a game engine runs once per tick, minus the tick: poll, and on
 * CG_PENDING come back later (here: after waiting up to 100 ms with cg_stream_wait). */
#include <stdio.h>

#include "comgrasp.h"

/* Reports a failed call: the status name plus the library's message for this thread. */
static int fail(const char *what, cg_status st) {
    fprintf(stderr, "%s failed: %s: %s\n", what, cg_status_string(st), cg_last_error());
    return 1;
}

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: %s BUNDLE_DIR [PROMPT]\n", argv[0]);
        return 2;
    }
    const char *prompt = argc > 2 ? argv[2] : "A woman drinks from the mug";
    if (cg_abi_version() != CG_ABI_VERSION || cg_frame_size() != sizeof(cg_frame)) {
        fprintf(stderr, "library does not match comgrasp.h (ABI %u, frame %zu bytes)\n",
                (unsigned)cg_abi_version(), cg_frame_size());
        return 1;
    }

    cg_engine_config ecfg;
    cg_engine_config_init(&ecfg);
    ecfg.bundle_path = argv[1];
    ecfg.enable_fk = 1;
    cg_engine *engine = NULL;
    cg_status st = cg_engine_create(&ecfg, &engine);
    if (st != CG_OK) return fail("cg_engine_create", st);

    cg_stream_config scfg;
    cg_stream_config_init(&scfg);
    scfg.seed = 42; /* override one field: set it and clear its use-default bit */
    scfg.use_defaults &= ~(uint32_t)CG_USE_DEFAULT_SEED;
    cg_stream *stream = NULL;
    st = cg_start(engine, prompt, &scfg, &stream);
    if (st != CG_OK) {
        int rc = fail("cg_start", st);
        cg_engine_destroy(engine);
        return rc;
    }

    cg_frame frame;  /* caller-owned; cg_stream_wait only copies into it */
    cg_frame last = {0};
    unsigned long frames = 0, contact_frames[2] = {0, 0};
    for (;;) {
        st = cg_stream_wait(stream, 100, &frame);
        if (st == CG_OK) {
            frames++;
            contact_frames[0] += frame.contact[0];
            contact_frames[1] += frame.contact[1];
            last = frame;
        } else if (st != CG_PENDING) {
            break; /* CG_END, CG_CANCELLED or an error */
        }
    }
    int rc = 0;
    if (st != CG_END) rc = fail("cg_stream_wait", st);

    /* A wrist's world position is the object centre plus its wrist-to-object vector. */
    const float *c = last.object_centre;
    printf("prompt: %s\n", prompt);
    printf("frames: %lu (last at %.2f s)\n", frames, last.time_s);
    printf("status: %s\n", st == CG_END ? "CG_END" : cg_status_string(st));
    printf("last frame flagged: %s\n", last.is_last ? "yes" : "no");
    printf("object: %.3f %.3f %.3f\n", last.object_translation[0], last.object_translation[1],
           last.object_translation[2]);
    printf("left wrist: %.3f %.3f %.3f\n", c[0] + last.left_wrist_to_object[0],
           c[1] + last.left_wrist_to_object[1], c[2] + last.left_wrist_to_object[2]);
    printf("right wrist: %.3f %.3f %.3f\n", c[0] + last.right_wrist_to_object[0],
           c[1] + last.right_wrist_to_object[1], c[2] + last.right_wrist_to_object[2]);
    printf("contact frames: left %lu, right %lu\n", contact_frames[0], contact_frames[1]);

    /* Streams survive their engine, but destroying the stream first is the tidy order. */
    if ((st = cg_stream_destroy(stream)) != CG_OK) rc = fail("cg_stream_destroy", st);
    if ((st = cg_engine_destroy(engine)) != CG_OK) rc = fail("cg_engine_destroy", st);
    return rc;
}

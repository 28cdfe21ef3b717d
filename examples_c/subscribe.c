/* A shared-memory consumer in plain C: reads the frames an engine in ANOTHER process
 * publishes (cg_engine_config.publish_name), without running a model.
 *
 *   subscribe NAME [OUT.bin [STREAMS [TIMEOUT_S]]]
 *
 * Prints "ready" once subscribed, one line per stream event, and a summary; writes every
 * received frame's bytes to OUT.bin (if given); stops after STREAMS streams (default 1)
 * delivered their last frame (is_last = 1), or fails after TIMEOUT_S seconds (default 60).
 * Exit code 0 on success, 1 on an error, 3 on timeout. */
#define _POSIX_C_SOURCE 200809L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "comgrasp.h"

static double now_s(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + (double)t.tv_nsec * 1e-9;
}

static const char *event_name(uint32_t kind) {
    switch (kind) {
    case CG_STREAM_EVENT_STARTED: return "started";
    case CG_STREAM_EVENT_ENDED: return "ended";
    case CG_STREAM_EVENT_CANCELLED: return "cancelled";
    case CG_STREAM_EVENT_FAILED: return "failed";
    default: return "unknown";
    }
}

int main(int argc, char **argv) {
    if (argc < 2) {
        fprintf(stderr, "usage: %s NAME [OUT.bin [STREAMS [TIMEOUT_S]]]\n", argv[0]);
        return 1;
    }
    const char *name = argv[1];
    FILE *out = NULL;
    if (argc > 2) {
        out = fopen(argv[2], "wb");
        if (!out) {
            perror(argv[2]);
            return 1;
        }
    }
    long streams = argc > 3 ? atol(argv[3]) : 1;
    double timeout_s = argc > 4 ? atof(argv[4]) : 60.0;

    cg_subscriber *sub = NULL;
    cg_status st = cg_subscriber_open(name, NULL, &sub);
    if (st != CG_OK) {
        fprintf(stderr, "cg_subscriber_open: %s\n", cg_last_error());
        return 1;
    }
    printf("ready\n");
    fflush(stdout);

    cg_frame frame;
    cg_stream_event event;
    long finished = 0, frames = 0;
    double deadline = now_s() + timeout_s;
    int rc = 0;
    while (finished < streams) {
        int idle = 1;
        while ((st = cg_subscriber_receive_event(sub, &event)) == CG_OK) {
            printf("event %s stream %llu frames %llu fps %g text \"%s\"\n", event_name(event.kind),
                   (unsigned long long)event.stream_id, (unsigned long long)event.frame_count, event.fps,
                   (const char *)event.text);
            idle = 0;
        }
        if (st < 0) break;
        while ((st = cg_subscriber_receive(sub, &frame)) == CG_OK) {
            if (out && fwrite(&frame, sizeof frame, 1, out) != 1) {
                perror("fwrite");
                rc = 1;
                break;
            }
            frames++;
            if (frame.is_last) finished++;
            idle = 0;
        }
        if (st < 0 || rc) break;
        if (now_s() > deadline) {
            fprintf(stderr, "timeout after %g s: %ld of %ld streams finished\n", timeout_s, finished, streams);
            rc = 3;
            break;
        }
        if (idle) {
            struct timespec nap = {0, 200000}; /* 0.2 ms: a consumer process has nothing else to do */
            nanosleep(&nap, NULL);
        }
    }
    if (st < 0) {
        fprintf(stderr, "receive: %s: %s\n", cg_status_string(st), cg_last_error());
        rc = 1;
    }
    cg_subscriber_stats stats;
    if (cg_subscriber_get_stats(sub, &stats) == CG_OK) {
        printf("frames: %ld received: %llu dropped: %llu events: %llu publishers: %llu\n", frames,
               (unsigned long long)stats.frames_received, (unsigned long long)stats.frames_dropped,
               (unsigned long long)stats.events_received, (unsigned long long)stats.publishers);
    }
    cg_subscriber_close(sub);
    if (out && fclose(out) != 0) rc = 1;
    return rc;
}

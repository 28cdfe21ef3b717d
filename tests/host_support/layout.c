/* Prints the C compiler's layout of the ABI structs of include/comgrasp.h (cg_frame, the
 * config structs, and the shared-memory records and counters), one fact per line:
 *   size STRUCT BYTES
 *   offset STRUCT FIELD BYTES
 * The C# and Python binding tests compare their struct declarations with it (field names
 * as in C; the C# test maps snake_case to PascalCase). Built and run by tests/host_support. */
#include <stddef.h>
#include <stdio.h>

#include "comgrasp.h"

#define SIZE(s) printf("size %s %zu\n", #s, sizeof(s))
#define OFF(s, f) printf("offset %s %s %zu\n", #s, #f, offsetof(s, f))

int main(void) {
    SIZE(cg_frame);
    OFF(cg_frame, stream_id);
    OFF(cg_frame, frame_index);
    OFF(cg_frame, time_s);
    OFF(cg_frame, root_translation);
    OFF(cg_frame, root_rotation);
    OFF(cg_frame, body_rotations);
    OFF(cg_frame, left_hand_rotations);
    OFF(cg_frame, right_hand_rotations);
    OFF(cg_frame, object_translation);
    OFF(cg_frame, object_rotation);
    OFF(cg_frame, object_centre);
    OFF(cg_frame, left_wrist_to_object);
    OFF(cg_frame, right_wrist_to_object);
    OFF(cg_frame, contact_probability);
    OFF(cg_frame, contact);
    OFF(cg_frame, is_last);
    OFF(cg_frame, has_joint_positions);
    OFF(cg_frame, reserved);
    OFF(cg_frame, joint_positions);

    SIZE(cg_bone_desc);
    OFF(cg_bone_desc, name);
    OFF(cg_bone_desc, parent);
    OFF(cg_bone_desc, rest_translation);
    OFF(cg_bone_desc, rest_rotation);

    SIZE(cg_bone_map_entry);
    OFF(cg_bone_map_entry, smplx_joint);
    OFF(cg_bone_map_entry, bone);

    SIZE(cg_bone_pose);
    OFF(cg_bone_pose, local_translation);
    OFF(cg_bone_pose, local_rotation);
    OFF(cg_bone_pose, world_position);
    OFF(cg_bone_pose, world_rotation);

    SIZE(cg_retarget_object);
    OFF(cg_retarget_object, world_position);
    OFF(cg_retarget_object, world_rotation);
    OFF(cg_retarget_object, in_hand_position);
    OFF(cg_retarget_object, in_hand_rotation);
    OFF(cg_retarget_object, hand_bone);
    OFF(cg_retarget_object, contact);
    OFF(cg_retarget_object, reserved);

    SIZE(cg_engine_config);
    OFF(cg_engine_config, struct_size);
    OFF(cg_engine_config, coordinate_system);
    OFF(cg_engine_config, bundle_path);
    OFF(cg_engine_config, enable_fk);
    OFF(cg_engine_config, ring_capacity);
    OFF(cg_engine_config, max_streams);
    OFF(cg_engine_config, reserved);
    OFF(cg_engine_config, publish_name);
    OFF(cg_engine_config, step_backend);
    OFF(cg_engine_config, decoder_backend);
    OFF(cg_engine_config, step_threads);
    OFF(cg_engine_config, decoder_threads);
    OFF(cg_engine_config, decode_group);
    OFF(cg_engine_config, overlap);
    OFF(cg_engine_config, max_isa);
    OFF(cg_engine_config, reserved2);
    OFF(cg_engine_config, scheduling);
    OFF(cg_engine_config, scheduler_threads);

    SIZE(cg_stream_config);
    OFF(cg_stream_config, struct_size);
    OFF(cg_stream_config, use_defaults);
    OFF(cg_stream_config, seed);
    OFF(cg_stream_config, temperature);
    OFF(cg_stream_config, top_k);
    OFF(cg_stream_config, min_len);
    OFF(cg_stream_config, max_len);
    OFF(cg_stream_config, flags);
    OFF(cg_stream_config, anchor);
    OFF(cg_stream_config, reserved);
    OFF(cg_stream_config, character_position);
    OFF(cg_stream_config, character_rotation);
    OFF(cg_stream_config, object_position);
    OFF(cg_stream_config, object_rotation);
    OFF(cg_stream_config, continue_from);
    OFF(cg_stream_config, guidance);

    SIZE(cg_stream_info);
    OFF(cg_stream_info, stream_id);
    OFF(cg_stream_info, object_index);
    OFF(cg_stream_info, object_named);
    OFF(cg_stream_info, object_name);

    SIZE(cg_subscriber_config);
    OFF(cg_subscriber_config, struct_size);
    OFF(cg_subscriber_config, buffer_frames);
    OFF(cg_subscriber_config, reserved);

    SIZE(cg_stream_event);
    OFF(cg_stream_event, stream_id);
    OFF(cg_stream_event, frame_count);
    OFF(cg_stream_event, kind);
    OFF(cg_stream_event, fps);
    OFF(cg_stream_event, text);

    SIZE(cg_subscriber_stats);
    OFF(cg_subscriber_stats, frames_received);
    OFF(cg_subscriber_stats, frames_dropped);
    OFF(cg_subscriber_stats, events_received);
    OFF(cg_subscriber_stats, events_dropped);
    OFF(cg_subscriber_stats, publisher_changes);
    OFF(cg_subscriber_stats, publishers);

    SIZE(cg_publisher_stats);
    OFF(cg_publisher_stats, frames_published);
    OFF(cg_publisher_stats, frames_skipped);
    OFF(cg_publisher_stats, events_published);
    OFF(cg_publisher_stats, events_skipped);
    OFF(cg_publisher_stats, subscribers);
    return 0;
}

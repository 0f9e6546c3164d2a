#version 460
// Several cameras of one rig see one object: view v's pose is rig[v] * pose of view 0
// (rig[0] is the identity), and the optimiser steps the pose of view 0 alone.
//   stage 0 (one invocation, before the step): the views' pose gradients to view 0's,
//     dL/dt = sum_v R_v^T dL/dt_v and dL/dd = sum_v R_v^T dL/dd_v (R_v = rig[v]'s
//     rotation: a left increment d of view 0 is the increment R_v d of view v, and moves
//     no translation), into grad_pose[0..6]; the views' losses summed into stats[3],
//     which the optimisers record (the other views' stats stay as they are);
//   stage 1 (x over views, after the step): views[v] = rig[v] * views[0] for v > 0.
// Sums run in view order (deterministic).
#include "views.glsl"

layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) buffer Views { ViewData views[]; };
layout(set = 0, binding = 1, std430) buffer GradPose { float grad_pose[]; };  // [view][6]
layout(set = 0, binding = 2, std430) buffer Stats { float stats[]; };        // [view][4]
layout(set = 0, binding = 3, std430) readonly buffer Rig { mat4 rig[]; };    // [view]

layout(push_constant, std430) uniform Constants {
    uint view_count;
    uint stage;
} pc;

void main() {
    uint v = gl_GlobalInvocationID.x;
    if (pc.stage == 1u) {
        if (v > 0u && v < pc.view_count) views[v].object_to_camera = rig[v] * views[0].object_to_camera;
        return;
    }
    if (v != 0u) return;
    vec3 t = vec3(0.0);
    vec3 d = vec3(0.0);
    float loss = 0.0;
    for (uint view = 0u; view < pc.view_count; ++view) {
        mat3 r_transpose = transpose(mat3(rig[view]));
        uint at = 6u * view;
        t += r_transpose * vec3(grad_pose[at], grad_pose[at + 1u], grad_pose[at + 2u]);
        d += r_transpose * vec3(grad_pose[at + 3u], grad_pose[at + 4u], grad_pose[at + 5u]);
        loss += stats[4u * view + 3u];
    }
    for (uint k = 0u; k < 3u; ++k) {
        grad_pose[k] = t[k];
        grad_pose[3u + k] = d[k];
    }
    stats[3] = loss;
}

#version 460
// Camera-space vertex gradients of every view to object-space vertex gradients (summed
// over views) and to each view's pose gradient: translation t and a local rotation
// increment d applied on the left (x_camera = exp([d]x) R x + t), so dL/dt = sum g and
// dL/dd = sum (R x) x g. No atomics, every sum in a fixed order:
//   stage 0 (x over vertices): grad_object[v] = sum over views of R^T g, in view order;
//   stage 1 (x over workgroups, z over views): each subgroup's sums over its fixed stride
//            of vertices into partials[view][group][subgroup][6] (no shared memory: a
//            barrier makes CPU drivers run a workgroup as coroutines, several times slower);
//   stage 2 (z over views): grad_pose[view] = the partials summed in slot order.
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_KHR_shader_subgroup_basic : require
#include "views.glsl"

layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };
layout(set = 0, binding = 1, std430) readonly buffer Views { ViewData views[]; };
layout(set = 0, binding = 2, std430) readonly buffer GradCamera { float grad_camera[]; };  // [view][vertex][3]
layout(set = 0, binding = 3, std430) buffer GradObject { float grad_object[]; };           // [vertex][3]
layout(set = 0, binding = 4, std430) buffer GradPose { float grad_pose[]; };               // [view][6]
layout(set = 0, binding = 5, std430) buffer Partials { float partials[]; };                // [view][group][6]

layout(push_constant, std430) uniform Constants {
    uint vertex_count;
    uint view_count;
    uint groups;  // workgroups of stage 1
    uint stage;
    uint subgroups;  // subgroups per workgroup (the partial slots of one workgroup)
} pc;

vec3 camera_gradient(uint view, uint v) {
    uint at = 3u * (view * pc.vertex_count + v);
    return vec3(grad_camera[at], grad_camera[at + 1u], grad_camera[at + 2u]);
}

void main() {
    if (pc.stage == 0u) {
        // Views outer, vertices inner: each view's rotation is loaded once per invocation
        // (CPU drivers load a buffer value per lane; per vertex it cost more than the rest
        // of the backward at 1e6 vertices), and each vertex still sums its views in order.
        uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
        for (uint view = 0u; view < pc.view_count; ++view) {
            mat3 r_transpose = transpose(mat3(views[view].object_to_camera));
            for (uint v = gl_GlobalInvocationID.x; v < pc.vertex_count; v += stride) {
                vec3 g = r_transpose * camera_gradient(view, v);
                if (view > 0u) {
                    g = vec3(grad_object[3u * v], grad_object[3u * v + 1u], grad_object[3u * v + 2u]) + g;
                }
                grad_object[3u * v] = g.x;
                grad_object[3u * v + 1u] = g.y;
                grad_object[3u * v + 2u] = g.z;
            }
        }
        return;
    }
    uint view = gl_WorkGroupID.z;
    if (pc.stage == 2u) {
        if (gl_LocalInvocationIndex < 6u) {
            float total = 0.0;
            uint slots = pc.groups * pc.subgroups;
            for (uint g = 0u; g < slots; ++g) total += partials[6u * (view * slots + g) + gl_LocalInvocationIndex];
            grad_pose[6u * view + gl_LocalInvocationIndex] = total;
        }
        return;
    }
    mat3 r = mat3(views[view].object_to_camera);
    vec3 sum_t = vec3(0.0);
    vec3 sum_r = vec3(0.0);
    uint stride = pc.groups * gl_WorkGroupSize.x;
    uint first = gl_WorkGroupID.x * gl_WorkGroupSize.x + gl_LocalInvocationIndex;
    for (uint v = first; v < pc.vertex_count; v += stride) {
        vec3 g = camera_gradient(view, v);
        if (g == vec3(0.0)) continue;
        vec3 x = vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]);
        sum_t += g;
        sum_r += cross(r * x, g);
    }
    sum_t = subgroupAdd(sum_t);
    sum_r = subgroupAdd(sum_r);
    if (subgroupElect()) {
        uint slot = (view * pc.groups + gl_WorkGroupID.x) * pc.subgroups + gl_SubgroupID;
        for (uint k = 0u; k < 3u; ++k) {
            partials[6u * slot + k] = sum_t[k];
            partials[6u * slot + 3u + k] = sum_r[k];
        }
    }
}

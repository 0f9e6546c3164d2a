#version 460
// Camera-space vertex gradients of every view to object-space vertex gradients (summed
// over views) and to each view's pose gradient: translation t and a local rotation
// increment d applied on the left (x_camera = exp([d]x) R x + t), so dL/dt = sum g and
// dL/dd = sum (R x) x g. No atomics, every sum in a fixed order:
//   stage 0 (x over workgroups, each invocation over a fixed stride of flag words): per
//            view in order, grad_object[v] (+)= R^T g, and each subgroup's sums over its
//            vertices into partials[view][group][subgroup][6] (no shared memory: a barrier
//            makes CPU drivers run a workgroup as coroutines, several times slower);
//   stage 1 (z over views): grad_pose[view] = the partials summed in slot order.
// The camera gradients g are read as floats (grad_camera, after the shading passes added
// to them), or with pc.from_fixed straight from the backward's fixed-point
// sums, resolved here as fixed_resolve.comp would (one pass over the vertices less).
// Blocks of pc.vertex_block vertices whose `touched` bit is 0 got no gradient term: they
// are skipped (their grad_object stays as cleared, 0), so the pass costs what the
// silhouette does, not the mesh: CPU drivers load and store buffer values lane by lane,
// and visiting every vertex cost 20 ms at 1e6 vertices on lavapipe. An invocation loops
// over many flag words, so each view's rotation is loaded once per invocation.
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_KHR_shader_subgroup_basic : require
#include "views.glsl"
#include "fixed_point.glsl"

layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };
layout(set = 0, binding = 1, std430) readonly buffer Views { ViewData views[]; };
layout(set = 0, binding = 2, std430) readonly buffer GradCamera { float grad_camera[]; };  // [view][vertex][3]
layout(set = 0, binding = 3, std430) buffer GradObject { float grad_object[]; };           // [vertex][3]
layout(set = 0, binding = 4, std430) buffer GradPose { float grad_pose[]; };               // [view][6]
layout(set = 0, binding = 5, std430) buffer Partials { float partials[]; };                // [view][group][subgroup][6]
layout(set = 0, binding = 6, std430) readonly buffer GradCameraFixed { int64_t grad_camera_fixed[]; };  // as grad_camera
layout(set = 0, binding = 7, std430) readonly buffer WorkCount { uint work_count[]; };
layout(set = 0, binding = 8, std430) readonly buffer Touched { uint touched[]; };  // a bit per block of pc.vertex_block vertices

layout(push_constant, std430) uniform Constants {
    uint vertex_count;
    uint view_count;
    uint groups;  // workgroups of stage 0
    uint stage;
    uint subgroups;  // subgroups per workgroup (the partial slots of one workgroup)
    uint from_fixed;  // 1: read grad_camera_fixed, 0: grad_camera
    uint max_slot;  // work_count slots of the bound on the fixed-point terms and of the
    uint seen_slot; // largest one (fixed_resolve.comp)
    uint terms_per_listed;
    uint vertex_block;  // vertices per touched flag
} pc;

void main() {
    if (pc.stage == 1u) {
        uint view = gl_WorkGroupID.z;
        if (gl_LocalInvocationIndex < 6u) {
            float total = 0.0;
            uint slots = pc.groups * pc.subgroups;
            for (uint g = 0u; g < slots; ++g) total += partials[6u * (view * slots + g) + gl_LocalInvocationIndex];
            grad_pose[6u * view + gl_LocalInvocationIndex] = total;
        }
        return;
    }
    uint max_bits = checked_bits(work_count[pc.max_slot], work_count[pc.seen_slot]);
    int shift = listed_shift(max_bits, pc.terms_per_listed, work_count[0]);
    bool finite = pc.from_fixed == 0u || max_bits < NON_FINITE_BITS;
    // Bit b of touched[w] flags block 32 w + b of pc.vertex_block vertices. Each invocation
    // takes every (pc.groups * 64)-th word and the blocks its set bits flag, in order, so
    // the pass costs a load per 32 blocks plus the flagged vertices (a loop over every
    // block, skipping the unflagged, took 12 ms at 1e6 vertices on lavapipe).
    uint blocks = (pc.vertex_count + pc.vertex_block - 1u) / pc.vertex_block;
    uint words = (blocks + 31u) / 32u;
    uint stride = pc.groups * gl_WorkGroupSize.x;
    for (uint view = 0u; view < pc.view_count; ++view) {
        mat3 r = mat3(views[view].object_to_camera);
        mat3 r_transpose = transpose(r);
        vec3 sum_t = vec3(0.0);
        vec3 sum_r = vec3(0.0);
        for (uint w = gl_WorkGroupID.x * gl_WorkGroupSize.x + gl_LocalInvocationIndex; w < words; w += stride) {
            // (Every block when a term was not finite: then every gradient is NaN, as the
            // resolve makes them, so that callers still see it.)
            uint bits = finite ? touched[w] : 0xffffffffu;
            while (bits != 0u) {
                uint block = 32u * w + uint(findLSB(bits));
                bits &= bits - 1u;
                uint end = min(pc.vertex_count, (block + 1u) * pc.vertex_block);
                for (uint v = block * pc.vertex_block; v < end; ++v) {
                    uint at = 3u * (view * pc.vertex_count + v);
                    vec3 g;
                    if (pc.from_fixed == 0u) {
                        g = vec3(grad_camera[at], grad_camera[at + 1u], grad_camera[at + 2u]);
                    } else {
                        g = vec3(resolved(grad_camera_fixed[at], max_bits, shift),
                                 resolved(grad_camera_fixed[at + 1u], max_bits, shift),
                                 resolved(grad_camera_fixed[at + 2u], max_bits, shift));
                    }
                    vec3 go = r_transpose * g;
                    if (view > 0u) go = vec3(grad_object[3u * v], grad_object[3u * v + 1u], grad_object[3u * v + 2u]) + go;
                    grad_object[3u * v] = go.x;
                    grad_object[3u * v + 1u] = go.y;
                    grad_object[3u * v + 2u] = go.z;
                    if (g == vec3(0.0)) continue;
                    vec3 x = vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]);
                    sum_t += g;
                    sum_r += cross(r * x, g);
                }
            }
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
}

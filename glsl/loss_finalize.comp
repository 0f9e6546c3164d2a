#version 460
// The loss of each view: adds the per-subgroup partials of classify.comp, in slot order, to
// what antialias.comp accumulated in stats_fixed[3 view + 0..2] (loss sum, intersection,
// union; int64 fixed point at pc.stats_shift), writes those sums to stats[4 view + 0..2]
// and the loss to stats[4 view + 3]. One workgroup per view; every sum is in a fixed order.
// One dispatch adds the slots [first, end), carrying on from the sums the one before it
// wrote (lavapipe ends an invocation's loops after 65535 iterations; src/gpu/mod.rs).
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_KHR_shader_subgroup_basic : require
#include "fixed_point.glsl"

layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) buffer Stats { float stats[]; };
layout(set = 0, binding = 1, std430) readonly buffer Partials { float partials[]; };
layout(set = 0, binding = 2, std430) readonly buffer StatsFixed { int64_t stats_fixed[]; };

layout(push_constant, std430) uniform Constants {
    uint loss;
    uint partial_slots;
    int stats_shift;
    uint first;
    uint end;
} pc;

shared vec3 per_subgroup[64];

void main() {
    uint view = gl_WorkGroupID.z;
    vec3 sum = vec3(0.0);
    for (uint slot = pc.first + gl_LocalInvocationIndex; slot < pc.end; slot += 64u) {
        uint at = 3u * (view * pc.partial_slots + slot);
        sum += vec3(partials[at], partials[at + 1u], partials[at + 2u]);
    }
    sum = subgroupAdd(sum);
    if (subgroupElect()) per_subgroup[gl_SubgroupID] = sum;
    barrier();
    if (gl_LocalInvocationIndex == 0u) {
        vec3 total = vec3(0.0);
        for (uint k = 0u; k < 3u; ++k) {
            total[k] = pc.first == 0u ? from_fixed(stats_fixed[3u * view + k], pc.stats_shift) : stats[4u * view + k];
        }
        for (uint s = 0u; s < gl_NumSubgroups; ++s) total += per_subgroup[s];
        float value = total.x;
        if (pc.loss == 1u) value = total.z > 0.0 ? 1.0 - total.y / total.z : 0.0;
        stats[4u * view] = total.x;
        stats[4u * view + 1u] = total.y;
        stats[4u * view + 2u] = total.z;
        stats[4u * view + 3u] = value;
    }
}

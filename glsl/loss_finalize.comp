#version 460
// The loss of each view (z over views) from the sums classify.comp and antialias.comp added
// to stats_fixed[3 view + 0..2] (loss sum, intersection, union; int64 fixed point at
// pc.stats_shift): writes the sums to stats[4 view + 0..2] and the loss to stats[4 view + 3].
#include "fixed_point.glsl"
#include "loss_codes.glsl"

layout(local_size_x = 1) in;

layout(set = 0, binding = 0, std430) buffer Stats { float stats[]; };
layout(set = 0, binding = 1, std430) readonly buffer StatsFixed { int64_t stats_fixed[]; };

layout(push_constant, std430) uniform Constants {
    uint loss;
    int stats_shift;
} pc;

void main() {
    uint view = gl_WorkGroupID.z;
    vec3 total;
    for (uint k = 0u; k < 3u; ++k) total[k] = from_fixed(stats_fixed[3u * view + k], pc.stats_shift);
    float value = loss_of(pc.loss, total);
    stats[4u * view] = total.x;
    stats[4u * view + 1u] = total.y;
    stats[4u * view + 2u] = total.z;
    stats[4u * view + 3u] = value;
}

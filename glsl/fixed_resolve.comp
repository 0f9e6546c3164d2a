#version 460
// Converts a fixed-point sum buffer (see include/fixed_point.glsl) to floats: value i is
// fixed[i] / 2^shift with the shift its terms were added at (from the bound on its terms
// in work_count[pc.max_slot] and at most pc.terms_per_listed terms per listed pixel);
// NaN everywhere when a term was not finite or above the bound (its largest in
// work_count[pc.seen_slot]), so that callers still see it.
#include "fixed_point.glsl"

layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) readonly buffer Fixed { int64_t fixed_sum[]; };
layout(set = 0, binding = 1, std430) buffer Floats { float values[]; };
layout(set = 0, binding = 2, std430) readonly buffer WorkCount { uint work_count[]; };

layout(push_constant, std430) uniform Constants {
    uint count;
    uint max_slot;
    uint seen_slot;
    uint terms_per_listed;
} pc;

void main() {
    uint max_bits = checked_bits(work_count[pc.max_slot], work_count[pc.seen_slot]);
    int shift = listed_shift(max_bits, pc.terms_per_listed, work_count[0]);
    uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
    for (uint i = gl_GlobalInvocationID.x; i < pc.count; i += stride) {
        values[i] = resolved(fixed_sum[i], max_bits, shift);
    }
}

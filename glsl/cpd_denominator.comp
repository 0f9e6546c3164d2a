#version 460
// CPD E-step, pass 1: per target point n, log(sum_m exp(-|x_n - t_m|^2 / (2 s2)) + c):
// the largest exponent first (no exponentials), then the sum relative to it.
#include "cpd.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Moving { vec4 moving[]; };  // t_m
layout(set = 0, binding = 1, std430) readonly buffer Target { vec4 target[]; };  // x_n
layout(set = 0, binding = 2, std430) writeonly buffer LogDen { float log_den[]; };

void main() {
    uint lane = gl_SubgroupInvocationID;
    vec3 x[ROWS];
    float nearest[ROWS];  // smallest squared distance
    for (uint r = 0u; r < ROWS; ++r) {
        x[r] = target[min(row(r), pc.n - 1u)].xyz;
        nearest[r] = 3.4e38;
    }
    for (uint base = 0u; base < pc.m; base += gl_SubgroupSize) {
        vec3 t = moving[min(base + lane, pc.m - 1u)].xyz;
        for (uint k = 0u; k < gl_SubgroupSize; ++k) {
            vec3 tk = subgroupShuffle(t, k);  // a clamped index repeats the last point
            for (uint r = 0u; r < ROWS; ++r) {
                vec3 d = x[r] - tk;
                nearest[r] = min(nearest[r], dot(d, d));
            }
        }
    }
    float top[ROWS], sum[ROWS];
    for (uint r = 0u; r < ROWS; ++r) {
        top[r] = max(-nearest[r] * pc.inv_two_sigma2, pc.log_c);
        sum[r] = exp(pc.log_c - top[r]);
    }
    for (uint base = 0u; base < pc.m; base += gl_SubgroupSize) {
        vec3 t = moving[min(base + lane, pc.m - 1u)].xyz;
        bool real = base + lane < pc.m;
        for (uint k = 0u; k < gl_SubgroupSize; ++k) {
            vec3 tk = subgroupShuffle(t, k);
            bool counts = subgroupShuffle(real, k);
            for (uint r = 0u; r < ROWS; ++r) {
                vec3 d = x[r] - tk;
                float term = exp(-dot(d, d) * pc.inv_two_sigma2 - top[r]);
                sum[r] += counts ? term : 0.0;
            }
        }
    }
    for (uint r = 0u; r < ROWS; ++r) {
        if (row(r) < pc.n) log_den[row(r)] = top[r] + log(sum[r]);
    }
}

#version 460
// CPD E-step, pass 2: per moving point m, P1_m = sum_n P_mn and PX_m = sum_n P_mn x_n
// (written as vec4: xyz = PX_m, w = P1_m), one span of the targets per dispatch, each
// adding to the sums of the spans before it.
#include "cpd.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Moving { vec4 moving[]; };
layout(set = 0, binding = 1, std430) readonly buffer Target { vec4 target[]; };
layout(set = 0, binding = 2, std430) readonly buffer LogDen { float log_den[]; };
layout(set = 0, binding = 3, std430) buffer Sums { vec4 sums[]; };

void main() {
    uint lane = gl_SubgroupInvocationID;
    vec3 t[ROWS];
    vec4 acc[ROWS];
    for (uint r = 0u; r < ROWS; ++r) {
        t[r] = moving[min(row(r), pc.m - 1u)].xyz;
        acc[r] = pc.first == 0u ? vec4(0.0) : sums[min(row(r), pc.m - 1u)];
    }
    for (uint base = pc.first; base < pc.end; base += gl_SubgroupSize) {
        uint j = min(base + lane, pc.end - 1u);
        vec3 x = target[j].xyz;
        // A lane past the end carries an infinite denominator: its terms are 0.
        float den = base + lane < pc.end ? log_den[j] : 3.4e38;
        for (uint k = 0u; k < gl_SubgroupSize; ++k) {
            vec3 xk = subgroupShuffle(x, k);
            float dk = subgroupShuffle(den, k);
            for (uint r = 0u; r < ROWS; ++r) {
                vec3 d = xk - t[r];
                float p = exp(-dot(d, d) * pc.inv_two_sigma2 - dk);
                acc[r] += vec4(p * xk, p);
            }
        }
    }
    for (uint r = 0u; r < ROWS; ++r) {
        if (row(r) < pc.m) sums[row(r)] = acc[r];
    }
}

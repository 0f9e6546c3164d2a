#version 460
// CPD E-step, pass 2: per moving point m, P1_m = sum_n P_mn, the pull
// sum_n P_mn (x_n - t_m) and the spread sum_n P_mn |x_n - t_m|^2 over the targets near
// it (its workgroup's ranges, see cpd.glsl), one piece of the ranges per dispatch, each
// adding to the sums of the pieces before it. Two vec4 per point: (pull, P1),
// (spread, 0, 0, 0). Rows are moving points in their sorted order.
//
// Sums of differences, not PX_m = sum_n P_mn x_n: near convergence x_n - t_m is tiny, and
// sigma^2 = sum P |x - t|^2 / (3 sum P) formed from PX in float32 cancels to rounding
// (noise-free sets lost sigma^2 below about 1e-7 of the squared radius that way).
#define ESTEP
#include "cpd.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Moving { vec4 moving[]; };
layout(set = 0, binding = 1, std430) readonly buffer Target { vec4 target[]; };
layout(set = 0, binding = 2, std430) readonly buffer LogDen { float log_den[]; };
layout(set = 0, binding = 3, std430) buffer Sums { vec4 sums[]; };

void main() {
    uint lane = gl_SubgroupInvocationID;
    uvec2 piece = own_piece();
    vec3 t[ROWS];
    vec4 acc[ROWS];
    float spread[ROWS];
    for (uint r = 0u; r < ROWS; ++r) {
        uint i = min(own_row(r), pc.m - 1u);
        t[r] = moving[i].xyz;
        acc[r] = pc.piece == 0u ? vec4(0.0) : sums[2u * i];
        spread[r] = pc.piece == 0u ? 0.0 : sums[2u * i + 1u].x;
    }
    for (uint k = 0u; k < piece.y; ++k) {
        uvec2 span = ranges[piece.x + k];
        for (uint base = span.x; base < span.y; base += gl_SubgroupSize) {
            uint j = min(base + lane, span.y - 1u);
            vec3 x = target[j].xyz;
            // A lane past the end carries an infinite denominator: its terms are 0.
            float den = base + lane < span.y ? log_den[j] : 3.4e38;
            for (uint l = 0u; l < gl_SubgroupSize; ++l) {
                vec3 xl = subgroupShuffle(x, l);
                float dl = subgroupShuffle(den, l);
                for (uint r = 0u; r < ROWS; ++r) {
                    vec3 d = xl - t[r];
                    float d2 = dot(d, d);
                    float p = exp(-d2 * pc.inv_two_sigma2 - dl);
                    acc[r] += vec4(p * d, p);
                    spread[r] += p * d2;
                }
            }
        }
    }
    for (uint r = 0u; r < ROWS; ++r) {
        if (own_row(r) >= pc.m) continue;
        sums[2u * own_row(r)] = acc[r];
        sums[2u * own_row(r) + 1u] = vec4(spread[r], 0.0, 0.0, 0.0);
    }
}

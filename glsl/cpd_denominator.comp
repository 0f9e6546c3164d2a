#version 460
// CPD E-step, pass 1: per target point n, log(sum_m exp(-|x_n - t_m|^2 / (2 s2)) + c) over
// the moving points near it (its workgroup's ranges, see cpd.glsl), one piece of the
// ranges per dispatch. The running sum is kept relative to the largest exponent seen so
// far, (top, sum) in `running`: each piece finds its own largest exponent first (no
// exponentials), rescales the sum so far to the new top once, and adds its terms. The
// last piece writes the logarithm. Rows are targets in their sorted order.
#define ESTEP
#include "cpd.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Moving { vec4 moving[]; };  // t_m
layout(set = 0, binding = 1, std430) readonly buffer Target { vec4 target[]; };  // x_n
layout(set = 0, binding = 2, std430) writeonly buffer LogDen { float log_den[]; };
layout(set = 0, binding = 3, std430) buffer Running { vec2 running[]; };  // (top, sum)

void main() {
    uint lane = gl_SubgroupInvocationID;
    uvec2 piece = own_piece();
    vec3 x[ROWS];
    float nearest[ROWS];  // smallest squared distance in this piece
    for (uint r = 0u; r < ROWS; ++r) {
        x[r] = target[min(own_row(r), pc.n - 1u)].xyz;
        nearest[r] = 3.4e38;
    }
    for (uint k = 0u; k < piece.y; ++k) {
        uvec2 span = ranges[piece.x + k];
        for (uint base = span.x; base < span.y; base += gl_SubgroupSize) {
            vec3 t = moving[min(base + lane, span.y - 1u)].xyz;
            for (uint j = 0u; j < gl_SubgroupSize; ++j) {
                vec3 tj = subgroupShuffle(t, j);  // a clamped index repeats the last point
                for (uint r = 0u; r < ROWS; ++r) {
                    vec3 d = x[r] - tj;
                    nearest[r] = min(nearest[r], dot(d, d));
                }
            }
        }
    }
    float top[ROWS], sum[ROWS];
    for (uint r = 0u; r < ROWS; ++r) {
        top[r] = max(-nearest[r] * pc.inv_two_sigma2, pc.log_c);
        if (pc.piece == 0u) {
            sum[r] = exp(pc.log_c - top[r]);
        } else {
            vec2 before = running[min(own_row(r), pc.n - 1u)];
            top[r] = max(top[r], before.x);
            sum[r] = before.y * exp(before.x - top[r]);
        }
    }
    for (uint k = 0u; k < piece.y; ++k) {
        uvec2 span = ranges[piece.x + k];
        for (uint base = span.x; base < span.y; base += gl_SubgroupSize) {
            vec3 t = moving[min(base + lane, span.y - 1u)].xyz;
            bool real = base + lane < span.y;
            for (uint j = 0u; j < gl_SubgroupSize; ++j) {
                vec3 tj = subgroupShuffle(t, j);
                bool counts = subgroupShuffle(real, j);
                for (uint r = 0u; r < ROWS; ++r) {
                    vec3 d = x[r] - tj;
                    float term = exp(-dot(d, d) * pc.inv_two_sigma2 - top[r]);
                    sum[r] += counts ? term : 0.0;
                }
            }
        }
    }
    for (uint r = 0u; r < ROWS; ++r) {
        if (own_row(r) >= pc.n) continue;
        running[own_row(r)] = vec2(top[r], sum[r]);
        if (pc.piece + 1u == pc.pieces) log_den[own_row(r)] = top[r] + log(sum[r]);
    }
}

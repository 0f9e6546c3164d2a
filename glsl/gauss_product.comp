#version 460
// Gaussian kernel product: out[i] = sum_j exp(-|y_i - y_j|^2 / (2 beta^2)) v[j] for four
// columns at a time (one vec4 per point; CPD's M-step needs three), without forming the
// M x M kernel. The push constants are the E-step's with beta in place of sigma (m = n);
// points are passed around the subgroup as there, one span of j per dispatch, each adding
// to the products of the spans before it.
#include "cpd.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Points { vec4 points[]; };
layout(set = 0, binding = 1, std430) readonly buffer Columns { vec4 columns[]; };
layout(set = 0, binding = 2, std430) buffer Product { vec4 product[]; };

void main() {
    uint lane = gl_SubgroupInvocationID;
    vec3 y[ROWS];
    vec4 acc[ROWS];
    for (uint r = 0u; r < ROWS; ++r) {
        y[r] = points[min(row(r), pc.m - 1u)].xyz;
        acc[r] = pc.first == 0u ? vec4(0.0) : product[min(row(r), pc.m - 1u)];
    }
    for (uint base = pc.first; base < pc.end; base += gl_SubgroupSize) {
        uint j = min(base + lane, pc.end - 1u);
        vec3 p = points[j].xyz;
        vec4 c = base + lane < pc.end ? columns[j] : vec4(0.0);
        for (uint k = 0u; k < gl_SubgroupSize; ++k) {
            vec3 q = subgroupShuffle(p, k);
            vec4 v = subgroupShuffle(c, k);
            for (uint r = 0u; r < ROWS; ++r) {
                vec3 d = y[r] - q;
                acc[r] += exp(-dot(d, d) * pc.inv_two_sigma2) * v;
            }
        }
    }
    for (uint r = 0u; r < ROWS; ++r) {
        if (row(r) < pc.m) product[row(r)] = acc[r];
    }
}

#version 460
// Gaussian kernel product: out[i][c] = sum_j exp(-|y_i - y_j|^2 / (2 beta^2)) v[j][c] for
// 16 columns c at a time (4 vec4 per point), without forming the M x M kernel: each
// exponential serves all 16 columns.
layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) readonly buffer Points { vec4 points[]; };
layout(set = 0, binding = 1, std430) readonly buffer Columns { vec4 columns[]; };  // [j][4]
layout(set = 0, binding = 2, std430) writeonly buffer Product { vec4 product[]; };  // [i][4]

layout(push_constant, std430) uniform Constants {
    uint m;
    float inv_two_beta2;
} pc;

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= pc.m) return;
    vec3 y = points[i].xyz;
    vec4 acc0 = vec4(0.0), acc1 = vec4(0.0), acc2 = vec4(0.0), acc3 = vec4(0.0);
    for (uint j = 0u; j < pc.m; ++j) {
        vec3 d = y - points[j].xyz;
        float g = exp(-dot(d, d) * pc.inv_two_beta2);
        acc0 += g * columns[4u * j];
        acc1 += g * columns[4u * j + 1u];
        acc2 += g * columns[4u * j + 2u];
        acc3 += g * columns[4u * j + 3u];
    }
    product[4u * i] = acc0;
    product[4u * i + 1u] = acc1;
    product[4u * i + 2u] = acc2;
    product[4u * i + 3u] = acc3;
}

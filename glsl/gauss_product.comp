#version 460
// Gaussian kernel product: out[i][c] = sum_j exp(-|y_i - y_j|^2 / (2 beta^2)) v[j][c] for
// 4 columns c at a time (vec4), without forming the M x M kernel.
layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) readonly buffer Points { vec4 points[]; };
layout(set = 0, binding = 1, std430) readonly buffer Columns { vec4 columns[]; };
layout(set = 0, binding = 2, std430) writeonly buffer Product { vec4 product[]; };

layout(push_constant, std430) uniform Constants {
    uint m;
    float inv_two_beta2;
} pc;

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= pc.m) return;
    vec3 y = points[i].xyz;
    vec4 acc = vec4(0.0);
    for (uint j = 0u; j < pc.m; ++j) {
        vec3 d = y - points[j].xyz;
        acc += exp(-dot(d, d) * pc.inv_two_beta2) * columns[j];
    }
    product[i] = acc;
}

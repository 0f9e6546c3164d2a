#version 460
// Deformed canonical mesh from the latent code on the device:
// positions[v] = C[v] + d0[v] + sum_j s_j B_j[v] (B already scaled to unit-variance codes).
layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) readonly buffer Canonical { float canonical[]; };  // C + d0, 3 per vertex
layout(set = 0, binding = 1, std430) readonly buffer Basis { float basis[]; };          // [j][3 v + c]
layout(set = 0, binding = 2, std430) readonly buffer State { float state[]; };          // latent at pc.latent_at
layout(set = 0, binding = 3, std430) writeonly buffer Positions { float positions[]; };

layout(push_constant, std430) uniform Constants {
    uint vertex_count;
    uint dims;
    uint latent_at;
} pc;

void main() {
    uint v = gl_GlobalInvocationID.x;
    if (v >= pc.vertex_count) return;
    for (uint c = 0u; c < 3u; ++c) {
        float p = canonical[3u * v + c];
        for (uint j = 0u; j < pc.dims; ++j) p += state[pc.latent_at + j] * basis[j * 3u * pc.vertex_count + 3u * v + c];
        positions[3u * v + c] = p;
    }
}

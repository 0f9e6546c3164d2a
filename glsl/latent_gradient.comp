#version 460
// dL/ds_j = sum_v B_j[v] . dL/dx_v: one workgroup per latent dimension j (z), subgroup
// sums added atomically into grad_latent[j] (zeroed before).
#extension GL_EXT_shader_atomic_float : require
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_KHR_shader_subgroup_basic : require
layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) readonly buffer Basis { float basis[]; };
layout(set = 0, binding = 1, std430) readonly buffer Gradient { float gradient[]; };  // dL/dx, 3 per vertex
layout(set = 0, binding = 2, std430) buffer GradLatent { float grad_latent[]; };

layout(push_constant, std430) uniform Constants {
    uint vertex_count;
    uint dims;
} pc;

void main() {
    uint j = gl_WorkGroupID.z;
    uint n = 3u * pc.vertex_count;
    float sum = 0.0;
    for (uint i = gl_LocalInvocationIndex; i < n; i += 64u) sum += basis[j * n + i] * gradient[i];
    sum = subgroupAdd(sum);
    if (subgroupElect()) atomicAdd(grad_latent[j], sum);
}

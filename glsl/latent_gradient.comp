#version 460
// dL/ds_j = sum_v B_j[v] . dL/dx_v: one workgroup per latent dimension j (z). Each
// invocation sums a fixed stride of the vertices, subgroups add their lanes, and the
// first invocation adds the subgroups' sums in order: the same order every run. One
// dispatch covers one span [first, end) of the 3 V coordinates and adds to what the
// dispatches before it left (the host zeroes grad_latent first): lavapipe ends an
// invocation's loops after 65535 iterations, so no loop may run over all of a big mesh.
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_KHR_shader_subgroup_basic : require
layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) readonly buffer Basis { float basis[]; };
layout(set = 0, binding = 1, std430) readonly buffer Gradient { float gradient[]; };  // dL/dx, 3 per vertex
layout(set = 0, binding = 2, std430) buffer GradLatent { float grad_latent[]; };

layout(push_constant, std430) uniform Constants {
    uint vertex_count;
    uint dims;
    uint first;
    uint end;
} pc;

shared float per_subgroup[64];

void main() {
    uint j = gl_WorkGroupID.z;
    uint n = 3u * pc.vertex_count;
    float sum = 0.0;
    for (uint i = pc.first + gl_LocalInvocationIndex; i < pc.end; i += 64u) sum += basis[j * n + i] * gradient[i];
    sum = subgroupAdd(sum);
    if (subgroupElect()) per_subgroup[gl_SubgroupID] = sum;
    barrier();
    if (gl_LocalInvocationIndex == 0u) {
        float total = 0.0;
        for (uint s = 0u; s < gl_NumSubgroups; ++s) total += per_subgroup[s];
        grad_latent[j] += total;
    }
}

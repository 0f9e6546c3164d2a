#version 460
// Per pixel: when no pair with a neighbour matters (pair_matters: with coverage, the
// pixel and its four neighbours are all covered or all background) and nothing is
// interpolated, its antialiased value is its coverage; write it and its loss terms (one
// partial sum per subgroup into `partials`). Every other pixel is appended to the work
// list for antialias.comp and antialias_backward.comp. z = view.
#include "diff_pass.glsl"

layout(local_size_x = 8, local_size_y = 8) in;

void main() {
    uint view = gl_GlobalInvocationID.z;
    ivec2 size = ivec2(pc.width, pc.height);
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    bool inside = all(lessThan(p, size));
    bool listed = false;
    vec3 terms = vec3(0.0);
    uint index = 0u;
    if (inside) {
        index = pixel_index(p, view);
        uint id = ids[index];
        bool any_pair = false;
        for (int s = 0; s < 4; ++s) {
            ivec2 q = clamp(p + STEPS[s], ivec2(0), size - 1);
            any_pair = any_pair || pair_matters(id, ids[pixel_index(q, view)]);
        }
        listed = any_pair || (pc.channels > 0u && id != 0u);
        if (!listed) {
            vec4 a = id == 0u ? vec4(0.0) : vec4(1.0, 0.0, 0.0, 0.0);
            store_antialiased(index, a);
            terms = loss_terms(index, a);
        }
    }
    uvec4 ballot = subgroupBallot(listed);
    uint count = subgroupBallotBitCount(ballot);
    uint base = 0u;
    if (subgroupElect() && count > 0u) base = atomicAdd(work_count[0], count);
    base = subgroupBroadcastFirst(base);
    if (listed) work[base + subgroupBallotExclusiveBitCount(ballot)] = index;

    terms = subgroupAdd(terms);
    if (subgroupElect()) {
        uint group = gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x;
        uint slot = view * pc.partial_slots + group * gl_NumSubgroups + gl_SubgroupID;
        for (int k = 0; k < 3; ++k) partials[3u * slot + uint(k)] = terms[k];
    }
}

#version 460
// Stage 0, per pixel of each view's box (bounds.comp; z = view): when no pair with a
// neighbour matters (pair_matters: with coverage, the pixel and its four neighbours are
// all covered or all background) and nothing is interpolated, its antialiased value is
// its coverage; write it and its loss terms less the background's (loss_excess; one
// partial sum per subgroup into `partials`). Every other pixel is appended to the work
// list for antialias.comp and antialias_backward.comp.
// Stage 1, once per observation (x over workgroups, grid stride over every pixel of view
// z): the background terms loss_terms(pixel, 0) of the whole image, added to stats_fixed
// (the host keeps them and starts every evaluation's sums from them).
#include "diff_pass.glsl"

layout(local_size_x = 8, local_size_y = 8) in;

void background_terms() {
    uint view = gl_WorkGroupID.z;
    uint pixels = pc.width * pc.height;
    uint stride = gl_NumWorkGroups.x * 64u;
    i64vec3 sum = i64vec3(0);
    for (uint i = gl_WorkGroupID.x * 64u + gl_LocalInvocationIndex; i < pixels; i += stride) {
        vec3 terms = loss_terms(view * pixels + i, vec4(0.0));
        for (int k = 0; k < 3; ++k) sum[k] += to_fixed(terms[k], pc.stats_shift);
    }
    for (int k = 0; k < 3; ++k) {
        if (sum[k] != 0) atomicAdd(stats_fixed[3u * view + uint(k)], sum[k]);
    }
}

void main() {
    if (pc.stage == 1u) {
        background_terms();
        return;
    }
    uint view = gl_GlobalInvocationID.z;
    uint box = 4u + 4u * gl_NumWorkGroups.z + 4u * view;
    ivec2 size = ivec2(pc.width, pc.height);
    ivec2 p = ivec2(boxes[box], boxes[box + 1u]) + ivec2(gl_GlobalInvocationID.xy);
    bool inside = all(lessThan(ivec2(gl_GlobalInvocationID.xy), ivec2(boxes[box + 2u], boxes[box + 3u])));
    bool listed = false;
    vec3 terms = vec3(0.0);
    uint index = 0u;
    if (inside) {
        index = pixel_index(p, view);
        uint id = ids[index];
        // Neighbours by index offset; at the image border the pixel itself stands in.
        uint right = p.x + 1 < size.x ? ids[index + 1u] : id;
        uint left = p.x > 0 ? ids[index - 1u] : id;
        uint down = p.y + 1 < size.y ? ids[index + pc.width] : id;
        uint up = p.y > 0 ? ids[index - pc.width] : id;
        bool any_pair = pair_matters(id, right) || pair_matters(id, left) || pair_matters(id, down)
            || pair_matters(id, up);
        listed = any_pair || (pc.channels > 0u && id != 0u);
        if (!listed && id != 0u) {
            // Covered, against a mask: one channel, no interpolation.
            antialiased[index] = 1.0;
            terms = loss_excess(index, vec4(1.0, 0.0, 0.0, 0.0));
        }
        // Background away from the object: value 0 (the whole image is cleared before),
        // no excess.
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

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
        // Neighbours by index offset; at the image border the pixel itself stands in.
        uint right = p.x + 1 < size.x ? ids[index + 1u] : id;
        uint left = p.x > 0 ? ids[index - 1u] : id;
        uint down = p.y + 1 < size.y ? ids[index + pc.width] : id;
        uint up = p.y > 0 ? ids[index - pc.width] : id;
        bool any_pair = pair_matters(id, right) || pair_matters(id, left) || pair_matters(id, down)
            || pair_matters(id, up);
        listed = any_pair || (pc.channels > 0u && id != 0u);
        if (!listed && pc.channels == 0u) {
            // Coverage against a mask: one channel, no interpolation.
            float a = id == 0u ? 0.0 : 1.0;
            antialiased[index] = a;
            float o = observed[index];
            float n = float(pc.width * pc.height);
            if (pc.loss == LOSS_MSE) terms.x = (a - o) * (a - o) / n;
            else if (pc.loss == LOSS_IOU) terms = vec3(0.0, a * o, a + o - a * o);
            else terms.x = a * distance_field[index] / n;
        } else if (!listed) {
            // Background with attributes, away from the object.
            store_antialiased(index, vec4(0.0));
            terms = loss_terms(index, vec4(0.0));
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

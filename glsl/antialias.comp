#version 460
// Forward of the listed pixels (see classify.comp): shade (coverage or interpolated
// attributes), antialias across silhouette edges between adjacent pixels, write the value
// and add the loss terms to stats (atomically; subgroup sums where a subgroup shares a
// view). Grid-stride loop over the work list.
#include "diff_pass.glsl"

layout(local_size_x = 64) in;

vec4 antialiased_value(uint view, ivec2 p, ivec2 size, uint id) {
    ViewData vd = views[view];
    vec4 c = colour_at(vd, view, p, id);
    vec4 a = c;
    for (int s = 0; s < 4; ++s) {
        ivec2 q = p + STEPS[s];
        if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, size))) continue;
        if (!pair_matters(id_at(p, view), id_at(q, view))) continue;
        // Pairs are always made from their left / upper pixel, as the backward does.
        Pair pair = s < 2 ? make_pair(vd, view, p, q, s == 0) : make_pair(vd, view, q, p, s == 2);
        if (pair.lost) atomicAdd(work_count[LOST_WALKS], 1u);
        if (!pair.valid) continue;
        ivec2 affected = pair.affects_g ? pair.g : pair.f;
        if (affected != p) continue;
        ivec2 other = pair.affects_g ? pair.f : pair.g;
        a += pair.weight * (colour_at(vd, view, other, id_at(other, view)) - c);
    }
    return a;
}

void main() {
    ivec2 size = ivec2(pc.width, pc.height);
    uint count = work_count[0];
    uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
    // Every invocation runs the same number of rounds so that subgroup operations see
    // the whole subgroup.
    uint rounds = (count + stride - 1u) / stride;
    for (uint round = 0u; round < rounds; ++round) {
        uint i = gl_GlobalInvocationID.x + round * stride;
        bool in_range = i < count;
        uint index = in_range ? work[i] : 0u;
        uint view = view_of(index);
        vec3 terms = vec3(0.0);
        if (in_range) {
            ivec2 p = pixel_of(index);
            vec4 a = antialiased_value(view, p, size, ids[index]);
            store_antialiased(index, a);
            terms = loss_terms(index, a);
        }
        if (subgroupAllEqual(view)) {
            terms = subgroupAdd(terms);
            if (subgroupElect()) {
                for (int k = 0; k < 3; ++k) {
                    if (terms[k] != 0.0) atomicAdd(stats[4u * view + uint(k)], terms[k]);
                }
            }
        } else if (in_range) {
            for (int k = 0; k < 3; ++k) {
                if (terms[k] != 0.0) atomicAdd(stats[4u * view + uint(k)], terms[k]);
            }
        }
    }
}

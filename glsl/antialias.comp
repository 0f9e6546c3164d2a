#version 460
// Forward of the listed pixels (see classify.comp): shade (coverage or interpolated
// attributes), antialias across silhouette edges between adjacent pixels, write the value
// and add the loss terms to stats_fixed (int64 atomics: the same sum in any order).
// Grid-stride loop over the work list.
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
        if (pair.missed && s < 2) atomicAdd(work_count[MISSED_STARTS], 1u);
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
    for (uint i = gl_GlobalInvocationID.x; i < count; i += stride) {
        uint index = work[i];
        uint view = view_of(index);
        vec4 a = antialiased_value(view, pixel_of(index), size, ids[index]);
        store_antialiased(index, a);
        vec3 terms = loss_excess(index, a);
        for (int k = 0; k < 3; ++k) {
            if (terms[k] != 0.0) atomicAdd(stats_fixed[3u * view + uint(k)], to_fixed(terms[k], pc.stats_shift));
        }
    }
}

#version 460
// Forward of the listed pixels (see classify.comp), grid-stride over the work list.
// Stage 0: for each pixel pair that matters, (p, p + (1, 0)) or (p, p + (0, 1)) as
// classify.comp listed them, the walk to the silhouette crossing (once per pair), written
// to pairs_x / pairs_y at p (every pair read later is one that matters, so is written
// here).
// Stage 1: shade (coverage or interpolated attributes), antialias across the silhouette
// edges of the pixel's four pairs, write the value and add the loss terms to stats_fixed
// (int64 atomics: the same sum in any order).
// Both stages also leave the ingredients of the backward's bound on its terms in
// work_count (diff_pass.glsl gradient_bounds): the crossings' camera terms per unit
// (stage 0); the colours, the loss magnitudes and with attributes the interpolation's
// terms per unit (stage 1).
#include "diff_pass.glsl"

layout(local_size_x = 64) in;

// The stage, a specialization constant (one pipeline per stage): CPU drivers run both sides
// of every branch, so a stage chosen at run time would pay for the other's code too.
layout(constant_id = 0) const uint STAGE = 0u;

// This invocation's maxima of the bound's ingredients, added once per subgroup at the end.
float largest_crossing = 0.0;
float largest_colour = 0.0;
float largest_shading = 0.0;
float largest_barycentric = 0.0;
vec2 largest_loss = vec2(0.0);

// The record of the pair of p with p + STEPS[s] (s = 0 or 1); its alpha in `alpha`.
uint pair_record(uint view, ivec2 p, ivec2 size, int s, out float alpha) {
    alpha = 0.0;
    ivec2 q = p + STEPS[s];
    if (any(greaterThanEqual(q, size)) || !pair_matters(id_at(p, view), id_at(q, view))) return 0u;
    Pair pair = make_pair(views[view], view, p, q, s == 0);
    if (pair.lost) atomicAdd(work_count[LOST_WALKS], 1u);
    if (pair.missed) atomicAdd(work_count[MISSED_STARTS], 1u);
    if (pair.valid) alpha = pair.crossing.alpha;
    largest_crossing = max(largest_crossing, crossing_magnitude(views[view], pair));
    return encode_pair(pair, p);
}

vec4 antialiased_value(uint view, ivec2 p, ivec2 size, uint id, bool has_pair) {
    // Only interpolation needs the camera (colour_at); coverage is 0 or 1.
    ViewData vd;
    if (CHANNELS > 0u) vd = views[view];
    vec4 c = vec4(0.0);
    if (CHANNELS == 0u) {
        c = colour_at(vd, view, p, id);
    } else if (id != 0u) {
        Triangle tri;
        vec2 np;
        vec3 e;
        c = shaded_colour_at(vd, view, p, id, tri, np, e);
        vec2 shading = shading_magnitudes(vd, view, tri, np, e);
        largest_shading = max(largest_shading, shading.x);
        largest_barycentric = max(largest_barycentric, shading.y);
    }
    vec4 own = abs(blended(c));
    largest_colour = max(largest_colour, own.x + own.y + own.z + own.w);
    vec4 a = c;
    for (int s = 0; s < 4 && has_pair; ++s) {
        ivec2 q = p + STEPS[s];
        if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, size))) continue;
        if (!pair_matters(id, id_at(q, view))) continue;
        Pair pair = pair_weight_at(view, p, s);
        if (!pair.valid) continue;
        ivec2 affected = pair.affects_g ? pair.g : pair.f;
        if (affected != p) continue;
        ivec2 other = pair.affects_g ? pair.f : pair.g;
        a += pair.weight * (blended_colour_at(vd, view, other, id_at(other, view)) - blended(c));
    }
    return a;
}

void main() {
    ivec2 size = ivec2(pc.width, pc.height);
    // Stage 0 runs over the pairs that matter (along x, then along y), stage 1 over the
    // listed pixels.
    uint along_x = work_count[PAIRS_X_COUNT];
    uint count = STAGE == 0u ? along_x + work_count[PAIRS_Y_COUNT] : work_count[0];
    uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
    uint done = 0u;
    for (uint i = gl_GlobalInvocationID.x; i < count; i += stride) {
        ++done;
        if (STAGE == 0u) {
            bool x = i < along_x;
            uint index = x ? pair_work_x[i] : pair_work_y[i - along_x];
            float alpha;
            uint record = pair_record(view_of(index), pixel_of(index), size, x ? 0 : 1, alpha);
            if (x) {
                pairs_x[index] = record;
                alphas_x[index] = alpha;
            } else {
                pairs_y[index] = record;
                alphas_y[index] = alpha;
            }
            continue;
        }
        uint entry = work[i];
        uint index = entry & ~HAS_PAIR;
        uint view = view_of(index);
        ivec2 p = pixel_of(index);
        vec4 a = antialiased_value(view, p, size, ids[index], (entry & HAS_PAIR) != 0u);
        // Against a mask the depth channel is 0 where the depth cannot count (as at the
        // pixels classify.comp does not list).
        if (COVERAGE != 0u && !depth_measured(index)) a[CHANNELS - 1u] = 0.0;
        store_antialiased(index, a);
        largest_loss = max(largest_loss, loss_magnitudes(index, a));
        vec3 terms = loss_excess(index, a);
        for (int k = 0; k < 3; ++k) {
            if (terms[k] != 0.0) atomicAdd(stats_fixed[3u * view + uint(k)], to_fixed(terms[k], pc.stats_shift));
        }
    }
    // A driver that ended the loop early (lavapipe's loop limit) is reported, not trusted.
    uint expected = grid_items(gl_GlobalInvocationID.x, stride, count);
    if (done < expected) atomicAdd(work_count[UNFINISHED], expected - done);
    if (STAGE == 0u) {
        add_maximum(CROSSING_MAX, largest_crossing);
    } else {
        add_maximum(COLOUR_MAX, largest_colour);
        add_maximum(SHADING_MAX, largest_shading);
        add_maximum(BARYCENTRIC_MAX, largest_barycentric);
        add_maximum(LOSS_MAX, largest_loss.x);
        add_maximum(LOSS_MAX + 1u, largest_loss.y);
    }
}

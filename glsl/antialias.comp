#version 460
// Forward of the compared image: shade (coverage or interpolated attributes), antialias
// across silhouette edges between adjacent pixels, and accumulate the loss terms of each
// view (workgroup sums added atomically into `stats`). One invocation per pixel; z = view.
#include "diff_pass.glsl"

shared float partial[3][64];

void main() {
    uint view = gl_GlobalInvocationID.z;
    ViewData vd = views[view];
    ivec2 size = ivec2(vd.size);
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    uint lane = gl_LocalInvocationIndex;
    partial[0][lane] = 0.0;
    partial[1][lane] = 0.0;
    partial[2][lane] = 0.0;
    if (all(lessThan(p, size))) {
        uint id = id_at(p, view);
        vec4 c = colour_at(vd, p, id);
        vec4 a = c;
        const ivec2 steps[4] = ivec2[4](ivec2(1, 0), ivec2(0, 1), ivec2(-1, 0), ivec2(0, -1));
        for (int s = 0; s < 4; ++s) {
            ivec2 q = p + steps[s];
            if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, size))) continue;
            // Pairs are always made from their left / upper pixel, as the backward does.
            bool forward = s < 2;
            Pair pair = forward ? make_pair(vd, view, p, q, s == 0) : make_pair(vd, view, q, p, s == 2);
            if (!pair.valid) continue;
            ivec2 affected = pair.affects_g ? pair.g : pair.f;
            if (affected != p) continue;
            ivec2 other = pair.affects_g ? pair.f : pair.g;
            a += pair.weight * (colour_at(vd, other, id_at(other, view)) - c);
        }
        uint index = pixel_index(p, view, vd);
        uint channels = image_channels();
        for (uint ch = 0u; ch < channels; ++ch) antialiased[index * channels + ch] = a[ch];
        vec4 o = load_observed(index);
        float n = vd.size.x * vd.size.y;
        if (pc.loss == LOSS_MSE) {
            vec4 d = a - o;
            partial[0][lane] = dot(d, d) / (n * float(channels));
        } else if (pc.loss == LOSS_IOU) {
            partial[1][lane] = a.x * o.x;
            partial[2][lane] = a.x + o.x - a.x * o.x;
        } else {
            partial[0][lane] = a.x * distance_field[index] / n;
        }
    }
    barrier();
    for (uint stride = 32u; stride > 0u; stride /= 2u) {
        if (lane < stride) {
            for (int k = 0; k < 3; ++k) partial[k][lane] += partial[k][lane + stride];
        }
        barrier();
    }
    if (lane == 0u) {
        for (int k = 0; k < 3; ++k) {
            if (partial[k][0] != 0.0) atomicAdd(stats[4u * view + uint(k)], partial[k][0]);
        }
    }
}

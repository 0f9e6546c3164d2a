// The losses (src/loss owns them): per-pixel terms, their change where the object is,
// and dL/dA, for the per-pixel passes of the differentiable renderer, which include this
// through diff_pass.glsl (so a loss costs no pass of its own). Adding a loss: a code in
// loss_codes.glsl and `Loss`, and its branch in loss_terms, loss_excess, loss_gradient,
// loss_magnitudes and loss_bound.
//
// The including shader declares, before the include: the buffers observed[],
// antialiased[], distance_field[], stats[] and ids[], the specialization constants LOSS,
// CHANNELS and DEPTH, the push constants pc.depth_scale, pc.depth_weight, pc.width,
// pc.height, pc.occlusion; and image_channels() (shade.glsl).
#include "loss_codes.glsl"

// As `MAX_DEPTH_RESIDUAL` in src/diff/mod.rs (metres).
const float MAX_DEPTH_RESIDUAL = 1000.0;

// Depth (DEPTH = 1) is the last channel: the interpolated camera-space z of the front
// surface at the pixel centre, compared only where the pixel is covered and the
// observation measured depth (observed > 0). It is not antialiased: the silhouette's
// gradient comes from the mask (or shading) channel, which is; so depth is a smooth
// function of the vertices and pose within each visibility piece, and `blended` removes
// it from every antialiasing term and its backward.
vec4 blended(vec4 v) {
    if (DEPTH != 0u) v[CHANNELS - 1u] = 0.0;
    return v;
}

// The channels compared by mse (all but depth).
uint mse_channels() { return max(CHANNELS, 1u) - DEPTH; }

// Whether pixel `index` compares depth; `residual` is rendered - observed there. Depth is
// compared where the rendering covers the pixel, the observation measured depth and its
// channel 0 (the mask, or the shading, 0 off the mask) shows the object: elsewhere the
// measurement is of another surface (the table behind, an occluder in front), whose
// distance from the rendered surface would make every pixel the silhouette sweeps over
// jump by its whole cost; the mask term places the silhouette.
bool depth_compared(uint index, vec4 a, out float residual) {
    residual = 0.0;
    if (DEPTH == 0u || ids[index] == 0u) return false;
    uint ch = CHANNELS - 1u;
    float o = observed[index * CHANNELS + ch];
    // Residuals past 1 km are clamped (a bound the fixed-point loss sums rely on).
    residual = clamp(a[ch] - o, -MAX_DEPTH_RESIDUAL, MAX_DEPTH_RESIDUAL);
    return o > 0.0 && observed[index * CHANNELS] > 0.0;
}

// The depth term of one pixel, bounded (Geman-McClure) in units of pc.depth_scale (s):
// u^2 / (1 + u^2) with u = r / s, about u^2 for small residuals, half a wrong mask pixel
// at s and never more than one, so that a depth edge inside the silhouette (an open
// container's rim before its inside) or a sensor's outlier does not outweigh the rest;
// times the weight / pixels.
float depth_term(float r, float n) {
    float u = r / pc.depth_scale;
    return pc.depth_weight * (u * u / (1.0 + u * u)) / n;
}

float depth_term_gradient(float r, float n) {
    float u = r / pc.depth_scale;
    float q = 1.0 + u * u;
    return pc.depth_weight * 2.0 * u / (q * q * pc.depth_scale * n);
}

// Pixels that count for nothing, neither mask (or shading) nor depth:
// - unknown ones, where the observation's channel 0 is below 0 (`loss::UNKNOWN`: hidden
//   by something in front, as outside BOP's mask_visib but inside its mask, or ignored);
// - with depth and pc.occlusion > 0 (metres), covered pixels that the observation shows
//   as background (channel 0 is 0) with a measured depth nearer than the rendered surface
//   by more than pc.occlusion: something stands in front of the object there. A pixel the
//   mask shows as object is never occluded, so its depth term pulls even from far off.
// Both are zero terms and zero gradients, so the gradients of the other pixels (the
// antialiased pixels at the border of an ignored region included) stay exact; the
// occluded set changes with the rendered depth (piecewise, as visibility does).
bool unknown(uint index) { return observed[index * image_channels()] < 0.0; }

// Whether pixel `index`'s rendered depth can count for anything (compared, or tested for
// occlusion): the observation measured depth there and the pixel is known. Against a mask
// (COVERAGE = 1) nothing else needs the depth, so a covered pixel where it cannot count
// is not interpolated away from the silhouette (classify.comp) and its depth channel is 0.
bool depth_measured(uint index) {
    return DEPTH != 0u && observed[index * CHANNELS + CHANNELS - 1u] > 0.0 && !unknown(index);
}

// Whether a covered pixel away from the silhouette needs its attributes interpolated.
bool interpolated_inside(uint index) {
    return CHANNELS > 0u && (COVERAGE == 0u || depth_measured(index));
}

bool occluded(uint index, vec4 a) {
    if (DEPTH == 0u || pc.occlusion <= 0.0 || ids[index] == 0u) return false;
    float o = observed[index * CHANNELS + CHANNELS - 1u];
    return observed[index * CHANNELS] == 0.0 && o > 0.0 && a[CHANNELS - 1u] - o > pc.occlusion;
}

vec4 load_antialiased(uint index) {
    vec4 a = vec4(0.0);
    for (uint ch = 0u; ch < image_channels(); ++ch) a[ch] = antialiased[index * image_channels() + ch];
    return a;
}

vec4 load_observed(uint index) {
    vec4 o = vec4(0.0);
    for (uint ch = 0u; ch < image_channels(); ++ch) o[ch] = observed[index * image_channels() + ch];
    return o;
}

// Loss terms of one pixel with antialiased value a: (sum term, intersection, union).
// Only the background terms (a = 0) are summed over the whole image, once per
// observation (classify.comp stage 1); every evaluation adds, for the pixels near the
// object, what its value changes: loss_excess.
vec3 loss_terms(uint index, vec4 a) {
    if (unknown(index)) return vec3(0.0);
    vec4 o = load_observed(index);
    float n = pc.loss_pixels;
    if (LOSS == LOSS_MSE) {
        // Only called for the background (a = 0), where depth is not compared.
        vec4 d = blended(a - o);
        return vec3(dot(d, d) / (n * float(mse_channels())), 0.0, 0.0);
    } else if (LOSS == LOSS_IOU) {
        return vec3(0.0, a.x * o.x, a.x + o.x - a.x * o.x);
    }
    return vec3(a.x * distance_field[index] / n, 0.0, 0.0);
}

// loss_terms(index, a) - loss_terms(index, 0), in forms without cancellation (at an
// occluded pixel, which counts for nothing, minus the background's terms).
vec3 loss_excess(uint index, vec4 a) {
    if (unknown(index)) return vec3(0.0);
    if (occluded(index, a)) return -loss_terms(index, vec4(0.0));
    vec4 o = load_observed(index);
    float n = pc.loss_pixels;
    if (LOSS == LOSS_MSE) {
        // (a - o)^2 - o^2 = a (a - 2 o)
        float excess = dot(blended(a), blended(a - 2.0 * o)) / (n * float(mse_channels()));
        float r;
        if (depth_compared(index, a, r)) excess += depth_term(r, n);
        return vec3(excess, 0.0, 0.0);
    } else if (LOSS == LOSS_IOU) {
        return vec3(0.0, a.x * o.x, a.x * (1.0 - o.x));
    }
    return vec3(a.x * distance_field[index] / n, 0.0, 0.0);
}

// dL/dA at one pixel, given the antialiased value A there (after the forward pass).
vec4 loss_gradient(uint index, uint view) {
    float n = pc.loss_pixels;
    vec4 a = load_antialiased(index);
    vec4 g = vec4(0.0);
    if (unknown(index) || occluded(index, a)) return g;
    vec4 o = load_observed(index);
    if (LOSS == LOSS_MSE) {
        g = 2.0 * blended(a - o) / (n * float(mse_channels()));
        float r;
        if (depth_compared(index, a, r)) g[CHANNELS - 1u] = depth_term_gradient(r, n);
    } else if (LOSS == LOSS_IOU) {
        float intersection = stats[4u * view + 1u];
        float union_ = stats[4u * view + 2u];
        if (union_ > 0.0) g.x = -(o.x * union_ - intersection * (1.0 - o.x)) / (union_ * union_);
    } else {
        g.x = distance_field[index] / n;
    }
    for (uint ch = image_channels(); ch < 4u; ++ch) g[ch] = 0.0;
    return g;
}

// Per-pixel magnitudes whose largest values over the listed pixels (`largest`, taken in
// antialias.comp after the value A is known) give loss_bound, a bound on |dL/dA| at every
// listed pixel for the backward's fixed-point scale (diff_pass.glsl gradient_bounds).
vec2 loss_magnitudes(uint index, vec4 a) {
    if (unknown(index) || occluded(index, a)) return vec2(0.0);
    float n = pc.loss_pixels;
    vec4 o = load_observed(index);
    if (LOSS == LOSS_MSE) {
        vec4 d = abs(blended(a - o));
        float m = 2.0 * max(max(d.x, d.y), max(d.z, d.w)) / (n * float(mse_channels()));
        float r;
        if (depth_compared(index, a, r)) m = max(m, abs(depth_term_gradient(r, n)));
        return vec2(m, 0.0);
    } else if (LOSS == LOSS_IOU) {
        return vec2(abs(o.x), abs(1.0 - o.x));
    }
    return vec2(abs(distance_field[index]) / n, 0.0);
}

// |dL/dA| <= loss_bound(largest, view) at every listed pixel of the view: for IoU,
// |o U - I (1 - o)| / U^2 with the view's intersection I and union U.
float loss_bound(vec2 largest, uint view) {
    if (LOSS == LOSS_IOU) {
        float intersection = stats[4u * view + 1u];
        float union_ = stats[4u * view + 2u];
        return union_ > 0.0 ? (largest.x * union_ + abs(intersection) * largest.y) / (union_ * union_) : 0.0;
    }
    return largest.x;
}

// Declarations shared by antialias.comp and antialias_backward.comp: bindings 0-9, push
// constants, and the per-pixel loss gradient dL/dA.
#extension GL_EXT_shader_atomic_float : require
#include "views.glsl"

layout(local_size_x = 8, local_size_y = 8) in;

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };
layout(set = 0, binding = 1, std430) readonly buffer Triangles { uint triangles[]; };
layout(set = 0, binding = 2, std430) readonly buffer Neighbours { uint neighbours[]; };
layout(set = 0, binding = 3, std430) readonly buffer Views { ViewData views[]; };
layout(set = 0, binding = 4, std430) readonly buffer Attributes { float attributes[]; };
layout(set = 0, binding = 5, r32ui) readonly uniform uimage2DArray ids;
layout(set = 0, binding = 6, std430) readonly buffer Observed { float observed[]; };    // [view][y][x][channel]
layout(set = 0, binding = 7, std430) readonly buffer Distance { float distance_field[]; };  // [view][y][x]
layout(set = 0, binding = 8, std430) buffer Antialiased { float antialiased[]; };        // [view][y][x][channel]
layout(set = 0, binding = 9, std430) buffer Stats { float stats[]; };                   // [view][4]

// Losses (`loss::Loss`): mean squared error, soft IoU, signed-distance-weighted coverage.
const uint LOSS_MSE = 0u;
const uint LOSS_IOU = 1u;
const uint LOSS_DISTANCE = 2u;

// stats[4 view + k]: 0 = sum of per-pixel loss terms, 1 = intersection, 2 = union,
// 3 = the view's loss (written by loss_finalize.comp).

layout(push_constant, std430) uniform Constants {
    uint channels;  // 0: coverage, else interpolated attributes per vertex
    uint loss;
    uint vertex_count;
    uint pad;
} pc;

#include "diff.glsl"
#include "shade.glsl"

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

// dL/dA at one pixel, given the antialiased value A there (after the forward pass).
vec4 loss_gradient(uint index, uint view, ViewData vd) {
    float n = vd.size.x * vd.size.y;
    vec4 a = load_antialiased(index);
    vec4 o = load_observed(index);
    vec4 g = vec4(0.0);
    if (pc.loss == LOSS_MSE) {
        g = 2.0 * (a - o) / (n * float(image_channels()));
    } else if (pc.loss == LOSS_IOU) {
        float intersection = stats[4u * view + 1u];
        float union_ = stats[4u * view + 2u];
        if (union_ > 0.0) g.x = -(o.x * union_ - intersection * (1.0 - o.x)) / (union_ * union_);
    } else {
        g.x = distance_field[index] / n;
    }
    for (uint ch = image_channels(); ch < 4u; ++ch) g[ch] = 0.0;
    return g;
}

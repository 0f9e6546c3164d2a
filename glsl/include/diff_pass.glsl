// Declarations shared by the per-pixel passes (classify.comp, antialias.comp,
// antialias_backward.comp): bindings, push constants, the per-pixel loss gradient dL/dA.
//
// classify.comp handles every pixel whose neighbourhood shows one triangle (or background)
// and needs no interpolation, and appends the others (silhouette and occlusion pixels,
// and with attributes every covered pixel) to the work list; the other two passes run
// over that list only, so their cost follows the silhouette's length, not the image's
// area.
#extension GL_EXT_shader_atomic_float : require
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_KHR_shader_subgroup_basic : require
#extension GL_KHR_shader_subgroup_ballot : require
#extension GL_KHR_shader_subgroup_vote : require
#include "views.glsl"
#include "fixed_point.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };
layout(set = 0, binding = 1, std430) readonly buffer Triangles { uint triangles[]; };
layout(set = 0, binding = 2, std430) readonly buffer Neighbours { uint neighbours[]; };
layout(set = 0, binding = 3, std430) readonly buffer Views { ViewData views[]; };
layout(set = 0, binding = 4, std430) readonly buffer Attributes { float attributes[]; };               // [view][vertex][channel]
layout(set = 0, binding = 5, std430) readonly buffer Ids { uint ids[]; };                 // [view][y][x]
layout(set = 0, binding = 6, std430) readonly buffer Observed { float observed[]; };    // [view][y][x][channel]
layout(set = 0, binding = 7, std430) readonly buffer Distance { float distance_field[]; };  // [view][y][x]
layout(set = 0, binding = 8, std430) buffer Antialiased { float antialiased[]; };        // [view][y][x][channel]
layout(set = 0, binding = 9, std430) buffer Stats { float stats[]; };                   // [view][4]
layout(set = 0, binding = 12, std430) buffer Work { uint work[]; };                     // pixel indices
layout(set = 0, binding = 13, std430) buffer WorkCount { uint work_count[]; };          // count, 3 dispatch args, then the slots below
layout(set = 0, binding = 14, std430) buffer StatsFixed { int64_t stats_fixed[]; };    // [view][3], fixed point at pc.stats_shift
layout(set = 0, binding = 15, std430) buffer GradCameraFixed { int64_t grad_camera_fixed[]; };  // [view][vertex][3]
layout(set = 0, binding = 16, std430) buffer GradAttributesFixed { int64_t grad_attributes_fixed[]; };  // [view][vertex][channel]
layout(set = 0, binding = 17, std430) buffer Boxes { int boxes[]; };  // see bounds.comp
// The pair records (diff.glsl encode_pair) of each listed pixel p with p + (1, 0) and with
// p + (0, 1): antialias.comp stage 0 walks to every crossing once and writes them; the
// antialias and its backward read them instead of walking again.
layout(set = 0, binding = 18, std430) buffer PairsX { uint pairs_x[]; };  // [view][y][x]
layout(set = 0, binding = 19, std430) buffer PairsY { uint pairs_y[]; };  // [view][y][x]
// Nonzero for each block of VERTEX_BLOCK vertices that got a camera-gradient term
// (antialias_backward.comp); pose_gradient.comp visits only those blocks.
layout(set = 0, binding = 20, std430) buffer Touched { uint touched[]; };
// Each valid pair's crossing parameter alpha beside its record (what antialiasing needs:
// pair_weight_at), [view][y][x].
layout(set = 0, binding = 21, std430) buffer AlphasX { float alphas_x[]; };
layout(set = 0, binding = 22, std430) buffer AlphasY { float alphas_y[]; };
const uint VERTEX_BLOCK = 64u;

// work_count slots after the count and dispatch arguments (LOST_WALKS = 4 in diff.glsl):
const uint CAMERA_MAX = 5u;     // magnitude_bits of the largest camera-gradient term
const uint ATTRIBUTE_MAX = 6u;  // the same for attribute-gradient terms
// A listed pixel adds at most this many terms to one vertex's sum (its own triangle's
// interpolation and the crossings of its two forward pairs).
const uint TERMS_PER_LISTED = 3u;

// stats[4 view + k]: 0 = sum of per-pixel loss terms, 1 = intersection, 2 = union,
// 3 = the view's loss. antialias.comp adds its terms to stats_fixed (int64 fixed point at
// pc.stats_shift, chosen on the host from a bound on the sums, so the order of the adds
// cannot change the result), and so does classify.comp, once per subgroup;
// loss_finalize.comp computes the loss from those sums.

layout(push_constant, std430) uniform Constants {
    uint channels;  // 0: coverage, else interpolated attributes per vertex
    uint loss;
    uint vertex_count;
    uint width;
    uint height;
    int stats_shift;
    uint stage;  // antialias.comp: 0 finds the pairs, 1 antialiases; its backward: 0
                 // measures the largest terms, 1 adds them
    uint depth;     // 1: the last channel is camera-space depth (see depth_term)
    uint coverage;  // 1: channel 0 is coverage, a constant attribute 1 (mask with depth)
    float depth_scale;   // metres: residuals up to it cost quadratically (Huber)
    float depth_weight;
} pc;

#include "diff.glsl"
#include "shade.glsl"

// The pixel and view of a pixel index (view * height + row) * width + column.
ivec2 pixel_of(uint index) { return ivec2(index % pc.width, (index / pc.width) % pc.height); }
uint view_of(uint index) { return index / (pc.width * pc.height); }

void store_antialiased(uint index, vec4 a) {
    for (uint ch = 0u; ch < image_channels(); ++ch) antialiased[index * image_channels() + ch] = a[ch];
}

// Whether the pair of pixels showing ids a and b can change the image: with coverage only
// where one is background (both colours are 1 otherwise, so antialiasing moves nothing).
bool pair_matters(uint a, uint b) {
    bool interpolated = pc.channels > 0u && pc.coverage == 0u;
    return a != b && (interpolated || (a == 0u) != (b == 0u));
}

const ivec2 STEPS[4] = ivec2[4](ivec2(1, 0), ivec2(0, 1), ivec2(-1, 0), ivec2(0, -1));

// The pair of pixel p with its neighbour p + STEPS[s] (inside the image, pair_matters),
// from the record its left / upper pixel holds.
Pair pair_at(ViewData vd, uint view, ivec2 p, int s) {
    ivec2 q = p + STEPS[s];
    ivec2 first = s < 2 ? p : q;
    uint index = pixel_index(first, view);
    uint record = (s % 2 == 0) ? pairs_x[index] : pairs_y[index];
    return s < 2 ? decode_pair(vd, p, q, s == 0, record) : decode_pair(vd, q, p, s == 2, record);
}

// The same pair as far as antialiasing needs it (decode_pair_weight: no triangle loaded).
Pair pair_weight_at(uint view, ivec2 p, int s) {
    ivec2 q = p + STEPS[s];
    ivec2 first = s < 2 ? p : q;
    uint index = pixel_index(first, view);
    uint record = (s % 2 == 0) ? pairs_x[index] : pairs_y[index];
    float alpha = (s % 2 == 0) ? alphas_x[index] : alphas_y[index];
    return s < 2 ? decode_pair_weight(p, q, record, alpha) : decode_pair_weight(q, p, record, alpha);
}

#include "loss.glsl"

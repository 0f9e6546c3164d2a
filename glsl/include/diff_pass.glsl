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
layout(set = 0, binding = 12, std430) buffer Work { uint work[]; };                     // pixel indices | HAS_PAIR
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
// A bit per block of VERTEX_BLOCK vertices (bit b of word w: block 32 w + b), set where
// the block got a camera-gradient term (antialias_backward.comp); pose_gradient.comp
// visits only those blocks.
layout(set = 0, binding = 20, std430) buffer Touched { uint touched[]; };
// Each valid pair's crossing parameter alpha beside its record (what antialiasing needs:
// pair_weight_at), [view][y][x].
layout(set = 0, binding = 21, std430) buffer AlphasX { float alphas_x[]; };
layout(set = 0, binding = 22, std430) buffer AlphasY { float alphas_y[]; };
const uint VERTEX_BLOCK = 8u;  // as in src/diff/mod.rs
// A work list entry's flag: a pair of its pixel with one of its four neighbours matters
// (pair_matters). Pixels without one (interpolated inside the silhouette) skip the pair
// loops: on a CPU driver a loop runs while any lane of the SIMD batch needs it. A pixel
// index is below 2^30 (the compared image, 4 bytes a pixel and channel, fits in one
// buffer: check_scene_fits in src/diff/mod.rs).
const uint HAS_PAIR = 0x80000000u;
// The pixel pairs that matter, as the pixel indices of their left / upper pixels: along x
// and along y, each appended by classify.comp (counts in work_count[PAIRS_X_COUNT] and
// [PAIRS_Y_COUNT]). antialias.comp stage 0 walks these instead of both pairs of every
// listed pixel, about a third of which matter: on a CPU driver a lane whose pair does not
// matter waits while the others of its SIMD batch walk.
layout(set = 0, binding = 23, std430) buffer PairWorkX { uint pair_work_x[]; };
layout(set = 0, binding = 24, std430) buffer PairWorkY { uint pair_work_y[]; };
const uint PAIRS_X_COUNT = 17u;  // work_count slots (as in src/diff/mod.rs), then at
const uint PAIRS_Y_COUNT = 18u;  // PAIR_DISPATCH the pairs pass's dispatch arguments
const uint PAIR_DISPATCH = 19u;  // (glsl/work_args.comp)

// work_count slots after the count and dispatch arguments (LOST_WALKS = 4, MISSED_STARTS
// = 7 and UNFINISHED = 8 in diff.glsl). The backward adds its terms in one pass, at a
// scale set by a bound on the largest term that the forward's passes leave behind
// (gradient_bounds below):
const uint CAMERA_MAX = 5u;     // magnitude_bits of that bound for camera-gradient terms
const uint ATTRIBUTE_MAX = 6u;  // the same for attribute-gradient terms
// The bound's ingredients, magnitude_bits maxima over the listed pixels:
const uint CROSSING_MAX = 9u;   // a crossing's camera terms per unit d L / d alpha (pairs)
const uint COLOUR_MAX = 10u;    // |blended colour|_1 (antialias)
const uint SHADING_MAX = 11u;   // interpolation's camera terms per unit |dL/dc| (antialias)
const uint BARYCENTRIC_MAX = 12u;  // |barycentric| (antialias)
const uint LOSS_MAX = 13u;      // and 14: loss_magnitudes (antialias)
// What the backward's terms came to (its largest magnitudes): above the bound, the
// resolve reports NaN rather than a sum that may have wrapped.
const uint CAMERA_SEEN = 15u;
const uint ATTRIBUTE_SEEN = 16u;
// A listed pixel adds at most this many terms to one vertex's sum (its own triangle's
// interpolation and the crossings of its two forward pairs).
const uint TERMS_PER_LISTED = 3u;

// stats[4 view + k]: 0 = sum of per-pixel loss terms, 1 = intersection, 2 = union,
// 3 = the view's loss. antialias.comp adds its terms to stats_fixed (int64 fixed point at
// pc.stats_shift, chosen on the host from a bound on the sums, so the order of the adds
// cannot change the result), and so does classify.comp, once per subgroup;
// loss_finalize.comp computes the loss from those sums.

layout(push_constant, std430) uniform Constants {
    uint vertex_count;
    uint width;
    uint height;
    int stats_shift;
    uint stage;     // bounds.comp's stage (antialias.comp and classify.comp: STAGE)
    float depth_scale;   // metres: the depth cost's scale (loss.glsl depth_term)
    float depth_weight;
    float occlusion;     // metres: a covered background pixel measured nearer is occluded (loss.glsl)
    float loss_pixels;   // the pixel count a view's loss is averaged over (loss.glsl)
} pc;

// What the scene compares, as specialization constants (ids 1 to 4; a pipeline per
// combination, `PassVariant` in src/diff/mod.rs), not push constants: a CPU driver runs
// both sides of every branch, so a branch on a push constant would make every pixel pay
// for every loss and channel layout.
layout(constant_id = 1) const uint LOSS = 0u;      // LOSS_MSE, LOSS_IOU, LOSS_DISTANCE
layout(constant_id = 2) const uint CHANNELS = 0u;  // 0: coverage, else interpolated attributes per vertex
layout(constant_id = 3) const uint DEPTH = 0u;     // 1: the last channel is camera-space depth
layout(constant_id = 4) const uint COVERAGE = 0u;  // 1: channel 0 is coverage (mask with depth)

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
    bool interpolated = CHANNELS > 0u && COVERAGE == 0u;
    return a != b && (interpolated || (a == 0u) != (b == 0u));
}

const ivec2 STEPS[4] = ivec2[4](ivec2(1, 0), ivec2(0, 1), ivec2(-1, 0), ivec2(0, -1));

// The pair of pixel p with its neighbour p + STEPS[s] (inside the image, pair_matters),
// from the record and the alpha its left / upper pixel holds (decode_pair).
Pair pair_at(ViewData vd, uint view, ivec2 p, int s) {
    ivec2 q = p + STEPS[s];
    ivec2 first = s < 2 ? p : q;
    uint index = pixel_index(first, view);
    uint record = (s % 2 == 0) ? pairs_x[index] : pairs_y[index];
    float alpha = (s % 2 == 0) ? alphas_x[index] : alphas_y[index];
    return s < 2 ? decode_pair(vd, p, q, record, alpha) : decode_pair(vd, q, p, record, alpha);
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

// blended(colour_at(...)): what antialiasing moves across a silhouette. Against a mask
// with depth alone (coverage and the depth, which is not antialiased) that is the
// coverage, and no triangle is loaded.
vec4 blended_colour_at(ViewData vd, uint view, ivec2 pixel, uint id) {
    if (COVERAGE != 0u && CHANNELS == 1u + DEPTH) return vec4(id != 0u ? 1.0 : 0.0, 0.0, 0.0, 0.0);
    return blended(colour_at(vd, view, pixel, id));
}

// d camera / d clip applied to a clip-space gradient: x_clip = sx x + ox z,
// y_clip = sy y + oy z, w = z.
vec3 camera_gradient(ViewData vd, vec3 g_clip) {
    vec2 s = clip_scale(vd);
    vec2 o = clip_shift(vd);
    return vec3(s.x * g_clip.x, s.y * g_clip.y, o.x * g_clip.x + o.y * g_clip.y + g_clip.z);
}

// A bound on |camera_gradient(vd, g)| for every |g| <= bound (componentwise).
vec3 camera_gradient_bound(ViewData vd, vec3 bound) {
    vec2 s = abs(clip_scale(vd));
    vec2 o = abs(clip_shift(vd));
    return vec3(s.x * bound.x, s.y * bound.y, o.x * bound.x + o.y * bound.y + bound.z);
}

float largest_component(vec3 v) { return max(abs(v.x), max(abs(v.y), abs(v.z))); }

// The clip-space gradients of a crossing's edge vertices (triangle corners (edge + 1) % 3
// and (edge + 2) % 3) for dL/d alpha = g_alpha: alpha = ef / (ef - eb), the edge function
// at the pair's two pixel centres.
void crossing_gradients(ViewData vd, Pair pair, float g_alpha, out vec3 gi, out vec3 gj) {
    Crossing c = pair.crossing;
    float d = c.ef - c.eb;
    float g_ef = g_alpha * -c.eb / (d * d);
    float g_eb = g_alpha * c.ef / (d * d);
    int i = (c.edge + 1) % 3;
    int j = (c.edge + 2) % 3;
    gi = vec3(0.0);
    gj = vec3(0.0);
    edge_function_backward(c.tri.clip[i], c.tri.clip[j], pixel_ndc(pair.f, vd), g_ef, gi, gj);
    edge_function_backward(c.tri.clip[i], c.tri.clip[j], pixel_ndc(pair.g, vd), g_eb, gi, gj);
}

// The largest camera term of a crossing per unit dL/d alpha (antialias.comp stage 0).
float crossing_magnitude(ViewData vd, Pair pair) {
    if (!pair.valid || pair.clamped) return 0.0;
    vec3 gi, gj;
    crossing_gradients(vd, pair, 1.0, gi, gj);
    return max(largest_component(camera_gradient(vd, gi)), largest_component(camera_gradient(vd, gj)));
}

// The backward's one pass needs the scale of its fixed-point sums before it adds the first
// term, so the forward passes record what bounds every term (the ingredient slots above)
// and the backward multiplies them out (gradient_bounds). With G a bound on |dL/dA| at
// every listed pixel (loss_bound), C on |blended colour|_1, X the crossings' slot, S the
// interpolation's and B the barycentrics':
//   a crossing's term is d L/d alpha = dot(dL/dA, blended(cf - cg)) (at most 2 G C) times
//     its camera term per unit, at most X;
//   a pixel's dL/dc is its own dL/dA plus +-w times each of its (at most four) pairs'
//     (w <= 1/2), so |dL/dc| <= 3 G: its interpolation terms are at most 3 G S (camera) and
//     3 G B (attributes; with depth the depth attribute's goes to the camera-space z, so
//     a camera term is at most 3 G (S + B)).
// Twice that, for float rounding. The bound is loose by the spread of dL/dA over the
// pixels (the largest term may sit where dL/dA is small); the sums' resolution stays far
// below float32's (include/fixed_point.glsl).
vec2 gradient_bounds() {
    float g = 0.0;
    vec2 largest = vec2(uintBitsToFloat(work_count[LOSS_MAX]), uintBitsToFloat(work_count[LOSS_MAX + 1u]));
    for (uint view = 0u; view < uint(views.length()); ++view) g = max(g, loss_bound(largest, view));
    // Every dL/dA is 0: no term is added (an ingredient that is not finite, from a
    // degenerate triangle, must not make the bound NaN then).
    if (g == 0.0) return vec2(0.0);
    float colour = uintBitsToFloat(work_count[COLOUR_MAX]);
    float crossing = uintBitsToFloat(work_count[CROSSING_MAX]);
    float shading = uintBitsToFloat(work_count[SHADING_MAX]);
    float barycentric = uintBitsToFloat(work_count[BARYCENTRIC_MAX]);
    float interpolation = shading + (DEPTH != 0u ? barycentric : 0.0);
    float camera = 2.0 * g * max(2.0 * colour * crossing, 3.0 * interpolation);
    float attributes_ = 2.0 * 3.0 * g * barycentric;
    return vec2(camera, attributes_);
}

// Per unit |dL/dc|: bounds on the interpolation's camera terms at a pixel and on its
// barycentrics, as antialias_backward.comp handle_pixel forms
// them: dL/db_k = sum over channels of dL/dc * attribute, dL/de_k = (dL/db_k -
// dot(b, dL/db)) / sum(e), then through the edge functions to the clip-space corners.
// The pixel's triangle `tri` and its edge functions `e` at the pixel's centre np, as the
// forward found them.
vec2 shading_magnitudes(ViewData vd, uint view, Triangle tri, vec2 np, vec3 e) {
    float sum = e.x + e.y + e.z;
    vec3 b = abs(e / sum);
    vec3 g_b = vec3(0.0);
    for (int k = 0; k < 3; ++k) {
        for (uint ch = first_interpolated(); ch < CHANNELS; ++ch) g_b[k] += abs(attributes[attribute_index(view, tri.v[k], ch)]);
    }
    vec3 g_e = (g_b + dot(b, g_b)) / abs(sum);
    vec3 g_clip[3] = vec3[3](vec3(0.0), vec3(0.0), vec3(0.0));
    edge_function_backward_bound(tri.clip[1], tri.clip[2], np, g_e.x, g_clip[1], g_clip[2]);
    edge_function_backward_bound(tri.clip[2], tri.clip[0], np, g_e.y, g_clip[2], g_clip[0]);
    edge_function_backward_bound(tri.clip[0], tri.clip[1], np, g_e.z, g_clip[0], g_clip[1]);
    float camera = 0.0;
    for (int k = 0; k < 3; ++k) camera = max(camera, largest_component(camera_gradient_bound(vd, g_clip[k])));
    return vec2(camera, max(b.x, max(b.y, b.z)));
}

// Adds a maximum of non-negative floats to a slot: once per subgroup.
void add_maximum(uint slot, float value) {
    uint bits = subgroupMax(magnitude_bits(value));
    if (subgroupElect() && bits > 0u) atomicMax(work_count[slot], bits);
}

#version 460
// Backward of antialias.comp over the work list (pixels off the list have no pair and
// nothing interpolated): dL/dA per pixel (loss_gradient) pushed to the camera-space
// vertex positions of every view (grad_camera_fixed[view][vertex], int64 fixed point, so
// the sums do not depend on the order of the adds) through
//   - the silhouette crossings: each pair is handled by its left / upper pixel, and
//     d alpha / d(edge function) chains to the edge's two clip-space vertices;
//   - with attributes, the interpolation: dL/dc per pixel (own term plus the pair terms
//     that moved colour into or out of it) to the attributes (grad_attributes; the depth
//     attribute's, the vertex's camera-space z, to that z) and, via the exact
//     barycentrics, to the triangle's three clip-space vertices.
// The pairs are the forward's records (pairs_x, pairs_y), so no pass here walks.
// One pass: the scale of the fixed-point sums (include/fixed_point.glsl) comes from a
// bound on every term that the forward left behind (diff_pass.glsl gradient_bounds); the
// first invocation stores it (work_count[CAMERA_MAX], [ATTRIBUTE_MAX]) for
// fixed_resolve.comp and pose_gradient.comp, and every invocation records the largest
// term it added (work_count[CAMERA_SEEN], [ATTRIBUTE_SEEN]), so that a term above the
// bound (or not finite) makes the resolved sums NaN instead of silently wrong.
#include "diff_pass.glsl"

layout(local_size_x = 64) in;

// The largest term magnitudes this invocation added (magnitude_bits), merged into
// work_count once per subgroup at the end.
uint largest_camera = 0u;
uint largest_attribute = 0u;

// The scales of the sums (set once per invocation in main).
int camera_shift = 0;
int attribute_shift = 0;

// Adds one term of a fixed-point sum.
void add_camera_term(uint at, float g) {
    if (g == 0.0) return;
    largest_camera = max(largest_camera, magnitude_bits(g));
    atomicAdd(grad_camera_fixed[at], to_fixed(g, camera_shift));
}

void add_attribute_term(uint at, float g) {
    if (g == 0.0) return;
    largest_attribute = max(largest_attribute, magnitude_bits(g));
    atomicAdd(grad_attributes_fixed[at], to_fixed(g, attribute_shift));
}

// Adds a clip-space gradient of vertex v, and g_z to its camera-space z (the depth
// attribute's gradient: the attribute is that z).
void add_clip_gradient(ViewData vd, uint view, uint v, vec3 g_clip, float g_z) {
    vec3 g = camera_gradient(vd, g_clip);
    g.z += g_z;
    uint at = 3u * (view * pc.vertex_count + v);
    uint block = v / VERTEX_BLOCK;
    uint bit = 1u << (block % 32u);
    if ((touched[block / 32u] & bit) == 0u) atomicOr(touched[block / 32u], bit);
    add_camera_term(at, g.x);
    add_camera_term(at + 1u, g.y);
    add_camera_term(at + 2u, g.z);
}

void crossing_backward(ViewData vd, uint view, Pair pair) {
    if (pair.clamped) return;
    ivec2 affected = pair.affects_g ? pair.g : pair.f;
    vec4 ga = loss_gradient(pixel_index(affected, view), view);
    vec4 cf = blended_colour_at(vd, view, pair.f, id_at(pair.f, view));
    vec4 cg = blended_colour_at(vd, view, pair.g, id_at(pair.g, view));
    float g_alpha = dot(ga, cf - cg);
    if (g_alpha == 0.0) return;
    vec3 gi, gj;
    crossing_gradients(vd, pair, g_alpha, gi, gj);
    int edge = pair.crossing.edge;
    add_clip_gradient(vd, view, pair.crossing.tri.v[(edge + 1) % 3], gi, 0.0);
    add_clip_gradient(vd, view, pair.crossing.tri.v[(edge + 2) % 3], gj, 0.0);
}

void handle_pixel(uint entry) {
    uint index = entry & ~HAS_PAIR;
    bool any_pair = (entry & HAS_PAIR) != 0u;
    uint view = view_of(index);
    ivec2 size = ivec2(pc.width, pc.height);
    ivec2 p = pixel_of(index);
    const ivec2 steps[4] = STEPS;
    uint id = ids[index];
    bool interpolated = id != 0u && interpolated_inside(index);
    ViewData vd = views[view];
    vec4 g_colour = interpolated ? loss_gradient(index, view) : vec4(0.0);
    // The pairs move colour between the pixels of the interpolated channels too; with
    // coverage (a mask with depth) only channel 0, which is not interpolated (shade.glsl),
    // so then only this pixel's forward pairs (their crossings) are visited.
    bool colour_pairs = interpolated && COVERAGE == 0u;
    for (int s = 0; s < (colour_pairs ? 4 : 2) && any_pair; ++s) {
        ivec2 q = p + steps[s];
        if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, size))) continue;
        if (!pair_matters(id, id_at(q, view))) continue;
        bool forward = s < 2;
        Pair pair = pair_at(vd, view, p, s);
        if (!pair.valid) continue;
        if (forward) crossing_backward(vd, view, pair);
        if (colour_pairs) {
            // out[a] += w (c[o] - c[a]): d/dc[a] = -w, d/dc[o] = +w.
            ivec2 affected = pair.affects_g ? pair.g : pair.f;
            vec4 ga = loss_gradient(pixel_index(affected, view), view);
            g_colour += (affected == p ? -pair.weight : pair.weight) * blended(ga);
        }
    }
    if (!interpolated) return;
    Triangle tri = load_triangle(vd, id - 1u);
    vec2 np = pixel_ndc(p, vd);
    vec3 e = edge_functions(tri.clip[0], tri.clip[1], tri.clip[2], np);
    float sum = e.x + e.y + e.z;
    vec3 b = e / sum;
    vec3 g_b = vec3(0.0);
    vec3 g_z = vec3(0.0);  // the depth attribute's gradient, per corner
    for (int k = 0; k < 3; ++k) {
        for (uint ch = first_interpolated(); ch < CHANNELS; ++ch) {
            if (DEPTH != 0u && ch == CHANNELS - 1u) {
                g_z[k] = b[k] * g_colour[ch];
            } else {
                add_attribute_term(attribute_index(view, tri.v[k], ch), b[k] * g_colour[ch]);
            }
            g_b[k] += g_colour[ch] * attributes[attribute_index(view, tri.v[k], ch)];
        }
    }
    // b = e / sum(e): dL/de_k = (dL/db_k - dot(b, dL/db)) / sum(e).
    vec3 g_e = (g_b - dot(b, g_b)) / sum;
    vec3 g_clip[3] = vec3[3](vec3(0.0), vec3(0.0), vec3(0.0));
    edge_function_backward(tri.clip[1], tri.clip[2], np, g_e.x, g_clip[1], g_clip[2]);
    edge_function_backward(tri.clip[2], tri.clip[0], np, g_e.y, g_clip[2], g_clip[0]);
    edge_function_backward(tri.clip[0], tri.clip[1], np, g_e.z, g_clip[0], g_clip[1]);
    for (int k = 0; k < 3; ++k) add_clip_gradient(vd, view, tri.v[k], g_clip[k], g_z[k]);
}

void main() {
    uint count = work_count[0];
    vec2 bounds = gradient_bounds();
    uint camera_bits = magnitude_bits(bounds.x);
    uint attribute_bits = magnitude_bits(bounds.y);
    camera_shift = listed_shift(camera_bits, TERMS_PER_LISTED, count);
    attribute_shift = listed_shift(attribute_bits, TERMS_PER_LISTED, count);
    if (gl_GlobalInvocationID.x == 0u) {
        work_count[CAMERA_MAX] = camera_bits;
        work_count[ATTRIBUTE_MAX] = attribute_bits;
    }
    uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
    uint done = 0u;
    for (uint i = gl_GlobalInvocationID.x; i < count; i += stride) {
        handle_pixel(work[i]);
        ++done;
    }
    // A driver that ended the loop early (lavapipe's loop limit) is reported, not trusted.
    uint expected = grid_items(gl_GlobalInvocationID.x, stride, count);
    if (done < expected) atomicAdd(work_count[UNFINISHED], expected - done);
    uint camera_seen = subgroupMax(largest_camera);
    uint attribute_seen = subgroupMax(largest_attribute);
    if (subgroupElect()) {
        if (camera_seen > 0u) atomicMax(work_count[CAMERA_SEEN], camera_seen);
        if (attribute_seen > 0u) atomicMax(work_count[ATTRIBUTE_SEEN], attribute_seen);
    }
}

#version 460
// Backward of antialias.comp over the work list (pixels off the list have no pair and
// nothing interpolated): dL/dA per pixel (loss_gradient) pushed to the camera-space
// vertex positions of every view (grad_camera_fixed[view][vertex], int64 fixed point, so
// the sums do not depend on the order of the adds) through
//   - the silhouette crossings: each pair is handled by its left / upper pixel, and
//     d alpha / d(edge function) chains to the edge's two clip-space vertices;
//   - with attributes, the interpolation: dL/dc per pixel (own term plus the pair terms
//     that moved colour into or out of it) to the attributes (grad_attributes) and, via
//     the exact barycentrics, to the triangle's three clip-space vertices.
// The pairs are the forward's records (pairs_x, pairs_y), so no pass here walks.
// It runs twice: stage 0 only finds the largest term of each sum kind (atomicMax into
// work_count[CAMERA_MAX], [ATTRIBUTE_MAX]), stage 1 adds every term at the scale that
// implies (include/fixed_point.glsl); fixed_resolve.comp turns the sums into floats.
#include "diff_pass.glsl"

layout(local_size_x = 64) in;

// Stage 0: the largest term magnitudes this invocation has seen (magnitude_bits), merged
// into work_count once per subgroup at the end rather than by one atomicMax per term, all
// on one word.
uint largest_camera = 0u;
uint largest_attribute = 0u;

// Adds one term of a fixed-point sum, or (stage 0) records its magnitude.
void add_camera_term(uint at, float g, int shift) {
    if (pc.stage == 0u) largest_camera = max(largest_camera, magnitude_bits(g));
    else if (g != 0.0) atomicAdd(grad_camera_fixed[at], to_fixed(g, shift));
}

void add_attribute_term(uint at, float g, int shift) {
    if (pc.stage == 0u) largest_attribute = max(largest_attribute, magnitude_bits(g));
    else if (g != 0.0) atomicAdd(grad_attributes_fixed[at], to_fixed(g, shift));
}

// The scales of stage 1's sums (read once per invocation in main).
int camera_shift = 0;
int attribute_shift = 0;

// d clip / d camera is (sx, sy, ox, oy): x_clip = sx x + ox z, y_clip = sy y + oy z, w = z.
void add_clip_gradient(ViewData vd, uint view, uint v, vec3 g_clip) {
    vec2 s = clip_scale(vd);
    vec2 o = clip_shift(vd);
    vec3 g = vec3(s.x * g_clip.x, s.y * g_clip.y, o.x * g_clip.x + o.y * g_clip.y + g_clip.z);
    uint at = 3u * (view * pc.vertex_count + v);
    if (pc.stage == 1u) touched[v / VERTEX_BLOCK] = 1u;
    add_camera_term(at, g.x, camera_shift);
    add_camera_term(at + 1u, g.y, camera_shift);
    add_camera_term(at + 2u, g.z, camera_shift);
}

void crossing_backward(ViewData vd, uint view, Pair pair) {
    if (pair.clamped) return;
    ivec2 affected = pair.affects_g ? pair.g : pair.f;
    vec4 ga = loss_gradient(pixel_index(affected, view), view);
    vec4 cf = colour_at(vd, view, pair.f, id_at(pair.f, view));
    vec4 cg = colour_at(vd, view, pair.g, id_at(pair.g, view));
    float g_alpha = dot(ga, blended(cf - cg));
    if (g_alpha == 0.0) return;
    Crossing c = pair.crossing;
    float d = c.ef - c.eb;
    float g_ef = g_alpha * -c.eb / (d * d);
    float g_eb = g_alpha * c.ef / (d * d);
    Triangle tri = c.tri;
    int i = (c.edge + 1) % 3;
    int j = (c.edge + 2) % 3;
    vec3 gi = vec3(0.0);
    vec3 gj = vec3(0.0);
    vec2 pf = pixel_ndc(pair.f, vd);
    vec2 pb = pixel_ndc(pair.g, vd);
    edge_function_backward(tri.clip[i], tri.clip[j], pf, g_ef, gi, gj);
    edge_function_backward(tri.clip[i], tri.clip[j], pb, g_eb, gi, gj);
    add_clip_gradient(vd, view, tri.v[i], gi);
    add_clip_gradient(vd, view, tri.v[j], gj);
}

void handle_pixel(uint index) {
    uint view = view_of(index);
    ivec2 size = ivec2(pc.width, pc.height);
    ivec2 p = pixel_of(index);
    const ivec2 steps[4] = STEPS;
    uint id = ids[index];
    bool interpolated = pc.channels > 0u && id != 0u;
    bool any_pair = false;
    for (int s = 0; s < 4; ++s) {
        ivec2 q = clamp(p + steps[s], ivec2(0), size - 1);
        any_pair = any_pair || pair_matters(id, id_at(q, view));
    }
    ViewData vd = views[view];
    vec4 g_colour = interpolated ? loss_gradient(index, view) : vec4(0.0);
    for (int s = 0; s < 4 && any_pair; ++s) {
        ivec2 q = p + steps[s];
        if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, size))) continue;
        if (!pair_matters(id_at(p, view), id_at(q, view))) continue;
        bool forward = s < 2;
        if (!forward && !interpolated) continue;
        Pair pair = pair_at(vd, view, p, s);
        if (!pair.valid) continue;
        if (forward) crossing_backward(vd, view, pair);
        if (interpolated) {
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
    for (int k = 0; k < 3; ++k) {
        for (uint ch = 0u; ch < pc.channels; ++ch) {
            add_attribute_term(attribute_index(view, tri.v[k], ch), b[k] * g_colour[ch], attribute_shift);
            g_b[k] += g_colour[ch] * attributes[attribute_index(view, tri.v[k], ch)];
        }
    }
    // b = e / sum(e): dL/de_k = (dL/db_k - dot(b, dL/db)) / sum(e).
    vec3 g_e = (g_b - dot(b, g_b)) / sum;
    vec3 g_clip[3] = vec3[3](vec3(0.0), vec3(0.0), vec3(0.0));
    edge_function_backward(tri.clip[1], tri.clip[2], np, g_e.x, g_clip[1], g_clip[2]);
    edge_function_backward(tri.clip[2], tri.clip[0], np, g_e.y, g_clip[2], g_clip[0]);
    edge_function_backward(tri.clip[0], tri.clip[1], np, g_e.z, g_clip[0], g_clip[1]);
    for (int k = 0; k < 3; ++k) add_clip_gradient(vd, view, tri.v[k], g_clip[k]);
}

void main() {
    uint count = work_count[0];
    if (pc.stage == 1u) {
        camera_shift = listed_shift(work_count[CAMERA_MAX], TERMS_PER_LISTED, count);
        attribute_shift = listed_shift(work_count[ATTRIBUTE_MAX], TERMS_PER_LISTED, count);
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
    if (pc.stage == 0u) {
        uint camera_bits = subgroupMax(largest_camera);
        uint attribute_bits = subgroupMax(largest_attribute);
        if (subgroupElect()) {
            if (camera_bits > 0u) atomicMax(work_count[CAMERA_MAX], camera_bits);
            if (attribute_bits > 0u) atomicMax(work_count[ATTRIBUTE_MAX], attribute_bits);
        }
    }
}

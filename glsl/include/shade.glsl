// The image that is compared, before antialiasing: coverage (1 on the object, 0 on the
// background) when CHANNELS == 0, else per-vertex attributes (CHANNELS of them,
// at most 4; each view has its own, [view][vertex][channel]) interpolated with the exact
// perspective-correct barycentrics. Background 0.
// Against a mask with depth (COVERAGE), channel 0 is the coverage: its attribute is 1 at
// every vertex, so it is 1 wherever a triangle is, not interpolated, and it has no
// interpolation gradient (its barycentric weights sum to 1).
// Needs diff.glsl, an `attributes[]` buffer, `CHANNELS`, `COVERAGE` and `pc.vertex_count`.

uint attribute_index(uint view, uint v, uint ch) {
    return (view * pc.vertex_count + v) * CHANNELS + ch;
}

// The first interpolated channel.
uint first_interpolated() { return COVERAGE != 0u ? 1u : 0u; }

vec4 shade_triangle(uint view, Triangle tri, vec3 b) {
    vec4 c = vec4(0.0);
    if (COVERAGE != 0u) c[0] = 1.0;
    for (uint ch = first_interpolated(); ch < CHANNELS; ++ch) {
        c[ch] = b.x * attributes[attribute_index(view, tri.v.x, ch)]
              + b.y * attributes[attribute_index(view, tri.v.y, ch)]
              + b.z * attributes[attribute_index(view, tri.v.z, ch)];
    }
    return c;
}

// The colour of triangle id - 1 (id != 0, CHANNELS > 0) at `pixel`, with the triangle, the
// pixel's NDC and its edge functions kept for whoever needs them too.
vec4 shaded_colour_at(ViewData vd, uint view, ivec2 pixel, uint id, out Triangle tri, out vec2 np,
                      out vec3 e) {
    tri = load_triangle(vd, id - 1u);
    np = pixel_ndc(pixel, vd);
    e = edge_functions(tri.clip[0], tri.clip[1], tri.clip[2], np);
    return shade_triangle(view, tri, e / (e.x + e.y + e.z));
}

vec4 colour_at(ViewData vd, uint view, ivec2 pixel, uint id) {
    if (id == 0u) return vec4(0.0);
    if (CHANNELS == 0u) return vec4(1.0, 0.0, 0.0, 0.0);
    Triangle tri;
    vec2 np;
    vec3 e;
    return shaded_colour_at(vd, view, pixel, id, tri, np, e);
}

uint image_channels() { return max(CHANNELS, 1u); }

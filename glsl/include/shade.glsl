// The image that is compared, before antialiasing: coverage (1 on the object, 0 on the
// background) when pc.channels == 0, else per-vertex attributes (pc.channels of them,
// at most 4) interpolated with the exact perspective-correct barycentrics. Background 0.
// Needs diff.glsl, an `attributes[]` buffer and `pc.channels`.

vec4 shade_triangle(Triangle tri, vec3 b) {
    vec4 c = vec4(0.0);
    for (uint ch = 0u; ch < pc.channels; ++ch) {
        c[ch] = b.x * attributes[tri.v.x * pc.channels + ch]
              + b.y * attributes[tri.v.y * pc.channels + ch]
              + b.z * attributes[tri.v.z * pc.channels + ch];
    }
    return c;
}

vec4 colour_at(ViewData vd, ivec2 pixel, uint id) {
    if (id == 0u) return vec4(0.0);
    if (pc.channels == 0u) return vec4(1.0, 0.0, 0.0, 0.0);
    Triangle tri = load_triangle(vd, id - 1u);
    return shade_triangle(tri, barycentrics(tri.clip[0], tri.clip[1], tri.clip[2], pixel_ndc(pixel, vd)));
}

uint image_channels() { return max(pc.channels, 1u); }

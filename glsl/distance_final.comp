#version 460
// Signed distance in pixels to the observed mask's boundary: outside, the distance to the
// nearest mask pixel centre minus 1/2; inside, minus (the distance to the nearest
// background pixel centre minus 1/2). With no pixel of the other kind, +-(width + height).
#include "distance.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Observed { float observed[]; };  // [view][y][x]
layout(set = 0, binding = 1, std430) readonly buffer Seeds { uint seeds[]; };         // [view][set][y][x]
layout(set = 0, binding = 2, std430) writeonly buffer Distance { float distance_field[]; };  // [view][y][x]

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= int(pc.width) || p.y >= int(pc.height)) return;
    uint view = gl_GlobalInvocationID.z;
    bool inside = observed[plane_index(p, view)] > 0.5;
    uint s = seeds[plane_index(p, 2u * view + (inside ? 1u : 0u))];
    float d = s == NO_SEED ? float(pc.width + pc.height) : length(vec2(unpack_pixel(s) - p)) - 0.5;
    distance_field[plane_index(p, view)] = inside ? -d : d;
}

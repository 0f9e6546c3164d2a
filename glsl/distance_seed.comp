#version 460
// Jump flooding, initialisation: every pixel of the set's kind is its own seed.
#include "distance.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Observed { float observed[]; };  // [view][y][x]
layout(set = 0, binding = 1, std430) writeonly buffer Seeds { uint seeds[]; };       // [view][set][y][x]

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= int(pc.width) || p.y >= int(pc.height)) return;
    uint plane = gl_GlobalInvocationID.z;  // 2 view + set
    bool inside = observed[plane_index(p, plane / 2u)] > 0.5;
    bool seed = (plane % 2u == 0u) == inside;
    seeds[plane_index(p, plane)] = seed ? pack_pixel(p) : NO_SEED;
}

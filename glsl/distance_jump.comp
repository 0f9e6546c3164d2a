#version 460
// Jump flooding, one pass of step pc.step: keep the nearest seed among the 3 x 3
// neighbours at that step.
#include "distance.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Source { uint source[]; };
layout(set = 0, binding = 1, std430) writeonly buffer Target { uint target[]; };

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= int(pc.width) || p.y >= int(pc.height)) return;
    uint plane = gl_GlobalInvocationID.z;
    uint best = source[plane_index(p, plane)];
    float best_d2 = best == NO_SEED ? 3.0e38 : dot(vec2(unpack_pixel(best) - p), vec2(unpack_pixel(best) - p));
    for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
            ivec2 q = p + pc.step * ivec2(dx, dy);
            if (q.x < 0 || q.y < 0 || q.x >= int(pc.width) || q.y >= int(pc.height)) continue;
            uint s = source[plane_index(q, plane)];
            if (s == NO_SEED) continue;
            vec2 d = vec2(unpack_pixel(s) - p);
            float d2 = dot(d, d);
            if (d2 < best_d2) { best_d2 = d2; best = s; }
        }
    }
    target[plane_index(p, plane)] = best;
}

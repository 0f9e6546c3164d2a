#version 460
// G-buffer pass, vertex stage: non-indexed draw with vertex pulling. Invocation 3 t + k is
// corner k of triangle t of this draw; it fetches all three corners so that the fragment
// stage receives the triangle's clip-space vertices (flat) and recomputes exact
// perspective-correct barycentrics from them.
#include "camera.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };
layout(set = 0, binding = 1, std430) readonly buffer Triangles { uint triangles[]; };

layout(location = 0) flat out uint out_id;     // triangle id + 1
layout(location = 1) flat out vec3 out_clip0;  // clip x, y, w of corner 0
layout(location = 2) flat out vec3 out_clip1;
layout(location = 3) flat out vec3 out_clip2;

vec4 corner_clip(uint triangle, uint corner) {
    uint v = triangles[3u * triangle + corner];
    vec3 p = vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]);
    return camera_to_clip(to_camera(p));
}

void main() {
    uint triangle = uint(gl_VertexIndex) / 3u;
    uint corner = uint(gl_VertexIndex) % 3u;
    vec4 c0 = corner_clip(triangle, 0u);
    vec4 c1 = corner_clip(triangle, 1u);
    vec4 c2 = corner_clip(triangle, 2u);
    gl_Position = corner == 0u ? c0 : (corner == 1u ? c1 : c2);
    out_id = view.first_triangle + triangle + 1u;
    out_clip0 = c0.xyw;
    out_clip1 = c1.xyw;
    out_clip2 = c2.xyw;
}

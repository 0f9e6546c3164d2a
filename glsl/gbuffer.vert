#version 460
// G-buffer pass, vertex stage: a non-indexed draw; invocation 3 t + k is corner k of
// triangle t of this draw. It pulls its vertex from the positions buffer, transforms it
// with the view's pose from the views buffer (which compute passes may update) and emits
// the triangle id (flat, exact as an integer) and the corner's unit barycentric vector,
// which the rasterizer interpolates perspective-correctly.
#include "views.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };
layout(set = 0, binding = 1, std430) readonly buffer Views { ViewData views[]; };
layout(set = 0, binding = 2, std430) readonly buffer Triangles { uint triangles[]; };  // this draw's

layout(push_constant, std430) uniform Constants {
    uint view;
    uint first_triangle;
} pc;

layout(location = 0) flat out uint out_id;
layout(location = 1) out vec2 out_bary;

void main() {
    ViewData vd = views[pc.view];
    uint corner = uint(gl_VertexIndex) % 3u;
    uint v = triangles[gl_VertexIndex];
    vec3 p = vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]);
    gl_Position = view_camera_to_clip(vd, (vd.object_to_camera * vec4(p, 1.0)).xyz);
    out_id = pc.first_triangle + uint(gl_VertexIndex) / 3u + 1u;
    out_bary = vec2(corner == 0u ? 1.0 : 0.0, corner == 1u ? 1.0 : 0.0);
}

#version 460
// G-buffer pass writing triangle ids only, vertex stage: an ordinary indexed draw (each
// vertex transformed once, as in the plain render), positions pulled from the positions
// buffer and the view's pose from the views buffer (which compute passes may update). The
// fragment stage takes the triangle id from gl_PrimitiveID.
#include "views.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };
layout(set = 0, binding = 1, std430) readonly buffer Views { ViewData views[]; };

layout(push_constant, std430) uniform Constants {
    uint view;
} pc;

void main() {
    ViewData vd = views[pc.view];
    uint v = uint(gl_VertexIndex);
    vec3 p = vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]);
    gl_Position = view_camera_to_clip(vd, (vd.object_to_camera * vec4(p, 1.0)).xyz);
}

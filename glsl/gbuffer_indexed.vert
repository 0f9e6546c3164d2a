#version 460
// G-buffer pass writing triangle ids only, vertex stage: one indexed draw in the order of
// raster::provoking_order, where entry t is the provoking (first) vertex of triangle t, so
// the flat id below is triangle t's id + 1 (without gl_PrimitiveID, which CPU drivers
// serve slowly). Each entry pulls its mesh vertex from the positions buffer and the view's
// pose from the views buffer (which compute passes may update).
#include "views.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };
layout(set = 0, binding = 1, std430) readonly buffer Views { ViewData views[]; };
layout(set = 0, binding = 2, std430) readonly buffer Sources { uint sources[]; };

layout(push_constant, std430) uniform Constants {
    uint view;
} pc;

layout(location = 0) flat out uint out_id;

void main() {
    ViewData vd = views[pc.view];
    uint v = sources[gl_VertexIndex];
    vec3 p = vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]);
    gl_Position = view_camera_to_clip(vd, (vd.object_to_camera * vec4(p, 1.0)).xyz);
    out_id = uint(gl_VertexIndex) + 1u;  // the id + 1 of the triangle this entry provokes
}

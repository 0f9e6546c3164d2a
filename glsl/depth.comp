#version 460
// Camera-space depth as the last per-vertex attribute of every view (see `depth_compared`
// in include/loss.glsl): attributes[view][v][channels - 1] = z of the vertex in the view's
// camera frame, and with pc.coverage attributes[view][v][0] = 1 (the mask channel). Its
// gradient needs no pass: antialias_backward.comp adds dL/dz straight to the vertex's
// camera-space z. One vertex of one view per invocation.
// Grid: x over vertices, z over views.
#include "views.glsl"

layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };
layout(set = 0, binding = 1, std430) readonly buffer Views { ViewData views[]; };
layout(set = 0, binding = 2, std430) buffer Attributes { float attributes[]; };  // [view][vertex][channel]

layout(push_constant, std430) uniform Constants {
    uint vertex_count;
    uint channels;
    uint coverage;
} pc;

void main() {
    uint v = gl_GlobalInvocationID.x;
    uint view = gl_GlobalInvocationID.z;
    if (v >= pc.vertex_count) return;
    uint slot = view * pc.vertex_count + v;
    vec3 p = vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]);
    attributes[slot * pc.channels + pc.channels - 1u] = (views[view].object_to_camera * vec4(p, 1.0)).z;
    if (pc.coverage != 0u) attributes[slot * pc.channels] = 1.0;
}

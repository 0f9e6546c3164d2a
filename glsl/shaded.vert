#version 460
// Plain colour render, vertex stage: an ordinary indexed draw (the index buffer is bound
// as such), positions pulled from the same storage buffer the G-buffer pass reads.
#include "camera.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };

layout(location = 0) out vec3 out_camera;  // camera-space position

void main() {
    uint v = uint(gl_VertexIndex);
    vec3 c = to_camera(vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]));
    out_camera = c;
    gl_Position = camera_to_clip(c);
}

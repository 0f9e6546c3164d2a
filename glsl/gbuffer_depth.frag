#version 460
// G-buffer fragment stage with the camera-space depth output.
#define WRITE_DEPTH
#include "gbuffer_frag.glsl"

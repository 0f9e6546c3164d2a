#version 460
// G-buffer fragment stage without a depth output (see include/gbuffer_frag.glsl).
#include "gbuffer_frag.glsl"

#version 460
// G-buffer fragment stage writing triangle ids only (see include/gbuffer_frag.glsl).
#define IDS_ONLY
#include "gbuffer_frag.glsl"

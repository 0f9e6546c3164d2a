// G-buffer pass, fragment stage (included by gbuffer.frag and gbuffer_depth.frag): writes
// triangle id + 1 and the perspective-correct barycentrics (weights of corners 0 and 1;
// corner 2 has 1 - u - v) of the pixel centre, computed from the clip-space vertices with
// 2D homogeneous edge functions. They are exact for the unsnapped triangle, so the
// backward pass differentiates the very function computed here. With WRITE_DEPTH it also
// writes camera-space z interpolated with the same weights.
#include "camera.glsl"

layout(location = 0) flat in uint in_id;
layout(location = 1) flat in vec3 in_clip0;
layout(location = 2) flat in vec3 in_clip1;
layout(location = 3) flat in vec3 in_clip2;

layout(location = 0) out uint out_id;
layout(location = 1) out vec2 out_bary;
#ifdef WRITE_DEPTH
layout(location = 2) out float out_depth;
#endif

float cross2(vec2 a, vec2 b) { return a.x * b.y - a.y * b.x; }

void main() {
    vec2 p = fragment_ndc(gl_FragCoord);
    vec2 a0 = in_clip0.xy - p * in_clip0.z;
    vec2 a1 = in_clip1.xy - p * in_clip1.z;
    vec2 a2 = in_clip2.xy - p * in_clip2.z;
    vec3 b = vec3(cross2(a1, a2), cross2(a2, a0), cross2(a0, a1));
    b /= b.x + b.y + b.z;
    out_bary = b.xy;
    out_id = in_id;
#ifdef WRITE_DEPTH
    out_depth = dot(b, vec3(in_clip0.z, in_clip1.z, in_clip2.z));
#endif
}

#version 460
// CPD E-step, pass 2: per moving point m, P1_m = sum_n P_mn and PX_m = sum_n P_mn x_n
// (written as vec4: xyz = PX_m, w = P1_m).
#include "cpd.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Moving { vec4 moving[]; };
layout(set = 0, binding = 1, std430) readonly buffer Target { vec4 target[]; };
layout(set = 0, binding = 2, std430) readonly buffer LogDen { float log_den[]; };
layout(set = 0, binding = 3, std430) writeonly buffer Sums { vec4 sums[]; };

void main() {
    uint m = gl_GlobalInvocationID.x;
    if (m >= pc.m) return;
    vec3 t = moving[m].xyz;
    vec4 acc = vec4(0.0);
    for (uint n = 0u; n < pc.n; ++n) {
        vec3 x = target[n].xyz;
        vec3 d = x - t;
        float p = exp(-dot(d, d) * pc.inv_two_sigma2 - log_den[n]);
        acc += vec4(p * x, p);
    }
    sums[m] = acc;
}

#version 460
// CPD E-step, pass 1: per target point n, log(sum_m exp(-|x_n - t_m|^2 / (2 s2)) + c),
// accumulated as a running log-sum-exp.
#include "cpd.glsl"

layout(set = 0, binding = 0, std430) readonly buffer Moving { vec4 moving[]; };  // t_m
layout(set = 0, binding = 1, std430) readonly buffer Target { vec4 target[]; };  // x_n
layout(set = 0, binding = 2, std430) writeonly buffer LogDen { float log_den[]; };

void main() {
    uint n = gl_GlobalInvocationID.x;
    if (n >= pc.n) return;
    vec3 x = target[n].xyz;
    float top = pc.log_c;  // running maximum exponent
    float sum = 1.0;       // sum of exp(exponent - top)
    for (uint m = 0u; m < pc.m; ++m) {
        vec3 d = x - moving[m].xyz;
        float e = -dot(d, d) * pc.inv_two_sigma2;
        if (e > top) {
            sum = sum * exp(top - e) + 1.0;
            top = e;
        } else {
            sum += exp(e - top);
        }
    }
    log_den[n] = top + log(sum);
}

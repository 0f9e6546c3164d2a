#version 460
// The loss of each view from the sums of antialias.comp: stats[4 view + 3].
layout(local_size_x = 1) in;

layout(set = 0, binding = 0, std430) buffer Stats { float stats[]; };

layout(push_constant, std430) uniform Constants { uint loss; } pc;

void main() {
    uint view = gl_GlobalInvocationID.x;
    float value = stats[4u * view];
    if (pc.loss == 1u) {
        float union_ = stats[4u * view + 2u];
        value = union_ > 0.0 ? 1.0 - stats[4u * view + 1u] / union_ : 0.0;
    }
    stats[4u * view + 3u] = value;
}

#ifndef LOSS_CODES_GLSL
#define LOSS_CODES_GLSL
// The losses' codes (`Loss::code` in src/loss/mod.rs, which a test checks against these):
// mean squared error, soft IoU, signed-distance-weighted coverage.
const uint LOSS_MSE = 0u;
const uint LOSS_IOU = 1u;
const uint LOSS_DISTANCE = 2u;

// The loss of a view from its sums (loss sum, intersection, union).
float loss_of(uint loss, vec3 sums) {
    if (loss == LOSS_IOU) return sums.z > 0.0 ? 1.0 - sums.y / sums.z : 0.0;
    return sums.x;
}

#endif  // LOSS_CODES_GLSL

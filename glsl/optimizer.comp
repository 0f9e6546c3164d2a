#version 460
// One optimiser step on the device (a single invocation): SGD with momentum and
// exponential learning-rate decay (or Adam) for the latent code every iteration, and
// for the pose every pc.pose_every iterations; records the loss. The pose lives in the
// views buffer (object_to_camera), updated as t -= step, R = exp(-[step]x) R (the
// rotation increment is applied on the left, as the pose gradient is defined).
//
// State layout (floats): pc's offsets (register::StateLayout).
#include "views.glsl"
#include "rotation.glsl"

layout(local_size_x = 1) in;

layout(set = 0, binding = 0, std430) buffer State { float state[]; };
layout(set = 0, binding = 1, std430) readonly buffer GradLatent { float grad_latent[]; };
layout(set = 0, binding = 2, std430) readonly buffer GradPose { float grad_pose[]; };
layout(set = 0, binding = 3, std430) readonly buffer Stats { float stats[]; };
layout(set = 0, binding = 4, std430) buffer Views { ViewData views[]; };

layout(push_constant, std430) uniform Constants {
    uint dims;
    uint pose_every;     // 0: pose fixed
    uint optimize_z;
    uint adam;
    float momentum;
    float decay;
    float latent_step;   // length of the first latent step (unit-variance code units)
    float translation_step;  // metres
    float rotation_step;     // radians
    uint max_iterations;
    uint pose_only;      // 1: the latent code stays where it is (pose alignment)
    float code_prior;    // weight of the code prior (RegisterParams::code_prior; objective.glsl)
    // The state's layout (register::StateLayout): float offsets.
    uint latent_at;
    uint velocity_at;
    uint second_moment_at;
    uint pose_velocity_at;
    uint losses_at;
    uint codes_at;
    uint accepted_loss_at;
    uint halvings_at;
    uint r0_at;
    uint t0_at;
    uint pose_x_at;
    uint accepted_at;
    uint accepted_grad_at;
    uint h_at;
    uint scratch_at;
    uint prior_at;
    uint bound_at;
    uint gravity_at;
    uint state_len;
} pc;

#include "objective.glsl"

// Offsets into `state`.
const uint ITERATION = 0u;
const uint LR_LATENT = 1u;
const uint LR_TRANSLATION = 2u;
const uint LR_ROTATION = 3u;
const uint POSE_STEPS = 4u;

void main() {
    uint t = uint(state[ITERATION]);
    // The objective: the images' loss, the code prior and gravity (objective.glsl).
    mat3 rotation = mat3(views[0].object_to_camera);
    float loss = stats[3] + prior_term() + gravity_term(rotation);
    if (t < pc.max_iterations) state[pc.losses_at + t] = loss;
    float decay = pow(pc.decay, float(t));
    bool shape = pc.pose_only == 0u;

    // Latent code: the gradients (the prior's at the code before this step) go into the
    // moments first, then every coordinate steps. The first gradient's norm sets the
    // step's scale.
    float norm = 0.0;
    for (uint j = 0u; j < pc.dims; ++j) {
        float g = grad_latent[j] + prior_gradient(j);
        norm += g * g;
        if (!shape) continue;
        state[pc.velocity_at + j] = pc.momentum * state[pc.velocity_at + j] + g;
        if (pc.adam != 0u) state[pc.second_moment_at + j] = 0.999 * state[pc.second_moment_at + j] + 0.001 * g * g;
    }
    norm = sqrt(norm);
    if (t == 0u) state[LR_LATENT] = norm > 0.0 ? pc.latent_step / norm : 0.0;
    for (uint j = 0u; j < pc.dims && shape; ++j) {
        float v = state[pc.velocity_at + j];
        float step = state[LR_LATENT] * decay * v;
        if (pc.adam != 0u) {
            float m2 = state[pc.second_moment_at + j];
            float m1 = v * (1.0 - pc.momentum);
            float bias1 = 1.0 - pow(pc.momentum, float(t + 1u));
            float bias2 = 1.0 - pow(0.999, float(t + 1u));
            step = pc.latent_step * decay * (m1 / bias1) / (sqrt(m2 / bias2) + 1e-12);
        }
        // Projected step: codes stay within their bound, CODE_BOUND standard deviations of
        // the training set (beyond it the space extrapolates and a stray gradient could
        // run away).
        float bound = state[pc.bound_at + j];
        state[pc.latent_at + j] = clamp(state[pc.latent_at + j] - step, -bound, bound);
    }
    for (uint j = 0u; j < pc.dims; ++j) {
        if (t < pc.max_iterations) state[pc.codes_at + t * pc.dims + j] = state[pc.latent_at + j];
    }

    // Pose, once every pc.pose_every iterations (every iteration while aligned alone).
    bool pose_step = !shape || (t + 1u) % pc.pose_every == 0u;
    if (pc.pose_every > 0u && pose_step) {
        vec3 gt = vec3(grad_pose[0], grad_pose[1], pc.optimize_z != 0u ? grad_pose[2] : 0.0);
        vec3 gr = vec3(grad_pose[3], grad_pose[4], grad_pose[5]) + gravity_gradient(rotation);
        uint k = uint(state[POSE_STEPS]);
        if (k == 0u) {
            state[LR_TRANSLATION] = length(gt) > 0.0 ? pc.translation_step / length(gt) : 0.0;
            state[LR_ROTATION] = length(gr) > 0.0 ? pc.rotation_step / length(gr) : 0.0;
        }
        float pose_decay = pow(pc.decay, float(k));
        vec3 vt = pc.momentum * vec3(state[pc.pose_velocity_at], state[pc.pose_velocity_at + 1u], state[pc.pose_velocity_at + 2u]) + gt;
        vec3 vr = pc.momentum * vec3(state[pc.pose_velocity_at + 3u], state[pc.pose_velocity_at + 4u], state[pc.pose_velocity_at + 5u]) + gr;
        for (uint c = 0u; c < 3u; ++c) {
            state[pc.pose_velocity_at + c] = vt[c];
            state[pc.pose_velocity_at + 3u + c] = vr[c];
        }
        // Steps are bounded in metres and radians: a first gradient near zero (a start at
        // the optimum) sets a huge rate, and momentum must not then fling the object away.
        vec3 dt = state[LR_TRANSLATION] * pose_decay * vt;
        vec3 dr = state[LR_ROTATION] * pose_decay * vr;
        if (length(dt) > pc.translation_step) dt *= pc.translation_step / length(dt);
        if (length(dr) > pc.rotation_step) dr *= pc.rotation_step / length(dr);
        mat4 m = views[0].object_to_camera;
        mat3 r = rodrigues(-dr) * mat3(m);
        vec3 translation = m[3].xyz - dt;
        views[0].object_to_camera = mat4(vec4(r[0], 0.0), vec4(r[1], 0.0), vec4(r[2], 0.0), vec4(translation, 1.0));
        state[POSE_STEPS] = float(k + 1u);
    }
    state[ITERATION] = float(t + 1u);
}

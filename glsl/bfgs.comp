#version 460
// One quasi-Newton (BFGS) step on the device (a single invocation), over the latent code
// and, with pose optimisation, the pose, as x = (z, t - t0, w) with the pose
// t = t0 + (x_t), R = exp([w]x) R0 around the initial pose (R0, t0).
//
// Each iteration has evaluated the loss and gradient at the current point x. If the loss
// decreased enough (Armijo) the point is accepted: the inverse-Hessian estimate H takes
// the BFGS update from the last accepted point, and the next point is the minimum of the
// quadratic model on the face of the bounds (below), its length capped. Otherwise the step
// back from the last accepted point is halved. The latent code and the pose are thereby
// scaled against each other by the curvature the iterations observe instead of by
// hand-set learning rates; H starts as a diagonal that makes the first step of each part
// the configured length.
//
// Each code coordinate i is bounded to +-bound(i) (register::CodeCoordinates: CODE_BOUND
// training RMS deformations) by an active set, in
// the manner of projected quasi-Newton methods (Bertsekas 1982; L-BFGS-B's subspace
// step): a code coordinate on its bound whose gradient pushes outward is held (active),
// and the free coordinates take the model's minimum with the active ones fixed,
// d_F = -(B_FF)^-1 g_F, where B = H^-1: with u = H g_F (g zero on the active set),
// d = -u + H[:, A] H_AA^-1 u_A, which is zero on A. The trial point is projected onto the
// box. (Clamping x - H g instead, as before, moved the free coordinates along a direction
// computed as if the clamped ones moved too.)
//
// State layout (floats): pc's offsets (register::StateLayout); this shader uses the
// quasi-Newton region.
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
    uint adam;           // unused
    float momentum;      // unused
    float decay;         // unused
    float latent_step;   // length of the first latent step (code units)
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

const uint ITERATION = 0u;
const uint MAX_N = 64u;
uint n() { return pc.dims + 6u; }
float bound(uint i) { return state[pc.bound_at + i]; }

float x_at(uint i) { return i < pc.dims ? state[pc.latent_at + i] : state[pc.pose_x_at + i - pc.dims]; }
void set_x(uint i, float v) {
    if (i < pc.dims) state[pc.latent_at + i] = v; else state[pc.pose_x_at + i - pc.dims] = v;
}
float h(uint i, uint j) { return state[pc.h_at + i * n() + j]; }
void set_h(uint i, uint j, float v) { state[pc.h_at + i * n() + j] = v; }

// The left Jacobian of the rotation exponential: exp([w + d]x) ~ exp([J d]x) exp([w]x).
mat3 left_jacobian(vec3 w) {
    float angle = length(w);
    if (angle < 1e-4) return mat3(1.0) + 0.5 * skew(w);
    mat3 k = skew(w);
    float a2 = angle * angle;
    return mat3(1.0) + (1.0 - cos(angle)) / a2 * k + (angle - sin(angle)) / (a2 * angle) * k * k;
}

// Which part of x coordinate i is in: 0 the code, 1 the translation, 2 the rotation.
uint part_of(uint i) { return i < pc.dims ? 0u : (i < pc.dims + 3u ? 1u : 2u); }

// Whether coordinate i moves: the code unless the pose is aligned alone, the pose when it
// is optimised (z only when asked for).
bool moves(uint i) {
    if (i < pc.dims) return pc.pose_only == 0u;
    if (pc.pose_every == 0u) return false;
    return i != pc.dims + 2u || pc.optimize_z != 0u;
}

// Whether code coordinate i is held on its bound: there, with the gradient pushing out.
bool held(uint i, float gi) {
    if (i >= pc.dims) return false;
    float x = x_at(i);
    return (x >= bound(i) && gi < 0.0) || (x <= -bound(i) && gi > 0.0);
}

float l(uint i, uint j) { return state[pc.scratch_at + i * n() + j]; }
void set_l(uint i, uint j, float v) { state[pc.scratch_at + i * n() + j] = v; }

// The step direction at the accepted point x with gradient g (see the top): -H g where
// nothing is active, else the minimum of the quadratic model with the active coordinates
// held. Should H_AA not factor (rounding), the direction is -H g_F with d_A = 0.
void direction(float g[MAX_N], out float d[MAX_N]) {
    uint count = n();
    uint act[MAX_N];
    uint k = 0u;
    float gf[MAX_N];
    for (uint i = 0u; i < count; ++i) {
        bool on_bound = held(i, g[i]);
        gf[i] = on_bound ? 0.0 : g[i];
        if (on_bound) act[k++] = i;
    }
    float u[MAX_N];
    for (uint i = 0u; i < count; ++i) {
        u[i] = 0.0;
        for (uint j = 0u; j < count; ++j) u[i] += h(i, j) * gf[j];
        d[i] = -u[i];
    }
    if (k == 0u) return;
    // Cholesky H_AA = L L^T in the scratch region, then lambda = H_AA^-1 u_A.
    bool factored = true;
    for (uint a = 0u; a < k && factored; ++a) {
        for (uint b = 0u; b <= a; ++b) {
            float v = h(act[a], act[b]);
            for (uint c = 0u; c < b; ++c) v -= l(a, c) * l(b, c);
            if (a == b) {
                if (v <= 0.0) {
                    factored = false;
                    break;
                }
                set_l(a, a, sqrt(v));
            } else {
                set_l(a, b, v / l(b, b));
            }
        }
    }
    float lambda[MAX_N];
    if (factored) {
        for (uint a = 0u; a < k; ++a) {
            float v = u[act[a]];
            for (uint c = 0u; c < a; ++c) v -= l(a, c) * lambda[c];
            lambda[a] = v / l(a, a);
        }
        for (uint a = k; a-- > 0u;) {
            float v = lambda[a];
            for (uint c = a + 1u; c < k; ++c) v -= l(c, a) * lambda[c];
            lambda[a] = v / l(a, a);
        }
        for (uint i = 0u; i < count; ++i) {
            for (uint a = 0u; a < k; ++a) d[i] += h(i, act[a]) * lambda[a];
        }
    }
    for (uint a = 0u; a < k; ++a) d[act[a]] = 0.0;
}

void main() {
    uint t = uint(state[ITERATION]);
    uint count = n();
    // The objective: the images' loss, the code prior and gravity (objective.glsl), at
    // the point the images were rendered at.
    mat3 rotation = mat3(views[0].object_to_camera);
    float loss = stats[3] + prior_term() + gravity_term(rotation);
    if (t < pc.max_iterations) state[pc.losses_at + t] = loss;

    if (t == 0u) {
        mat4 m = views[0].object_to_camera;
        for (uint c = 0u; c < 3u; ++c) {
            for (uint r = 0u; r < 3u; ++r) state[pc.r0_at + 3u * c + r] = m[c][r];
            state[pc.t0_at + c] = m[3][c];
        }
        for (uint i = 0u; i < 6u; ++i) state[pc.pose_x_at + i] = 0.0;
        for (uint i = 0u; i < count * count; ++i) state[pc.h_at + i] = 0.0;
        state[pc.accepted_loss_at] = 3.0e38;
    }

    // The gradient at x, in x's coordinates (the renderer's rotation gradient is for a
    // left increment of the current rotation).
    float g[MAX_N];
    vec3 w = vec3(state[pc.pose_x_at + 3u], state[pc.pose_x_at + 4u], state[pc.pose_x_at + 5u]);
    vec3 gw = transpose(left_jacobian(w)) * (vec3(grad_pose[3], grad_pose[4], grad_pose[5]) + gravity_gradient(rotation));
    for (uint i = 0u; i < count; ++i) {
        float v = i < pc.dims ? grad_latent[i] + prior_gradient(i)
            : (i < pc.dims + 3u ? grad_pose[i - pc.dims] : gw[i - pc.dims - 3u]);
        g[i] = moves(i) ? v : 0.0;
    }

    // H starts as the diagonal that makes each part's first step the set length.
    float steps[3] = float[3](pc.latent_step, pc.translation_step, pc.rotation_step);
    if (t == 0u) {
        float parts[3] = float[3](0.0, 0.0, 0.0);
        for (uint i = 0u; i < count; ++i) parts[part_of(i)] += g[i] * g[i];
        for (uint i = 0u; i < count; ++i) {
            float norm = sqrt(parts[part_of(i)]);
            if (moves(i)) set_h(i, i, norm > 0.0 ? steps[part_of(i)] / norm : 0.0);
        }
    }

    float accepted_loss = state[pc.accepted_loss_at];
    float predicted = 0.0;
    for (uint i = 0u; i < count; ++i) {
        predicted += state[pc.accepted_grad_at + i] * (x_at(i) - state[pc.accepted_at + i]);
    }
    bool finite = !isnan(loss) && !isinf(loss);
    for (uint i = 0u; i < count; ++i) finite = finite && !isnan(g[i]) && !isinf(g[i]);
    // A non-finite loss or gradient is never accepted (the first point keeps a zero step).
    if (!finite) {
        for (uint i = 0u; i < count; ++i) g[i] = 0.0;
    }
    bool accept = t == 0u || (finite && loss <= accepted_loss + 1e-4 * predicted);
    if (accept) {
        // BFGS update of H from the step s and the gradient change y.
        float s[MAX_N];
        float y[MAX_N];
        float sy = 0.0;
        for (uint i = 0u; i < count; ++i) {
            s[i] = x_at(i) - state[pc.accepted_at + i];
            y[i] = g[i] - state[pc.accepted_grad_at + i];
            sy += s[i] * y[i];
        }
        if (t > 0u && sy > 1e-12) {
            float hy[MAX_N];
            float yhy = 0.0;
            for (uint i = 0u; i < count; ++i) {
                hy[i] = 0.0;
                for (uint j = 0u; j < count; ++j) hy[i] += h(i, j) * y[j];
                yhy += y[i] * hy[i];
            }
            // H' = H + (sy + yHy) ss^T / sy^2 - (Hy s^T + s y^T H) / sy
            for (uint i = 0u; i < count; ++i) {
                for (uint j = 0u; j < count; ++j) {
                    float v = h(i, j) + (sy + yhy) * s[i] * s[j] / (sy * sy)
                        - (hy[i] * s[j] + s[i] * hy[j]) / sy;
                    set_h(i, j, v);
                }
            }
        }
        for (uint i = 0u; i < count; ++i) {
            state[pc.accepted_at + i] = x_at(i);
            state[pc.accepted_grad_at + i] = g[i];
        }
        state[pc.accepted_loss_at] = loss;
        state[pc.halvings_at] = 0.0;

        // Next point: the model's minimum on the face, each part's step at most twice
        // its first length.
        float d[MAX_N];
        direction(g, d);
        float lengths[3] = float[3](0.0, 0.0, 0.0);
        for (uint i = 0u; i < count; ++i) lengths[part_of(i)] += d[i] * d[i];
        float scale = 1.0;
        for (uint p = 0u; p < 3u; ++p) {
            float cap = 2.0 * steps[p];
            if (lengths[p] > cap * cap) scale = min(scale, cap / sqrt(lengths[p]));
        }
        for (uint i = 0u; i < count; ++i) set_x(i, x_at(i) + scale * d[i]);
    } else {
        for (uint i = 0u; i < count; ++i) {
            float a = state[pc.accepted_at + i];
            set_x(i, a + 0.5 * (x_at(i) - a));
        }
        state[pc.halvings_at] += 1.0;
    }
    // The trial point projected onto the box (halving towards an accepted point stays in it).
    for (uint i = 0u; i < pc.dims; ++i) state[pc.latent_at + i] = clamp(state[pc.latent_at + i], -bound(i), bound(i));
    // The code after this iteration is the best found so far.
    for (uint j = 0u; j < pc.dims; ++j) {
        if (t < pc.max_iterations) state[pc.codes_at + t * pc.dims + j] = state[pc.accepted_at + j];
    }

    if (pc.pose_every > 0u) {
        mat3 r0;
        for (uint c = 0u; c < 3u; ++c) {
            for (uint r = 0u; r < 3u; ++r) r0[c][r] = state[pc.r0_at + 3u * c + r];
        }
        vec3 x_t = vec3(state[pc.pose_x_at], state[pc.pose_x_at + 1u], state[pc.pose_x_at + 2u]);
        vec3 x_w = vec3(state[pc.pose_x_at + 3u], state[pc.pose_x_at + 4u], state[pc.pose_x_at + 5u]);
        mat3 r = rodrigues(x_w) * r0;
        vec3 translation = vec3(state[pc.t0_at], state[pc.t0_at + 1u], state[pc.t0_at + 2u]) + x_t;
        views[0].object_to_camera = mat4(vec4(r[0], 0.0), vec4(r[1], 0.0), vec4(r[2], 0.0), vec4(translation, 1.0));
    }
    state[ITERATION] = float(t + 1u);
}

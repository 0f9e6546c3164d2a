// What the optimisers minimise besides the images' loss (glsl/optimizer.comp and
// glsl/bfgs.comp include this after declaring state[], views[] and pc, with pc.dims,
// pc.pose_every, pc.code_prior, pc.prior_at and pc.gravity_at):
// - the code prior: code_prior z^T P z, with P (dims x dims at prior_at, written by the
//   host: register::StateLayout::initial) the inverse training covariance in the
//   optimiser's coordinates z, so that the term is code_prior |s|^2 in training standard
//   deviations (zero rows for a scale coordinate);
// - gravity: the object's up axis u (object frame) kept within a tolerance of the up
//   direction g (camera frame), GRAVITY_WEIGHT (angle - tolerance)^2 beyond it, for the
//   first view's rotation R. 8 floats at gravity_at: u, g, tolerance (radians), on (0/1).
#ifndef OBJECTIVE_GLSL
#define OBJECTIVE_GLSL

// Per squared radian past the tolerance (src/register GRAVITY_WEIGHT): a mask loss
// changes by a few tenths per radian of tilt, so the tilt settles within a fraction of a
// degree of the tolerance.
const float GRAVITY_WEIGHT = 100.0;

float prior_row(uint i) {
    float v = 0.0;
    for (uint j = 0u; j < pc.dims; ++j) v += state[pc.prior_at + i * pc.dims + j] * state[pc.latent_at + j];
    return v;
}

float prior_term() {
    if (pc.code_prior == 0.0) return 0.0;
    float v = 0.0;
    for (uint i = 0u; i < pc.dims; ++i) v += state[pc.latent_at + i] * prior_row(i);
    return pc.code_prior * v;
}

// d prior / d z_i.
float prior_gradient(uint i) {
    return pc.code_prior == 0.0 ? 0.0 : 2.0 * pc.code_prior * prior_row(i);
}

bool gravity_on() { return pc.pose_every > 0u && state[pc.gravity_at + 7u] != 0.0; }

// The tilt of R u from g past the tolerance (radians, >= 0), and d tilt / d d for a
// rotation increment d applied on the left (R' = exp([d]x) R): with v = R u,
// d cos / d d = v x g, so d angle / d d = -(v x g) / sin(angle).
float gravity_excess(mat3 r, out vec3 gradient) {
    gradient = vec3(0.0);
    if (!gravity_on()) return 0.0;
    vec3 u = vec3(state[pc.gravity_at], state[pc.gravity_at + 1u], state[pc.gravity_at + 2u]);
    vec3 g = vec3(state[pc.gravity_at + 3u], state[pc.gravity_at + 4u], state[pc.gravity_at + 5u]);
    vec3 v = normalize(r * u);
    float c = clamp(dot(v, g), -1.0, 1.0);
    float angle = acos(c);
    float excess = angle - state[pc.gravity_at + 6u];
    if (excess <= 0.0) return 0.0;
    float s = sqrt(max(1.0 - c * c, 1e-12));
    gradient = -cross(v, g) / s;
    return excess;
}

float gravity_term(mat3 r) {
    vec3 unused;
    float e = gravity_excess(r, unused);
    return GRAVITY_WEIGHT * e * e;
}

// d gravity_term / d d (left increment).
vec3 gravity_gradient(mat3 r) {
    vec3 d;
    float e = gravity_excess(r, d);
    return 2.0 * GRAVITY_WEIGHT * e * d;
}

#endif  // OBJECTIVE_GLSL

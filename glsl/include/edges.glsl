#ifndef EDGES_GLSL
#define EDGES_GLSL
// 2D homogeneous edge functions of clip-space triangles (x, y, w per corner) and their
// derivatives. For the pixel p in NDC, a_k(p) = c_k.xy - p c_k.w and the edge function of
// the edge (i, j) is e(p) = cross(a_i, a_j) = L . (p, 1) with L = c_i x c_j. The
// perspective-correct barycentric weight of corner k is e_k / (e_0 + e_1 + e_2), where
// e_k belongs to the edge opposite corner k, and e_0 + e_1 + e_2 = det(c_0, c_1, c_2).

float cross2(vec2 a, vec2 b) { return a.x * b.y - a.y * b.x; }

float edge_function(vec3 ci, vec3 cj, vec2 p) {
    return cross2(ci.xy - p * ci.z, cj.xy - p * cj.z);
}

vec3 edge_functions(vec3 c0, vec3 c1, vec3 c2, vec2 p) {
    return vec3(edge_function(c1, c2, p), edge_function(c2, c0, p), edge_function(c0, c1, p));
}

vec3 barycentrics(vec3 c0, vec3 c1, vec3 c2, vec2 p) {
    vec3 e = edge_functions(c0, c1, c2, p);
    return e / (e.x + e.y + e.z);
}

// Adds g * de/dc_i and g * de/dc_j for e = edge_function(ci, cj, p).
void edge_function_backward(vec3 ci, vec3 cj, vec2 p, float g, inout vec3 gi, inout vec3 gj) {
    vec2 ai = ci.xy - p * ci.z;
    vec2 aj = cj.xy - p * cj.z;
    vec2 g_ai = g * vec2(aj.y, -aj.x);
    vec2 g_aj = g * vec2(-ai.y, ai.x);
    gi += vec3(g_ai, -dot(g_ai, p));
    gj += vec3(g_aj, -dot(g_aj, p));
}

// Adds bounds on |g * de/dc_i| and |g * de/dc_j| (componentwise) for every |g| <= bound.
void edge_function_backward_bound(vec3 ci, vec3 cj, vec2 p, float bound, inout vec3 bi, inout vec3 bj) {
    vec2 ai = abs(ci.xy - p * ci.z);
    vec2 aj = abs(cj.xy - p * cj.z);
    vec2 ap = abs(p);
    bi += bound * vec3(aj.y, aj.x, aj.y * ap.x + aj.x * ap.y);
    bj += bound * vec3(ai.y, ai.x, ai.y * ap.x + ai.x * ap.y);
}

#endif  // EDGES_GLSL

// Shared code of the differentiable passes: per-view camera data, exact perspective-correct
// barycentrics and depth of a pixel, and the search for the silhouette edge that crosses
// between two adjacent pixels (analytic antialiasing, after nvdiffrast's `antialias`).
//
// The including shader declares, before the include:
//   buffers  positions[] (float x, y, z), triangles[] (uint), neighbours[] (uint, the
//            triangle across the edge opposite corner k of triangle t at 3 t + k, or
//            NO_NEIGHBOUR), views[] (ViewData), ids[] (triangle id + 1 per pixel,
//            [view][row][column]);
// and push constants pc.width, pc.height.
#include "views.glsl"
#include "edges.glsl"

const uint NO_NEIGHBOUR = 0xffffffffu;
const int MAX_WALK = 8;  // triangles crossed between two pixel centres, at most
const float BACKGROUND_DEPTH = 3.0e38;

struct Triangle {
    uvec3 v;      // vertex indices
    vec3 cam[3];  // camera-space corners
    vec3 clip[3]; // clip-space corners (x, y, w)
};

Triangle load_triangle(ViewData vd, uint t) {
    Triangle tri;
    tri.v = uvec3(triangles[3u * t], triangles[3u * t + 1u], triangles[3u * t + 2u]);
    for (int k = 0; k < 3; ++k) {
        uint v = tri.v[k];
        vec3 p = vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]);
        tri.cam[k] = (vd.object_to_camera * vec4(p, 1.0)).xyz;
        vec4 c = view_camera_to_clip(vd, tri.cam[k]);
        tri.clip[k] = c.xyw;
    }
    return tri;
}

// +1 when the camera sees the triangle's counter-clockwise side, -1 otherwise.
float facing(Triangle tri) {
    return dot(tri.cam[0], cross(tri.cam[1], tri.cam[2])) >= 0.0 ? 1.0 : -1.0;
}

vec2 pixel_ndc(ivec2 pixel, ViewData vd) {
    return (vec2(pixel) + 0.5) * 2.0 / vd.size - 1.0;
}

uint pixel_index(ivec2 pixel, uint view) {
    return (view * pc.height + uint(pixel.y)) * pc.width + uint(pixel.x);
}

uint id_at(ivec2 pixel, uint view) {
    return ids[pixel_index(pixel, view)];
}

// Camera-space depth of the pixel centre on triangle `tri`.
float depth_on(Triangle tri, vec2 p) {
    vec3 b = barycentrics(tri.clip[0], tri.clip[1], tri.clip[2], p);
    return dot(b, vec3(tri.cam[0].z, tri.cam[1].z, tri.cam[2].z));
}

// Where the segment from pixel centre pf (covered by triangle t, the front surface) to
// pixel centre pb leaves the surface through a silhouette edge: walk across neighbours
// that face the same way until an edge with no neighbour, or one whose neighbour faces
// away, is crossed. alpha is the crossing's position along the segment (0 at pf); ef and
// eb are that edge's function at pf and pb (alpha = ef / (ef - eb)).
struct Crossing {
    bool found;
    uint triangle;
    int edge;  // opposite corner `edge`: corners (edge + 1) % 3 and (edge + 2) % 3
    float alpha;
    float ef;
    float eb;
};

Crossing find_crossing(ViewData vd, uint t, vec2 pf, vec2 pb) {
    Crossing none;
    none.found = false;
    uint current = t;
    uint previous = NO_NEIGHBOUR;
    for (int step = 0; step < MAX_WALK; ++step) {
        Triangle tri = load_triangle(vd, current);
        vec3 ef = edge_functions(tri.clip[0], tri.clip[1], tri.clip[2], pf);
        vec3 eb = edge_functions(tri.clip[0], tri.clip[1], tri.clip[2], pb);
        float inside = sign(ef.x + ef.y + ef.z);  // sum = det of the clip corners
        int exit_edge = -1;
        float exit_alpha = 2.0;
        for (int k = 0; k < 3; ++k) {
            if (previous != NO_NEIGHBOUR && neighbours[3u * current + uint(k)] == previous) continue;
            if (ef[k] * inside > 0.0 && eb[k] * inside < 0.0) {
                float a = ef[k] / (ef[k] - eb[k]);
                if (a < exit_alpha) { exit_alpha = a; exit_edge = k; }
            }
        }
        if (exit_edge < 0) return none;
        uint next = neighbours[3u * current + uint(exit_edge)];
        bool silhouette = next == NO_NEIGHBOUR || facing(load_triangle(vd, next)) != facing(tri);
        if (silhouette) {
            Crossing c;
            c.found = true;
            c.triangle = current;
            c.edge = exit_edge;
            c.alpha = exit_alpha;
            c.ef = ef[exit_edge];
            c.eb = eb[exit_edge];
            return c;
        }
        previous = current;
        current = next;
    }
    return none;
}

// Whether the crossing edge is handled by a pair along x (the edge is closer to vertical
// in pixel units) or along y; each edge is antialiased in one direction only.
bool handled_along_x(Triangle tri, int edge, ViewData vd) {
    vec3 ci = tri.clip[(edge + 1) % 3];
    vec3 cj = tri.clip[(edge + 2) % 3];
    float lx = ci.y * cj.z - ci.z * cj.y;
    float ly = ci.z * cj.x - ci.x * cj.z;
    return abs(lx) / vd.size.x >= abs(ly) / vd.size.y;
}

// One pair of adjacent pixels across a silhouette: the front pixel f, the other g, where
// the edge crosses, and which pixel's antialiased value changes (by w (c[o] - c[a])).
struct Pair {
    bool valid;
    ivec2 f;
    ivec2 g;
    uint front_triangle;  // triangle at f
    Crossing crossing;
    bool affects_g;       // alpha > 0.5: the front surface reaches into g's pixel
    float weight;         // |alpha - 0.5|
};

// The pair (p, q) with q = p + step (step (1, 0) or (0, 1)), both inside the image.
Pair make_pair(ViewData vd, uint view, ivec2 p, ivec2 q, bool along_x) {
    Pair pair;
    pair.valid = false;
    uint id_p = id_at(p, view);
    uint id_q = id_at(q, view);
    if (id_p == id_q) return pair;
    vec2 np = pixel_ndc(p, vd);
    vec2 nq = pixel_ndc(q, vd);
    float zp = BACKGROUND_DEPTH;
    float zq = BACKGROUND_DEPTH;
    if (id_p != 0u) zp = depth_on(load_triangle(vd, id_p - 1u), np);
    if (id_q != 0u) zq = depth_on(load_triangle(vd, id_q - 1u), nq);
    bool p_front = zp <= zq;
    pair.f = p_front ? p : q;
    pair.g = p_front ? q : p;
    pair.front_triangle = (p_front ? id_p : id_q) - 1u;
    vec2 pf = p_front ? np : nq;
    vec2 pb = p_front ? nq : np;
    Crossing c = find_crossing(vd, pair.front_triangle, pf, pb);
    if (!c.found) return pair;
    Triangle edge_tri = load_triangle(vd, c.triangle);
    if (handled_along_x(edge_tri, c.edge, vd) != along_x) return pair;
    pair.valid = true;
    pair.crossing = c;
    pair.affects_g = c.alpha > 0.5;
    pair.weight = abs(c.alpha - 0.5);
    return pair;
}

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

// The silhouette search: where the segment from pixel centre pf (covered by triangle t,
// the front surface) to pixel centre pb leaves the surface through a silhouette edge.
//
// Design. The search walks along the segment across the triangles of the front surface,
// edge by edge, until it leaves through a silhouette edge: one with no neighbour, or
// whose neighbour faces the other way. Four properties make it exact at any mesh
// density:
//  * No step limit short of MAX_WALK, a guard against broken meshes far above any real
//    count (a smooth rim seen edge-on has about sqrt(triangles per pixel) triangles
//    between two pixel centres; a 5e6-triangle sphere about a hundred). A walk that
//    reaches the guard, or finds the mesh's neighbour table inconsistent, is counted in
//    work_count[LOST_WALKS] and the host refuses the result (`Error::Limit`): a crossing
//    is never dropped silently.
//  * Occlusion comes with it: the walk starts on the surface seen at the front pixel and
//    only ever crosses that surface, so an edge hidden behind nearer geometry is never
//    reached, and whichever triangle owns the edge, the walk arrives at it.
//  * Decisions that cannot contradict each other. Which edge the walk leaves a triangle
//    by is decided by the side of the segment's line its corner opposite the entry edge
//    lies on (the line must leave through the edge joining that corner to the entry
//    edge's corner on the other side). That side is a property of the vertex alone,
//    computed by one expression, so every triangle around a vertex sees the same answer
//    and the walk cannot lose its way in triangles far thinner than float32 resolves
//    (comparing three independently rounded crossing parameters per triangle did: about
//    one walk in a thousand found no exit on a 1e4-vertex sphere and its crossing was
//    dropped). Only the first triangle compares parameters, to pick its exit.
//  * A shared edge's function is evaluated from its two vertices in index order
//    (walk_edge_function), so both triangles see the same bits when the walk asks
//    whether the segment ends before that edge.
// Rasterizing the silhouette edges instead (redner's edge sampling, Li et al. 2018) finds
// crossings without walking, but needs a visibility test per crossing that one G-buffer
// cannot answer between pixel centres; nvdiffrast only looks at the two triangles at the
// pixel centres and misses the edge when more lie between (the failure this replaces).
//
// The pixel centre need not lie inside the first triangle (the rasterizer snaps vertices
// to its sub-pixel grid, and a triangle thinner than that grid can own a pixel whose
// centre it misses): the crossing can then lie behind pf (alpha < 0, clamped in
// make_pair), and when the segment's line misses that triangle altogether there is no
// crossing to differentiate (counted in work_count[MISSED_STARTS], reported by bench).
//
// alpha is the crossing's position along the segment (0 at pf); ef and eb are that
// edge's function (edge_function(c_i, c_j) of its corners in triangle order) at pf and pb,
// alpha = ef / (ef - eb).
const int MAX_WALK = 65536;
const uint LOST_WALKS = 4u;     // work_count slot counting walks that could not finish
const uint MISSED_STARTS = 7u;  // work_count slot counting lines that miss their start
const uint UNFINISHED = 8u;     // work_count slot counting listed pixels a pass never reached

// The items of a grid-stride loop from `first` in steps of `stride` below `count`.
uint grid_items(uint first, uint stride, uint count) {
    return first < count ? (count - first - 1u) / stride + 1u : 0u;
}
const uint NO_VERTEX = 0xffffffffu;

struct Crossing {
    bool found;
    bool lost;    // the walk reached MAX_WALK or met an inconsistent neighbour table
    bool missed;  // the segment's line misses the first triangle
    uint triangle;
    Triangle tri;  // that triangle, loaded
    int edge;  // opposite corner `edge`: corners (edge + 1) % 3 and (edge + 2) % 3
    float alpha;
    float ef;
    float eb;
};

// The function of the edge opposite corner k at p, in the triangle's corner order, computed
// from the edge's vertices in index order so that both triangles sharing it agree exactly.
float walk_edge_function(Triangle tri, int k, vec2 p) {
    int i = (k + 1) % 3;
    int j = (k + 2) % 3;
    if (tri.v[i] < tri.v[j]) return edge_function(tri.clip[i], tri.clip[j], p);
    return -edge_function(tri.clip[j], tri.clip[i], p);
}

// Which side of the line through pf along d the clip-space point c lies on (w > 0).
bool left_of_line(vec3 c, vec2 pf, vec2 d) {
    precise float side = cross2(d, c.xy - pf * c.z);
    return side >= 0.0;
}

// Which side of the line through pf along d each corner of `tri` lies on.
bvec3 sides_of_line(Triangle tri, vec2 pf, vec2 d) {
    return bvec3(left_of_line(tri.clip[0], pf, d), left_of_line(tri.clip[1], pf, d),
                 left_of_line(tri.clip[2], pf, d));
}

Crossing find_crossing(ViewData vd, uint t, vec2 pf, vec2 pb) {
    Crossing c;
    c.found = false;
    c.lost = false;
    c.missed = false;
    vec2 d = pb - pf;
    uint current = t;
    uvec2 entry = uvec2(NO_VERTEX);  // the vertices of the edge the walk came in by
    // Each triangle is loaded once: the next one is loaded to test its facing and then
    // walked through.
    Triangle tri = load_triangle(vd, current);
    // The triangle's orientation on screen; det(clip corners) = sx sy det(camera corners).
    // The same on every triangle the walk enters (it stops at the first that differs).
    float inside = facing(tri);
    // The first triangle's exit: of the edges the line crosses (corners on both sides), the
    // one it leaves by. (Before the loop, which then holds only the later steps' rule: a
    // CPU driver runs both sides of a branch inside it at every step.)
    bvec3 left = sides_of_line(tri, pf, d);
    int exit_edge = -1;
    float best = -3.0e38;
    for (int k = 0; k < 3; ++k) {
        if (left[(k + 1) % 3] == left[(k + 2) % 3]) continue;
        float ef = walk_edge_function(tri, k, pf);
        float eb = walk_edge_function(tri, k, pb);
        float outward = (ef - eb) * inside;
        if (outward > best) {
            best = outward;
            exit_edge = k;
        }
    }
    if (exit_edge < 0) {
        c.missed = true;
        return c;
    }
    for (int step = 0; step < MAX_WALK; ++step) {
        float ef = walk_edge_function(tri, exit_edge, pf);
        float eb = walk_edge_function(tri, exit_edge, pb);
        // The segment ends before the exit: pb is on this surface, no silhouette between.
        if (eb * inside >= 0.0) return c;
        uint next = neighbours[3u * current + uint(exit_edge)];
        Triangle next_tri;
        bool silhouette = next == NO_NEIGHBOUR;
        if (!silhouette) {
            next_tri = load_triangle(vd, next);
            silhouette = facing(next_tri) != inside;
        }
        if (silhouette) {
            c.found = true;
            c.tri = tri;
            c.triangle = current;
            c.edge = exit_edge;
            c.alpha = ef / (ef - eb);
            c.ef = ef;
            c.eb = eb;
            return c;
        }
        entry = uvec2(tri.v[(exit_edge + 1) % 3], tri.v[(exit_edge + 2) % 3]);
        current = next;
        tri = next_tri;
        // The next exit. The corner opposite the entry edge, and the entry corner on its
        // other side.
        left = sides_of_line(tri, pf, d);
        int apex = -1;
        int on_entry = 0;
        for (int k = 0; k < 3; ++k) {
            if (tri.v[k] == entry.x || tri.v[k] == entry.y) ++on_entry;
            else apex = k;
        }
        if (on_entry != 2 || apex < 0) {
            c.lost = true;  // the neighbour table does not match the triangles
            return c;
        }
        int i = (apex + 1) % 3;
        int j = (apex + 2) % 3;
        // Leave by the edge apex-i if i is across the line from apex (the edge opposite
        // j), else by apex-j (opposite i).
        exit_edge = left[i] != left[apex] ? j : i;
    }
    c.lost = true;
    return c;
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
    bool lost;            // the silhouette search gave up (see find_crossing)
    bool missed;          // the segment's line misses the front pixel's triangle
    bool clamped;         // the crossing lies outside the pair: alpha held at 0 or 1
    ivec2 f;
    ivec2 g;
    Crossing crossing;
    bool affects_g;       // alpha > 0.5: the front surface reaches into g's pixel
    float weight;         // |alpha - 0.5|
};

// The pair's crossing where the crossing edge's function has values ef at f and eb at g.
// What the crossing's position alpha along the pair decides: a crossing behind the front
// pixel's centre (see find_crossing) counts as at it, and moves nothing there; one past
// the other centre (a front pixel centre just outside its triangle, from the
// rasterizer's snapping, next to an edge almost along the pair) as at that centre. So
// weight <= 1/2, which the backward's bound relies on (diff_pass.glsl gradient_bounds).
void place_alpha(inout Pair pair, float alpha) {
    pair.crossing.alpha = alpha;
    pair.clamped = alpha < 0.0 || alpha > 1.0;
    pair.affects_g = alpha > 0.5;
    pair.weight = abs(clamp(alpha, 0.0, 1.0) - 0.5);
}

void place_crossing(inout Pair pair, float ef, float eb) {
    pair.crossing.found = true;
    pair.crossing.ef = ef;
    pair.crossing.eb = eb;
    place_alpha(pair, ef / (ef - eb));
}

// The pair (p, q) with q = p + step (step (1, 0) or (0, 1)), both inside the image.
Pair make_pair(ViewData vd, uint view, ivec2 p, ivec2 q, bool along_x) {
    Pair pair;
    pair.valid = false;
    pair.lost = false;
    pair.missed = false;
    pair.clamped = false;
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
    uint front_triangle = (p_front ? id_p : id_q) - 1u;
    vec2 pf = p_front ? np : nq;
    vec2 pb = p_front ? nq : np;
    Crossing c = find_crossing(vd, front_triangle, pf, pb);
    pair.lost = c.lost;
    pair.missed = c.missed;
    if (!c.found) return pair;
    if (handled_along_x(c.tri, c.edge, vd) != along_x) return pair;
    pair.valid = true;
    pair.crossing = c;
    place_crossing(pair, c.ef, c.eb);
    return pair;
}

// A valid pair as one word, so that the walk runs once per pair and evaluation (make_pair
// from antialias.comp stage 0) and the passes after it rebuild the pair from the word:
// bit 31 valid, bit 30 the first pixel p is the front one, bits 28-29 the crossing edge,
// bits 0-27 its triangle (Scene::new refuses meshes with 2^28 triangles or more). The
// rebuilt crossing evaluates the edge's function at the two pixel centres as the walk did.
const uint PAIR_VALID = 0x80000000u;
const uint PAIR_P_FRONT = 0x40000000u;
const uint PAIR_TRIANGLE = 0x0fffffffu;

uint encode_pair(Pair pair, ivec2 p) {
    if (!pair.valid) return 0u;
    return PAIR_VALID | (pair.f == p ? PAIR_P_FRONT : 0u) | (uint(pair.crossing.edge) << 28u)
        | pair.crossing.triangle;
}

// The pair (p, q) from its record: whether it is valid and which pixel is in front.
Pair decode_sides(ivec2 p, ivec2 q, uint record) {
    Pair pair;
    pair.valid = (record & PAIR_VALID) != 0u;
    pair.lost = false;
    pair.missed = false;
    pair.clamped = false;
    if (!pair.valid) return pair;
    bool p_front = (record & PAIR_P_FRONT) != 0u;
    pair.f = p_front ? p : q;
    pair.g = p_front ? q : p;
    return pair;
}

// The pair as far as antialiasing needs it, from its record and its crossing's alpha (the
// backward needs the edge's vertices too: decode_pair).
Pair decode_pair_weight(ivec2 p, ivec2 q, uint record, float alpha) {
    Pair pair = decode_sides(p, q, record);
    if (pair.valid) place_alpha(pair, alpha);
    return pair;
}

// The pair as the backward needs it: also the crossing edge's triangle and the edge's
// function at the two pixel centres (what its gradient is taken through). What alpha
// decides (clamped, which pixel changes, the weight) comes from the forward's `alpha`,
// not from these values' quotient, so that a compiler's different rounding in this shader
// cannot turn a pair the forward held clamped (and the backward's bound left out) into one
// with a gradient.
Pair decode_pair(ViewData vd, ivec2 p, ivec2 q, uint record, float alpha) {
    Pair pair = decode_sides(p, q, record);
    if (!pair.valid) return pair;
    pair.crossing.lost = false;
    pair.crossing.missed = false;
    pair.crossing.found = true;
    pair.crossing.triangle = record & PAIR_TRIANGLE;
    pair.crossing.edge = int((record >> 28u) & 3u);
    pair.crossing.tri = load_triangle(vd, pair.crossing.triangle);
    pair.crossing.ef = walk_edge_function(pair.crossing.tri, pair.crossing.edge, pixel_ndc(pair.f, vd));
    pair.crossing.eb = walk_edge_function(pair.crossing.tri, pair.crossing.edge, pixel_ndc(pair.g, vd));
    place_alpha(pair, alpha);
    return pair;
}

#version 460
// Stage 0, per pixel of each view's box (bounds.comp; z = view): when no pair with a
// neighbour matters (pair_matters: with coverage, the pixel and its four neighbours are
// all covered or all background) and nothing is interpolated, its antialiased value is
// its coverage; write it and add its loss terms less the background's (loss_excess) to
// stats_fixed, one int64 fixed-point sum per subgroup (the same sums in any order). Every
// other pixel is appended to the work list for antialias.comp and antialias_backward.comp.
// Stage 1, once per observation (x over workgroups, grid stride over every pixel of view
// z): the background terms loss_terms(pixel, 0) of the whole image, added to stats_fixed
// (the host keeps them and starts every evaluation's sums from them).
#include "diff_pass.glsl"

layout(local_size_x = 8, local_size_y = 8) in;

void background_terms() {
    uint view = gl_WorkGroupID.z;
    uint pixels = pc.width * pc.height;
    uint stride = gl_NumWorkGroups.x * 64u;
    i64vec3 sum = i64vec3(0);
    for (uint i = gl_WorkGroupID.x * 64u + gl_LocalInvocationIndex; i < pixels; i += stride) {
        vec3 terms = loss_terms(view * pixels + i, vec4(0.0));
        for (int k = 0; k < 3; ++k) sum[k] += to_fixed(terms[k], pc.stats_shift);
    }
    for (int k = 0; k < 3; ++k) {
        if (sum[k] != 0) atomicAdd(stats_fixed[3u * view + uint(k)], sum[k]);
    }
}

// Each invocation classifies a column of ROWS pixels (a workgroup an 8 x (8 ROWS) tile):
// the ids above and below each pixel are its column neighbours' own, so an invocation
// loads 3 ROWS + 2 ids instead of 5 ROWS (per-lane buffer loads are what a CPU driver
// pays for).
const int ROWS = 4;

void main() {
    if (pc.stage == 1u) {
        background_terms();
        return;
    }
    uint view = gl_GlobalInvocationID.z;
    uint box = 4u + 4u * gl_NumWorkGroups.z + 4u * view;
    ivec2 size = ivec2(pc.width, pc.height);
    ivec2 extent = ivec2(boxes[box + 2u], boxes[box + 3u]);
    ivec2 local = ivec2(gl_GlobalInvocationID.x, gl_GlobalInvocationID.y * uint(ROWS));
    ivec2 top = ivec2(boxes[box], boxes[box + 1u]) + local;
    // ids[r + 1] is row top.y + r of this column (r = -1 .. ROWS); at the image border the
    // pixel itself stands in for its missing neighbour.
    uint column[ROWS + 2];
    uint left[ROWS];
    uint right[ROWS];
    bool inside[ROWS];
    uint index[ROWS];
    for (int r = 0; r < ROWS; ++r) {
        ivec2 p = top + ivec2(0, r);
        inside[r] = local.x < extent.x && local.y + r < extent.y;
        index[r] = inside[r] ? pixel_index(p, view) : 0u;
        column[r + 1] = inside[r] ? ids[index[r]] : 0u;
    }
    for (int r = 0; r < ROWS; ++r) {
        if (!inside[r]) continue;
        ivec2 p = top + ivec2(0, r);
        left[r] = p.x > 0 ? ids[index[r] - 1u] : column[r + 1];
        right[r] = p.x + 1 < size.x ? ids[index[r] + 1u] : column[r + 1];
    }
    // Rows inside the box are a prefix; the one below the last of them is loaded too.
    int rows = 0;
    for (int r = 0; r < ROWS; ++r) rows += int(inside[r]);
    if (rows > 0) {
        column[0] = top.y > 0 ? ids[index[0] - pc.width] : column[1];
        uint last = index[rows - 1];
        column[rows + 1] = top.y + rows < size.y ? ids[last + pc.width] : column[rows];
    }

    bool listed[ROWS];
    uint count = 0u;
    vec3 terms = vec3(0.0);
    for (int r = 0; r < ROWS; ++r) {
        uint id = column[r + 1];
        bool any_pair = pair_matters(id, right[r]) || pair_matters(id, left[r])
            || pair_matters(id, column[r + 2]) || pair_matters(id, column[r]);
        listed[r] = inside[r] && (any_pair || (pc.channels > 0u && id != 0u));
        if (inside[r] && !listed[r] && id != 0u) {
            // Covered, against a mask: one channel, no interpolation.
            antialiased[index[r]] = 1.0;
            terms += loss_excess(index[r], vec4(1.0, 0.0, 0.0, 0.0));
        }
        // Background away from the object: value 0 (the whole image is cleared before),
        // no excess.
        count += uint(listed[r]);
    }

    // One slot range per subgroup in the work list, then each invocation's pixels in order.
    uint total = subgroupAdd(count);
    uint base = 0u;
    if (subgroupElect() && total > 0u) base = atomicAdd(work_count[0], total);
    base = subgroupBroadcastFirst(base) + subgroupExclusiveAdd(count);
    for (int r = 0; r < ROWS; ++r) {
        if (listed[r]) work[base++] = index[r];
    }

    terms = subgroupAdd(terms);
    if (subgroupElect()) {
        for (int k = 0; k < 3; ++k) {
            if (terms[k] != 0.0) atomicAdd(stats_fixed[3u * view + uint(k)], to_fixed(terms[k], pc.stats_shift));
        }
    }
}

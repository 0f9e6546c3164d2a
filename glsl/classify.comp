#version 460
// Stage 0, per pixel of each view's box (bounds.comp; z = view): when no pair with a
// neighbour matters (pair_matters: with coverage, the pixel and its four neighbours are
// all covered or all background) and nothing is interpolated (interpolated_inside in
// loss.glsl: with a mask and depth, only where depth is measured), its antialiased value
// is its coverage; write it and add its loss terms less the background's (loss_excess) to
// stats_fixed, one int64 fixed-point sum per subgroup (the same sums in any order). Every
// other pixel is appended to the work list for antialias.comp and antialias_backward.comp
// (flagged HAS_PAIR where a pair with a neighbour matters),
// and each pair that matters of a pixel with its right and lower neighbours to the pair
// lists (diff_pass.glsl pair_work_x, pair_work_y) for antialias.comp stage 0.
// Stage 1, once per observation (x over workgroups, grid stride over every pixel of view
// z): the background terms loss_terms(pixel, 0) of the whole image, added to stats_fixed
// (the host keeps them and starts every evaluation's sums from them).
#include "diff_pass.glsl"

layout(local_size_x = 8, local_size_y = 8) in;

// The stage, a specialization constant (one pipeline per stage, as in antialias.comp).
layout(constant_id = 0) const uint STAGE = 0u;

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

// Each invocation classifies a column of ROWS pixels (a workgroup a tile of 8 x (8 ROWS)),
// walking down it with the ids above, at and below the current pixel in hand: 3 id loads
// per pixel instead of 5, and a CPU driver's cost per invocation (on lavapipe about that
// of classifying a pixel) paid once per ROWS pixels. Listed rows are bits of a mask until
// the work list is appended to, once per subgroup.
const int ROWS = 16;

// This invocation's first slot in the list counted at work_count[counter] for the rows
// `bits` flags (one atomic per subgroup).
uint list_slots(uint counter, uint bits) {
    uint count = bitCount(bits);
    uint total = subgroupAdd(count);
    uint base = 0u;
    if (subgroupElect() && total > 0u) base = atomicAdd(work_count[counter], total);
    return subgroupBroadcastFirst(base) + subgroupExclusiveAdd(count);
}

void main() {
    if (STAGE == 1u) {
        background_terms();
        return;
    }
    uint view = gl_GlobalInvocationID.z;
    uint box = 4u + 4u * gl_NumWorkGroups.z + 4u * view;
    ivec2 size = ivec2(pc.width, pc.height);
    ivec2 extent = ivec2(boxes[box + 2u], boxes[box + 3u]);
    ivec2 local = ivec2(gl_GlobalInvocationID.x, gl_GlobalInvocationID.y * uint(ROWS));
    ivec2 top = ivec2(boxes[box], boxes[box + 1u]) + local;
    // Rows of this column inside the box (at the image border the pixel itself stands in
    // for its missing neighbour).
    int rows = local.x < extent.x ? clamp(extent.y - local.y, 0, ROWS) : 0;
    uint first = rows > 0 ? pixel_index(top, view) : 0u;
    uint id = rows > 0 ? ids[first] : 0u;
    uint up = rows > 0 && top.y > 0 ? ids[first - pc.width] : id;
    uint listed = 0u;  // bit r: row r is listed
    uint paired = 0u;  // bit r: a pair of row r's pixel with a neighbour matters
    uint pairs_x = 0u;  // bit r: row r's pair with its right neighbour matters
    uint pairs_y = 0u;  // ... with the pixel below
    vec3 terms = vec3(0.0);
    for (int r = 0; r < rows; ++r) {
        uint index = first + uint(r) * pc.width;
        int y = top.y + r;
        uint down = y + 1 < size.y ? ids[index + pc.width] : id;
        uint left = top.x > 0 ? ids[index - 1u] : id;
        uint right = top.x + 1 < size.x ? ids[index + 1u] : id;
        bool pair_x = pair_matters(id, right);
        bool pair_y = pair_matters(id, down);
        pairs_x |= uint(pair_x) << uint(r);
        pairs_y |= uint(pair_y) << uint(r);
        bool any_pair = pair_x || pair_matters(id, left) || pair_y || pair_matters(id, up);
        paired |= uint(any_pair) << uint(r);
        if (any_pair || (id != 0u && interpolated_inside(index))) {
            listed |= 1u << uint(r);
        } else if (id != 0u) {
            // Covered, against a mask, and no depth to compare: coverage 1 (the depth
            // channel, if any, stays 0), no interpolation.
            antialiased[index * image_channels()] = 1.0;
            terms += loss_excess(index, vec4(1.0, 0.0, 0.0, 0.0));
        }
        // Background away from the object: value 0 (the whole image is cleared before),
        // no excess.
        up = id;
        id = down;
    }

    // One slot range per subgroup in each list, then each invocation's pixels in order.
    uint base = list_slots(0u, listed);
    while (listed != 0u) {
        int r = findLSB(listed);
        listed &= listed - 1u;
        work[base++] = (first + uint(r) * pc.width) | ((paired >> uint(r)) & 1u) * HAS_PAIR;
    }
    base = list_slots(PAIRS_X_COUNT, pairs_x);
    while (pairs_x != 0u) {
        int r = findLSB(pairs_x);
        pairs_x &= pairs_x - 1u;
        pair_work_x[base++] = first + uint(r) * pc.width;
    }
    base = list_slots(PAIRS_Y_COUNT, pairs_y);
    while (pairs_y != 0u) {
        int r = findLSB(pairs_y);
        pairs_y &= pairs_y - 1u;
        pair_work_y[base++] = first + uint(r) * pc.width;
    }

    terms = subgroupAdd(terms);
    if (subgroupElect()) {
        for (int k = 0; k < 3; ++k) {
            if (terms[k] != 0.0) atomicAdd(stats_fixed[3u * view + uint(k)], to_fixed(terms[k], pc.stats_shift));
        }
    }
}

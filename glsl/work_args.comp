#version 460
// Dispatch arguments for the passes over the work list: enough workgroups of 64 for the
// listed pixels, at most pc.max_groups (those passes loop with a grid stride), but never
// so few that an invocation handles more than ITEMS_PER_INVOCATION of them: lavapipe ends
// an invocation's loops after 65535 iterations (src/gpu/mod.rs, LOOP_LIMIT), and a listed
// pixel costs a pass a few dozen of them (about 36 on average with four channels).
layout(local_size_x = 1) in;

layout(set = 0, binding = 0, std430) buffer WorkCount { uint work_count[]; };  // count, x, y, z

layout(push_constant, std430) uniform Constants { uint max_groups; } pc;

const uint ITEMS_PER_INVOCATION = 64u;

// work_count slots: the pair lists' counts and the pairs pass's dispatch (as in
// include/diff_pass.glsl).
const uint PAIRS_X_COUNT = 17u;
const uint PAIRS_Y_COUNT = 18u;
const uint PAIR_DISPATCH = 19u;

// The dispatch (x, y, z) at `at` for a grid-stride pass over `count` items.
void dispatch(uint at, uint count) {
    uint fewest = (count + 64u * ITEMS_PER_INVOCATION - 1u) / (64u * ITEMS_PER_INVOCATION);
    work_count[at] = clamp((count + 63u) / 64u, 1u, max(pc.max_groups, fewest));
    work_count[at + 1u] = 1u;
    work_count[at + 2u] = 1u;
}

void main() {
    // The passes over the listed pixels, and the pairs pass.
    dispatch(1u, work_count[0]);
    dispatch(PAIR_DISPATCH, work_count[PAIRS_X_COUNT] + work_count[PAIRS_Y_COUNT]);
}

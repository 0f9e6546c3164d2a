#version 460
// Dispatch arguments for the passes over the work list: enough workgroups of 64 for the
// listed pixels, at most pc.max_groups (those passes loop with a grid stride).
layout(local_size_x = 1) in;

layout(set = 0, binding = 0, std430) buffer WorkCount { uint work_count[]; };  // count, x, y, z

layout(push_constant, std430) uniform Constants { uint max_groups; } pc;

void main() {
    work_count[1] = clamp((work_count[0] + 63u) / 64u, 1u, pc.max_groups);
    work_count[2] = 1u;
    work_count[3] = 1u;
}

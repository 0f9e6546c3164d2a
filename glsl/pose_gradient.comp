#version 460
// Camera-space vertex gradients of every view to object-space vertex gradients (summed
// over views, atomically) and to each view's pose gradient: translation t and a local
// rotation increment d applied on the left (x_camera = exp([d]x) R x + t), so
// dL/dt = sum g and dL/dd = sum (R x) x g. Subgroup sums are added atomically.
#extension GL_EXT_shader_atomic_float : require
#extension GL_KHR_shader_subgroup_arithmetic : require
#extension GL_KHR_shader_subgroup_basic : require
#include "views.glsl"

layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };
layout(set = 0, binding = 1, std430) readonly buffer Views { ViewData views[]; };
layout(set = 0, binding = 2, std430) readonly buffer GradCamera { float grad_camera[]; };  // [view][vertex][3]
layout(set = 0, binding = 3, std430) buffer GradObject { float grad_object[]; };           // [vertex][3]
layout(set = 0, binding = 4, std430) buffer GradPose { float grad_pose[]; };               // [view][6]

layout(push_constant, std430) uniform Constants { uint vertex_count; } pc;

void main() {
    uint view = gl_GlobalInvocationID.z;
    mat3 r = mat3(views[view].object_to_camera);
    vec3 sum_t = vec3(0.0);
    vec3 sum_r = vec3(0.0);
    uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
    for (uint v = gl_GlobalInvocationID.x; v < pc.vertex_count; v += stride) {
        uint at = 3u * (view * pc.vertex_count + v);
        vec3 g = vec3(grad_camera[at], grad_camera[at + 1u], grad_camera[at + 2u]);
        if (g == vec3(0.0)) continue;
        vec3 x = vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]);
        vec3 g_object = transpose(r) * g;
        atomicAdd(grad_object[3u * v], g_object.x);
        atomicAdd(grad_object[3u * v + 1u], g_object.y);
        atomicAdd(grad_object[3u * v + 2u], g_object.z);
        sum_t += g;
        sum_r += cross(r * x, g);
    }
    sum_t = subgroupAdd(sum_t);
    sum_r = subgroupAdd(sum_r);
    if (subgroupElect()) {
        for (int k = 0; k < 3; ++k) {
            atomicAdd(grad_pose[6u * view + uint(k)], sum_t[k]);
            atomicAdd(grad_pose[6u * view + 3u + uint(k)], sum_r[k]);
        }
    }
}

#version 460
// Lambert shading as a per-vertex attribute of every view, and its backward. One
// directional light (pc.light: unit vector towards it, camera frame) and an ambient term:
//   a = ambient + (1 - ambient) max(0, s n . light),   n = m / |m|,
//   m = sum over the vertex's triangles of (x1 - x0) x (x2 - x0)   (camera space),
//   s = -1 where the vertex faces away from the camera (n . x > 0), else 1.
// Two-sided: a surface seen from behind is lit with its normal flipped, as a camera sees
// the inside of an open scan (a cup seen into its opening). On a closed mesh such vertices
// only reach pixels by interpolation next to the silhouette. s is constant between the
// places where n . x changes sign, so the backward carries it as a factor.
// The area-weighted normal m only needs each vertex's own triangles (the `incident` list),
// so every stage writes one vertex of one view per invocation, without atomics:
//   stage 0: attributes[view][v][0] = a (pc.stride channels a vertex: with depth, 2);
//   stage 1: grad_normal[view][v] = dL/dm from dL/da (grad_attributes);
//   stage 2: grad_camera[view][v] += dL/dx through every m that x is a corner of, with
//            d(e1 x e2) . g = de1 . (e2 x g) + de2 . (g x e1), e1 = x1 - x0, e2 = x2 - x0.
// Grid: x over vertices, z over views.
#include "views.glsl"

layout(local_size_x = 64) in;

layout(set = 0, binding = 0, std430) readonly buffer Positions { float positions[]; };
layout(set = 0, binding = 1, std430) readonly buffer Triangles { uint triangles[]; };
layout(set = 0, binding = 2, std430) readonly buffer Views { ViewData views[]; };
layout(set = 0, binding = 3, std430) readonly buffer IncidentStart { uint incident_start[]; };  // [vertex + 1]
layout(set = 0, binding = 4, std430) readonly buffer Incident { uint incident[]; };  // 3 triangle + corner
layout(set = 0, binding = 5, std430) buffer Attributes { float attributes[]; };        // [view][vertex][stride]
layout(set = 0, binding = 6, std430) readonly buffer GradAttributes { float grad_attributes[]; };  // [view][vertex][stride]
layout(set = 0, binding = 7, std430) buffer GradNormal { float grad_normal[]; };       // [view][vertex][3]
layout(set = 0, binding = 8, std430) buffer GradCamera { float grad_camera[]; };       // [view][vertex][3]

layout(push_constant, std430) uniform Constants {
    uint vertex_count;
    uint stage;
    float ambient;
    float light_x;
    float light_y;
    float light_z;
    uint stride;  // attribute channels a vertex (the shade is channel 0)
} pc;

vec3 camera_position(mat4 object_to_camera, uint v) {
    vec3 p = vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]);
    return (object_to_camera * vec4(p, 1.0)).xyz;
}

vec3 load3(uint at, bool normal) {
    return normal ? vec3(grad_normal[at], grad_normal[at + 1u], grad_normal[at + 2u])
                  : vec3(grad_camera[at], grad_camera[at + 1u], grad_camera[at + 2u]);
}

void main() {
    uint v = gl_GlobalInvocationID.x;
    uint view = gl_GlobalInvocationID.z;
    if (v >= pc.vertex_count) return;
    mat4 to_camera = views[view].object_to_camera;
    uint slot = view * pc.vertex_count + v;
    vec3 light = vec3(pc.light_x, pc.light_y, pc.light_z);

    if (pc.stage == 2u) {
        vec3 g_x = vec3(0.0);
        for (uint i = incident_start[v]; i < incident_start[v + 1u]; ++i) {
            uint t = incident[i] / 3u;
            uint corner = incident[i] % 3u;
            uvec3 tri = uvec3(triangles[3u * t], triangles[3u * t + 1u], triangles[3u * t + 2u]);
            uint base = view * pc.vertex_count;
            vec3 g = load3(3u * (base + tri.x), true) + load3(3u * (base + tri.y), true)
                   + load3(3u * (base + tri.z), true);
            vec3 x0 = camera_position(to_camera, tri.x);
            vec3 e1 = camera_position(to_camera, tri.y) - x0;
            vec3 e2 = camera_position(to_camera, tri.z) - x0;
            vec3 g1 = cross(e2, g);
            vec3 g2 = cross(g, e1);
            g_x += corner == 0u ? -(g1 + g2) : (corner == 1u ? g1 : g2);
        }
        vec3 sum = load3(3u * slot, false) + g_x;
        grad_camera[3u * slot] = sum.x;
        grad_camera[3u * slot + 1u] = sum.y;
        grad_camera[3u * slot + 2u] = sum.z;
        return;
    }

    vec3 m = vec3(0.0);
    for (uint i = incident_start[v]; i < incident_start[v + 1u]; ++i) {
        uint t = incident[i] / 3u;
        vec3 x0 = camera_position(to_camera, triangles[3u * t]);
        vec3 x1 = camera_position(to_camera, triangles[3u * t + 1u]);
        vec3 x2 = camera_position(to_camera, triangles[3u * t + 2u]);
        m += cross(x1 - x0, x2 - x0);
    }
    float len = length(m);
    vec3 n = len > 0.0 ? m / len : vec3(0.0);
    float side = dot(n, camera_position(to_camera, v)) > 0.0 ? -1.0 : 1.0;
    float lit = side * dot(n, light);
    if (pc.stage == 0u) {
        attributes[slot * pc.stride] = pc.ambient + (1.0 - pc.ambient) * max(lit, 0.0);
        return;
    }
    vec3 g_n = lit > 0.0 ? grad_attributes[slot * pc.stride] * (1.0 - pc.ambient) * side * light : vec3(0.0);
    vec3 g_m = len > 0.0 ? (g_n - n * dot(n, g_n)) / len : vec3(0.0);
    grad_normal[3u * slot] = g_m.x;
    grad_normal[3u * slot + 1u] = g_m.y;
    grad_normal[3u * slot + 2u] = g_m.z;
}

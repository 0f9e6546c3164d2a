#version 460
// Each view's box of pixels that can differ from background, and the classify dispatch
// that covers the boxes (classify.comp runs over the boxes only; the background terms of
// the loss outside them were summed once per observation, see loss_excess).
//
// boxes[] (int):
//   0..2          indirect dispatch of classify.comp (x, y, z groups of 8 x 128 pixels);
//   4 + 2 v       smallest projected vertex pixel (x, y) of view v, atomicMin;
//   4 + 2 n + 2 v largest, atomicMax (the host fills both before stage 0);
//   4 + 4 n + 4 v the view's box: first column, first row, width, height.
// Every covered pixel centre lies in a triangle, so within the bounding box of the
// projected vertices; a pixel is listed or changed only next to a covered pixel. The box
// is that bounding box grown by MARGIN pixels (a neighbour, and vertex snapping to the
// rasterizer's sub-pixel grid). A vertex not in front of the near plane (clipped
// triangles) or not finite makes the box the whole image. With at least a third as many
// vertices as pixels the host skips stage 0 and fills the extremes beyond the image
// instead (Scene::record_marked): projecting the vertices would cost more than
// classifying every pixel.
//   stage 0 (x over vertices, grid stride): the per-view extremes;
//   stage 1 (one invocation; dispatched with z = views too): the boxes and the dispatch.
#include "diff_pass.glsl"

layout(local_size_x = 64) in;

const int MARGIN = 2;

void main() {
    uint views_n = gl_NumWorkGroups.z;
    ivec2 size = ivec2(pc.width, pc.height);
    if (pc.stage == 0u) {
        uint view = gl_WorkGroupID.z;
        ViewData vd = views[view];
        ivec2 lo = ivec2(0x7fffffff);
        ivec2 hi = ivec2(-0x7fffffff);
        uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
        for (uint v = gl_GlobalInvocationID.x; v < pc.vertex_count; v += stride) {
            vec3 p = vec3(positions[3u * v], positions[3u * v + 1u], positions[3u * v + 2u]);
            vec3 cam = (vd.object_to_camera * vec4(p, 1.0)).xyz;
            vec4 clip = view_camera_to_clip(vd, cam);
            vec2 pixel = (clip.xy / clip.w + 1.0) * 0.5 * vd.size;
            bool usable = cam.z >= vd.near && all(lessThan(abs(pixel), vec2(1.0e6)));
            // Beyond the image on either side is as good as its edge (clamped, so the
            // conversion to int is defined).
            ivec2 at = usable ? ivec2(floor(clamp(pixel, vec2(-8.0), vd.size + 8.0))) : ivec2(0);
            lo = min(lo, usable ? at : ivec2(-8));
            hi = max(hi, usable ? at : size + 8);
        }
        lo = subgroupMin(lo);
        hi = subgroupMax(hi);
        if (subgroupElect()) {
            atomicMin(boxes[4u + 2u * view], lo.x);
            atomicMin(boxes[4u + 2u * view + 1u], lo.y);
            atomicMax(boxes[4u + 2u * views_n + 2u * view], hi.x);
            atomicMax(boxes[4u + 2u * views_n + 2u * view + 1u], hi.y);
        }
        return;
    }
    if (gl_GlobalInvocationID != uvec3(0u)) return;
    ivec2 groups = ivec2(0);
    for (uint view = 0u; view < views_n; ++view) {
        ivec2 lo = ivec2(boxes[4u + 2u * view], boxes[4u + 2u * view + 1u]);
        ivec2 hi = ivec2(boxes[4u + 2u * views_n + 2u * view], boxes[4u + 2u * views_n + 2u * view + 1u]);
        ivec2 first = clamp(lo - MARGIN, ivec2(0), size);
        ivec2 end = clamp(hi + 1 + MARGIN, ivec2(0), size);
        ivec2 extent = lo.x <= hi.x ? max(end - first, ivec2(0)) : ivec2(0);  // no vertex: empty
        uint at = 4u + 4u * views_n + 4u * view;
        boxes[at] = first.x;
        boxes[at + 1u] = first.y;
        boxes[at + 2u] = extent.x;
        boxes[at + 3u] = extent.y;
        groups = max(groups, (extent + ivec2(7, 127)) / ivec2(8, 128));
    }
    boxes[0] = groups.x;
    boxes[1] = groups.y;
    boxes[2] = int(views_n);
}

#ifndef VIEWS_GLSL
#define VIEWS_GLSL
// Per-view camera data as stored in the views buffer (same layout as the raster push
// constants in camera.glsl): object-to-camera pose, intrinsics, image size, near plane.

struct ViewData {
    mat4 object_to_camera;
    vec4 intrinsics;  // fx, fy, cx, cy
    vec2 size;        // width, height
    float near;
    uint first_triangle;
};

// Clip space of a camera-space point: x_clip = sx x + ox z, y_clip = sy y + oy z,
// z_clip = near (reverse-Z, infinite far plane), w = z.
vec2 clip_scale(ViewData v) { return 2.0 * v.intrinsics.xy / v.size; }
vec2 clip_shift(ViewData v) { return 2.0 * v.intrinsics.zw / v.size - 1.0; }

vec4 view_camera_to_clip(ViewData v, vec3 c) {
    return vec4(clip_scale(v) * c.xy + clip_shift(v) * c.z, v.near, c.z);
}

#endif  // VIEWS_GLSL

// Object-to-camera pose and OpenCV pinhole projection, shared by the raster shaders.
// Clip space is reverse-Z with an infinite far plane: z_clip = near, w = z_camera, so
// z_ndc = near / z_camera (1 at the near plane, towards 0 far away) and anything with
// z_camera < near is clipped by the fixed-function clipper.

layout(push_constant, std430) uniform View {
    mat4 object_to_camera;  // column-major [R | t]
    vec4 intrinsics;        // fx, fy, cx, cy in pixels
    vec2 size;              // width, height in pixels
    float near;             // metres
    uint first_triangle;    // id of the first triangle of this draw (chunked draws)
} view;

vec3 to_camera(vec3 p) {
    return (view.object_to_camera * vec4(p, 1.0)).xyz;
}

// Pixel u = fx x / z + cx maps to NDC 2 u / width - 1 (Vulkan NDC: y down, like OpenCV).
vec4 camera_to_clip(vec3 c) {
    vec2 scale = 2.0 * view.intrinsics.xy / view.size;
    vec2 shift = 2.0 * view.intrinsics.zw / view.size - 1.0;
    return vec4(scale * c.xy + shift * c.z, view.near, c.z);
}

// NDC of the pixel centre under gl_FragCoord (pixel (i, j) has its centre at (j + 0.5, i + 0.5)).
vec2 fragment_ndc(vec4 frag_coord) {
    return 2.0 * frag_coord.xy / view.size - 1.0;
}

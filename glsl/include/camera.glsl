// Push constants of the plain shaded render: one view (see views.glsl).
#include "views.glsl"

layout(push_constant, std430) uniform Constants { ViewData view; } pc;

vec3 to_camera(vec3 p) {
    return (pc.view.object_to_camera * vec4(p, 1.0)).xyz;
}

vec4 camera_to_clip(vec3 c) {
    return view_camera_to_clip(pc.view, c);
}

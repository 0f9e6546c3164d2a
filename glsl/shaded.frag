#version 460
// Plain colour render, fragment stage: Lambert shading of the face normal with one light
// at the camera.
#include "camera.glsl"

layout(location = 0) in vec3 in_camera;
layout(location = 0) out vec4 out_colour;

void main() {
    vec3 n = normalize(cross(dFdx(in_camera), dFdy(in_camera)));
    vec3 to_light = normalize(-in_camera);
    float lambert = abs(dot(n, to_light));
    vec3 albedo = vec3(0.80, 0.62, 0.35);
    out_colour = vec4(albedo * (0.15 + 0.85 * lambert), 1.0);
}

#ifndef ROTATION_GLSL
#define ROTATION_GLSL
// Rotations as rotation vectors (axis times angle, radians), shared by the optimisers.

// [w]x: skew(w) v = cross(w, v).
mat3 skew(vec3 w) { return mat3(0.0, w.z, -w.y, -w.z, 0.0, w.x, w.y, -w.x, 0.0); }

// exp([w]x), Rodrigues' formula; below 1e-6 rad its first order, I + [w]x (the second
// order is below float32's resolution there).
mat3 rodrigues(vec3 w) {
    float angle = length(w);
    if (angle < 1e-6) return mat3(1.0) + skew(w);
    mat3 k = skew(w / angle);
    return mat3(1.0) + sin(angle) * k + (1.0 - cos(angle)) * k * k;
}

#endif  // ROTATION_GLSL

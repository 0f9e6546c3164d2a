#version 460
// G-buffer pass writing triangle ids only, fragment stage: triangle id + 1 from the
// primitive's index in the draw (one indexed draw of the whole mesh).
layout(location = 0) out uint out_id;

void main() {
    out_id = uint(gl_PrimitiveID) + 1u;
}

#version 460
// G-buffer pass writing triangle ids only, fragment stage: triangle id + 1, the flat
// attribute of the triangle's provoking vertex (see gbuffer_indexed.vert).
layout(location = 0) flat in uint in_id;
layout(location = 0) out uint out_id;

void main() {
    out_id = in_id;
}

// G-buffer pass, fragment stage (included by gbuffer.frag and gbuffer_depth.frag): writes
// triangle id + 1 and the perspective-correct barycentrics of the pixel centre (weights of
// corners 0 and 1; corner 2 has 1 - u - v) as interpolated by the rasterizer. With
// WRITE_DEPTH it also writes camera-space z = 1 / (interpolated 1 / w). (Ids alone come
// from an indexed draw: gbuffer_indexed.vert, gbuffer_indexed_ids.frag.)

layout(location = 0) flat in uint in_id;
layout(location = 1) in vec2 in_bary;

layout(location = 0) out uint out_id;
layout(location = 1) out vec2 out_bary;
#ifdef WRITE_DEPTH
layout(location = 2) out float out_depth;
#endif

void main() {
    out_id = in_id;
    out_bary = in_bary;
#ifdef WRITE_DEPTH
    out_depth = 1.0 / gl_FragCoord.w;
#endif
}

// Jump flooding (Rong & Tan 2006, with two extra passes of steps 2 and 1) for the signed
// distance field of an observed mask. Seeds are packed pixel coordinates x | y << 16;
// NO_SEED marks none. Set 0 floods from mask pixels, set 1 from background pixels;
// z = 2 view + set.

layout(local_size_x = 8, local_size_y = 8) in;

const uint NO_SEED = 0xffffffffu;

layout(push_constant, std430) uniform Constants {
    uint width;
    uint height;
    int step;
} pc;

uint pack_pixel(ivec2 p) { return uint(p.x) | (uint(p.y) << 16); }
ivec2 unpack_pixel(uint s) { return ivec2(int(s & 0xffffu), int(s >> 16)); }

uint plane_index(ivec2 p, uint plane) { return (plane * pc.height + uint(p.y)) * pc.width + uint(p.x); }

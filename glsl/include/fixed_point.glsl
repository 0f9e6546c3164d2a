#ifndef FIXED_POINT_GLSL
#define FIXED_POINT_GLSL
// Deterministic sums. Float atomics add in whatever order threads arrive, so their
// results differ from run to run in the last bits (and an optimiser amplifies those).
// Sums that many threads add to are kept as int64 fixed point instead: integer addition
// is associative, so the order cannot matter. The scale 2^shift is chosen from the data:
// the largest term's magnitude (found with atomicMax over the float bits, which is
// order-free too) or a bound on it (the differentiable renderer's backward), and the
// most terms one sum can take, so that no sum can pass 2^62; the resolution is then
// 2^-(62 - headroom) of the largest term or of the bound (about 4e-12 of it with 2^24
// terms), far below float32's even where the bound is a few thousand times the largest
// term.
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#extension GL_EXT_shader_atomic_int64 : require

// The float bits of |x|: for non-negative floats the unsigned order of the bits is the
// order of the values, so atomicMax over them finds the largest magnitude (and NaN or Inf
// come out above every finite value).
uint magnitude_bits(float x) { return floatBitsToUint(abs(x)); }

// Bits at or above this mark a non-finite term.
const uint NON_FINITE_BITS = 0x7f800000u;

// The shift for terms no larger than uintBitsToFloat(max_bits), in sums of at most
// `terms` terms.
int fixed_shift(uint max_bits, uint terms) {
    int exponent = int((max_bits >> 23u) & 0xffu) - 126;  // max |term| < 2^exponent
    int headroom = findMSB(max(terms, 1u)) + 1;           // terms <= 2^headroom
    return 62 - headroom - exponent;
}

int64_t to_fixed(float x, int shift) { return int64_t(ldexp(x, shift)); }

float from_fixed(int64_t v, int shift) { return ldexp(float(v), -shift); }

// The shift of the backward's sums (antialias_backward.comp): at most `terms_per_listed`
// terms per listed pixel, `listed` of them (and one pixel's worth of room).
int listed_shift(uint max_bits, uint terms_per_listed, uint listed) {
    return fixed_shift(max_bits, terms_per_listed * listed + terms_per_listed);
}

// The bits to resolve sums with whose scale came from a bound (bound_bits) on terms that
// turned out at most seen_bits: the bound's, or NON_FINITE_BITS (so NaN) when a term came
// above it (it was not finite, or the bound failed and a sum may have wrapped).
uint checked_bits(uint bound_bits, uint seen_bits) {
    return seen_bits > bound_bits ? NON_FINITE_BITS : bound_bits;
}

// A fixed-point sum as a float; NaN when a term was not finite (max_bits at or above
// NON_FINITE_BITS), so that callers still see it.
float resolved(int64_t v, uint max_bits, int shift) {
    return max_bits >= NON_FINITE_BITS ? uintBitsToFloat(0x7fc00000u) : from_fixed(v, shift);
}

#endif  // FIXED_POINT_GLSL

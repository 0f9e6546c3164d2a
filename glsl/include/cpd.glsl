// Coherent Point Drift (Myronenko & Song 2010), E-step without the M x N matrix:
//   P_mn = exp(-|x_n - t_m|^2 / (2 s2)) / (sum_k exp(-|x_n - t_k|^2 / (2 s2)) + c),
//   c = (2 pi s2)^(D/2) w / (1 - w) M / N.
// Denominators are kept as logarithms (log-sum-exp), so far points and collapsing s2
// never divide 0 by 0. Points are vec4 (x, y, z, unused).
//
// Every pass loops over points of the other set (gauss_product over all of them, the
// E-step passes over those near their own, see below). Each subgroup loads one point per
// lane and passes them around with subgroupShuffle: on a CPU driver a buffer load at an
// index the compiler cannot prove uniform is gathered lane by lane (6x slower on
// lavapipe); on a GPU it is one broadcast load either way. So no invocation may return
// early: every lane takes part in the shuffles. Each invocation serves ROWS points of its
// own set (gauss_product: a grid-stride apart; the E-step: 64 apart in a workgroup's
// consecutive block), so that each point passed serves ROWS pairs (on
// lavapipe, 4 rows ran 3x faster than 1; 8 rows another 1.2x at 2000 points, seven
// interleaved runs of `vkdr cpd`, whole process 0.64 -> 0.52 s median; 16 no faster. A GPU
// keeps 8 x 64 points per workgroup busy from a few thousand points up).
//
// One dispatch loops over one span [first, end) of the other set (the E-step: one piece
// of each workgroup's ranges), and the host runs a dispatch per span, in order, each carrying on from the last one's partial sums. That
// bounds the loop iterations of one invocation, which lavapipe needs: llvmpipe stops every
// shader invocation's loops, silently, after 65535 iterations all loops together
// (LP_MAX_TGSI_LOOP_ITERATIONS in Mesa's gallivm), and a single loop over 4e4 points
// summed less than a third of them. The span is `SPAN` in src/cpd/mod.rs (the E-step
// passes split each workgroup's ranges into pieces of about SPAN points, one per dispatch).
#extension GL_KHR_shader_subgroup_shuffle : require

layout(local_size_x = 64) in;

layout(push_constant, std430) uniform Constants {
    uint m;                // moving (source) points
    uint n;                // target points
    uint first;            // gauss_product: this dispatch's span of the other set,
    uint end;              // [first, end)
    float inv_two_sigma2;  // 1 / (2 s2)
    float log_c;           // log of the outlier term c
    uint piece;            // E-step: this dispatch's piece of each workgroup's ranges,
    uint pieces;           // of `pieces` (the first starts the sums, the last ends them)
} pc;

const uint ROWS = 8u;

// The r-th point of this invocation's own set (gauss_product).
uint row(uint r) {
    return gl_GlobalInvocationID.x + r * gl_NumWorkGroups.x * gl_WorkGroupSize.x;
}

// The E-step passes visit, per workgroup, only the other set's points near its own: both
// sets are sorted into cells of a grid (Morton order, src/cpd/neighbours.rs, `plan`),
// a workgroup serves ROWS x 64 consecutive own points, and loops over the ranges of other
// points in the cells next to theirs, where every term that is not negligible lies (the
// cell is wider than the distance at which a term drops below 2^-24 of the outlier term
// c over all points). With a coarse grid the one range is the whole other set.
// ranges[piece * groups + group] = (offset, count) of this piece's ranges, which are
// ranges[offset ..< offset + count], each (first, end) in the other set's sorted order.
#ifdef ESTEP
layout(set = 0, binding = 4, std430) readonly buffer Ranges { uvec2 ranges[]; };

uint own_row(uint r) {
    return gl_WorkGroupID.x * (ROWS * 64u) + r * 64u + gl_LocalInvocationIndex;
}

uvec2 own_piece() {
    return ranges[pc.piece * gl_NumWorkGroups.x + gl_WorkGroupID.x];
}
#endif  // ESTEP

// Coherent Point Drift (Myronenko & Song 2010), E-step without the M x N matrix:
//   P_mn = exp(-|x_n - t_m|^2 / (2 s2)) / (sum_k exp(-|x_n - t_k|^2 / (2 s2)) + c),
//   c = (2 pi s2)^(D/2) w / (1 - w) M / N.
// Denominators are kept as logarithms (log-sum-exp), so far points and collapsing s2
// never divide 0 by 0. Points are vec4 (x, y, z, unused).
//
// Every pass loops over all points of the other set. Each subgroup loads one point per
// lane and passes them around with subgroupShuffle: on a CPU driver a buffer load at an
// index the compiler cannot prove uniform is gathered lane by lane (6x slower on
// lavapipe); on a GPU it is one broadcast load either way. So no invocation may return
// early: every lane takes part in the shuffles. Each invocation serves ROWS points of its
// own set (a grid-stride apart), so that each point passed serves ROWS pairs (on
// lavapipe, 4 rows ran 3x faster than 1; 8 rows another 1.2x at 2000 points, seven
// interleaved runs of `vkdr cpd`, whole process 0.64 -> 0.52 s median; 16 no faster. A GPU
// keeps 8 x 64 points per workgroup busy from a few thousand points up).
//
// One dispatch loops over one span [first, end) of the other set, and the host runs a
// dispatch per span, in order, each carrying on from the last one's partial sums. That
// bounds the loop iterations of one invocation, which lavapipe needs: llvmpipe stops every
// shader invocation's loops, silently, after 65535 iterations all loops together
// (LP_MAX_TGSI_LOOP_ITERATIONS in Mesa's gallivm), and a single loop over 4e4 points
// summed less than a third of them. The span is `SPAN` in src/cpd/mod.rs.
#extension GL_KHR_shader_subgroup_shuffle : require

layout(local_size_x = 64) in;

layout(push_constant, std430) uniform Constants {
    uint m;                // moving (source) points
    uint n;                // target points
    uint first;            // this dispatch's span of the other set: [first, end)
    uint end;
    float inv_two_sigma2;  // 1 / (2 s2)
    float log_c;           // log of the outlier term c
} pc;

const uint ROWS = 8u;

// The r-th point of this invocation's own set.
uint row(uint r) {
    return gl_GlobalInvocationID.x + r * gl_NumWorkGroups.x * gl_WorkGroupSize.x;
}

// Coherent Point Drift (Myronenko & Song 2010), E-step without the M x N matrix:
//   P_mn = exp(-|x_n - t_m|^2 / (2 s2)) / (sum_k exp(-|x_n - t_k|^2 / (2 s2)) + c),
//   c = (2 pi s2)^(D/2) w / (1 - w) M / N.
// Denominators are kept as logarithms (log-sum-exp), so far points and collapsing s2
// never divide 0 by 0. Points are vec4 (x, y, z, unused).

layout(local_size_x = 64) in;

layout(push_constant, std430) uniform Constants {
    uint m;                // moving (source) points
    uint n;                // target points
    float inv_two_sigma2;  // 1 / (2 s2)
    float log_c;           // log of the outlier term c
} pc;

#pragma once
// Per-Gaussian colour and distance of the render, written once for the CPU and CUDA shading kernels:
// colour = SH(view direction) + 0.5 clamped at 0 (3DGS, real SH up to degree 3), and the distance from the
// camera centre that the paper's depth (eq. depth_render) composites. Their readable reference is
// sh_to_color (spherical_harmonics.h) plus a norm, in ATen operations.
#include "gs_trainer/raster/raster_math.h"

namespace gaps::raster {

constexpr double kShBasisC0 = 0.28209479177387814;
constexpr double kShBasisC1 = 0.4886025119029199;
// Scalars, not arrays: constexpr arrays are not usable in CUDA device code.
constexpr double kShBasisC2_0 = 1.0925484305920792, kShBasisC2_1 = -1.0925484305920792,
                 kShBasisC2_2 = 0.31539156525252005, kShBasisC2_3 = -1.0925484305920792,
                 kShBasisC2_4 = 0.5462742152960396;
constexpr double kShBasisC3_0 = -0.5900435899266435, kShBasisC3_1 = 2.890611442640554,
                 kShBasisC3_2 = -0.4570457994644658, kShBasisC3_3 = 0.3731763325901154,
                 kShBasisC3_4 = -0.4570457994644658, kShBasisC3_5 = 1.445305721320277,
                 kShBasisC3_6 = -0.5900435899266435;
// Below this distance the view direction is the offset scaled by its inverse (as the reference's clamp).
constexpr double kMinViewDistance = 1e-12;

// The (degree + 1)^2 basis values at unit direction (x, y, z).
template <typename T>
GAPS_HD void sh_basis(int degree, T x, T y, T z, T b[16]) {
  b[0] = T(kShBasisC0);
  if (degree < 1) return;
  b[1] = -T(kShBasisC1) * y;
  b[2] = T(kShBasisC1) * z;
  b[3] = -T(kShBasisC1) * x;
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z;
  b[4] = T(kShBasisC2_0) * x * y;
  b[5] = T(kShBasisC2_1) * y * z;
  b[6] = T(kShBasisC2_2) * (2 * zz - xx - yy);
  b[7] = T(kShBasisC2_3) * x * z;
  b[8] = T(kShBasisC2_4) * (xx - yy);
  if (degree < 3) return;
  b[9] = T(kShBasisC3_0) * y * (3 * xx - yy);
  b[10] = T(kShBasisC3_1) * x * y * z;
  b[11] = T(kShBasisC3_2) * y * (4 * zz - xx - yy);
  b[12] = T(kShBasisC3_3) * z * (2 * zz - 3 * xx - 3 * yy);
  b[13] = T(kShBasisC3_4) * x * (4 * zz - xx - yy);
  b[14] = T(kShBasisC3_5) * z * (xx - yy);
  b[15] = T(kShBasisC3_6) * x * (xx - 3 * yy);
}

// d(sum_k gb[k] * b[k]) / d(x, y, z) for the basis of sh_basis.
template <typename T>
GAPS_HD void sh_basis_vjp(int degree, T x, T y, T z, const T gb[16], T g[3]) {
  g[0] = g[1] = g[2] = T(0);
  if (degree < 1) return;
  const T c1 = T(kShBasisC1);
  g[0] -= c1 * gb[3];
  g[1] -= c1 * gb[1];
  g[2] += c1 * gb[2];
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z;
  g[0] += T(kShBasisC2_0) * y * gb[4] - 2 * T(kShBasisC2_2) * x * gb[6] + T(kShBasisC2_3) * z * gb[7] +
          2 * T(kShBasisC2_4) * x * gb[8];
  g[1] += T(kShBasisC2_0) * x * gb[4] + T(kShBasisC2_1) * z * gb[5] - 2 * T(kShBasisC2_2) * y * gb[6] -
          2 * T(kShBasisC2_4) * y * gb[8];
  g[2] += T(kShBasisC2_1) * y * gb[5] + 4 * T(kShBasisC2_2) * z * gb[6] + T(kShBasisC2_3) * x * gb[7];
  if (degree < 3) return;
  const T k0 = T(kShBasisC3_0) * gb[9], k1 = T(kShBasisC3_1) * gb[10], k2 = T(kShBasisC3_2) * gb[11],
          k3 = T(kShBasisC3_3) * gb[12], k4 = T(kShBasisC3_4) * gb[13], k5 = T(kShBasisC3_5) * gb[14],
          k6 = T(kShBasisC3_6) * gb[15];
  g[0] += k0 * 6 * x * y + k1 * y * z - k2 * 2 * x * y - k3 * 6 * x * z + k4 * (4 * zz - 3 * xx - yy) + k5 * 2 * x * z +
          k6 * 3 * (xx - yy);
  g[1] += k0 * 3 * (xx - yy) + k1 * x * z + k2 * (4 * zz - xx - 3 * yy) - k3 * 6 * y * z - k4 * 2 * x * y -
          k5 * 2 * y * z - k6 * 6 * x * y;
  g[2] += k1 * x * y + k2 * 8 * y * z + k3 * (6 * zz - 3 * xx - 3 * yy) + k4 * 8 * x * z + k5 * (xx - yy);
}

// The view offset mean - centre, its length and the unit direction.
template <typename T>
struct ViewRay {
  T o[3];
  T dist;
  T inv;  // 1 / max(dist, kMinViewDistance)
};

template <typename T>
GAPS_HD ViewRay<T> view_ray(const T mean[3], const T centre[3]) {
  ViewRay<T> r;
  for (int k = 0; k < 3; ++k) r.o[k] = mean[k] - centre[k];
  r.dist = sqrt(r.o[0] * r.o[0] + r.o[1] * r.o[1] + r.o[2] * r.o[2]);
  r.inv = T(1) / (r.dist > T(kMinViewDistance) ? r.dist : T(kMinViewDistance));
  return r;
}

// out[0..2] = max(SH colour + 0.5, 0), out[3] = distance. `rest` holds the coefficients of degree >= 1
// (rest_count x 3, the first (degree + 1)^2 - 1 used).
template <typename T>
GAPS_HD void shade_one(int degree, const T mean[3], const T centre[3], const T dc[3], const T* rest, T out[4]) {
  const ViewRay<T> r = view_ray(mean, centre);
  T b[16];
  sh_basis(degree, r.o[0] * r.inv, r.o[1] * r.inv, r.o[2] * r.inv, b);
  const int count = (degree + 1) * (degree + 1);
  for (int c = 0; c < 3; ++c) {
    T v = b[0] * dc[c];
    for (int k = 1; k < count; ++k) v += b[k] * rest[3 * (k - 1) + c];
    v += T(0.5);
    out[c] = v < T(0) ? T(0) : v;
  }
  out[3] = r.dist;
}

// Gradients of shade_one given dL/dout (4 values); g_rest gets (degree + 1)^2 - 1 rows, the rest untouched.
template <typename T>
GAPS_HD void shade_one_vjp(int degree, const T mean[3], const T centre[3], const T dc[3], const T* rest,
                           const T g_out[4], T g_mean[3], T g_dc[3], T* g_rest) {
  const ViewRay<T> r = view_ray(mean, centre);
  const T dir[3] = {r.o[0] * r.inv, r.o[1] * r.inv, r.o[2] * r.inv};
  T b[16];
  sh_basis(degree, dir[0], dir[1], dir[2], b);
  const int count = (degree + 1) * (degree + 1);
  T gc[3];
  for (int c = 0; c < 3; ++c) {
    T v = b[0] * dc[c];
    for (int k = 1; k < count; ++k) v += b[k] * rest[3 * (k - 1) + c];
    gc[c] = v + T(0.5) >= T(0) ? g_out[c] : T(0);  // the clamp passes the gradient where not clipped
  }
  T gb[16];
  for (int k = 0; k < count; ++k) {
    const T* coef = k == 0 ? dc : rest + 3 * (k - 1);
    gb[k] = coef[0] * gc[0] + coef[1] * gc[1] + coef[2] * gc[2];
  }
  for (int c = 0; c < 3; ++c) g_dc[c] = b[0] * gc[c];
  for (int k = 1; k < count; ++k)
    for (int c = 0; c < 3; ++c) g_rest[3 * (k - 1) + c] = b[k] * gc[c];
  T g_dir[3];
  sh_basis_vjp(degree, dir[0], dir[1], dir[2], gb, g_dir);
  // Through the normalisation dir = o / |o| (or o / kMinViewDistance below it), then the distance |o|.
  const bool normalised = r.dist > T(kMinViewDistance);
  const T along = normalised ? dir[0] * g_dir[0] + dir[1] * g_dir[1] + dir[2] * g_dir[2] : T(0);
  const T g_dist = r.dist > T(0) ? g_out[3] / r.dist : T(0);
  for (int k = 0; k < 3; ++k) g_mean[k] = (g_dir[k] - dir[k] * along) * r.inv + r.o[k] * g_dist;
}

}  // namespace gaps::raster

#pragma once
// SSIM of 3DGS (11x11 Gaussian window, sigma 1.5, zero padding, C1 = 0.01^2, C2 = 0.03^2) as two separable
// passes per direction, written once for the CPU and CUDA implementations. Images are H x W x C, row-major.
//
// Forward: the five local moments (mu_x, mu_y, E[x^2], E[y^2], E[xy]) are blurred horizontally into an
// H x W x C x 5 buffer, then vertically, and turned into the map value S and its partial derivatives
// (dS/dmu_x, dS/dE[x^2], dS/dE[xy]), stored H x W x C x 3. Backward: for dL/dS = g, the prediction gets
//   dL/dx_p = blur(g dS/dmu_x)_p + 2 x_p blur(g dS/dE[x^2])_p + y_p blur(g dS/dE[xy])_p,
// the window being symmetric (zero-padded correlation is its own adjoint).
#include <cmath>

#include "gs_trainer/raster/raster_math.h"

namespace gaps::ssim {

constexpr int kWindow = 11;
constexpr int kRadius = kWindow / 2;
constexpr double kSigma = 1.5;
constexpr double kC1 = 0.01 * 0.01;
constexpr double kC2 = 0.03 * 0.03;
constexpr int kMoments = 5;
constexpr int kPartials = 3;

template <typename T>
struct Window {
  T w[kWindow];
};

// The normalised 1-D Gaussian (the 2-D window is its outer product).
template <typename T>
Window<T> gaussian_window() {
  double g[kWindow], sum = 0;
  for (int i = 0; i < kWindow; ++i)
    sum += g[i] = std::exp(-double((i - kRadius) * (i - kRadius)) / (2 * kSigma * kSigma));
  Window<T> out;
  for (int i = 0; i < kWindow; ++i) out.w[i] = T(g[i] / sum);
  return out;
}

struct Shape {
  int height, width, channels;
};

// Horizontal pass of the five moments at (y, x, c).
template <typename T>
GAPS_HD void horizontal_moments(const T* pred, const T* gt, const Shape& s, const Window<T>& win, int y, int x, int c,
                                T out[kMoments]) {
  for (int k = 0; k < kMoments; ++k) out[k] = T(0);
  for (int t = 0; t < kWindow; ++t) {
    const int xx = x + t - kRadius;
    if (xx < 0 || xx >= s.width) continue;
    const int64_t i = (int64_t(y) * s.width + xx) * s.channels + c;
    const T a = pred[i], b = gt[i], w = win.w[t];
    out[0] += w * a;
    out[1] += w * b;
    out[2] += w * (a * a);
    out[3] += w * (b * b);
    out[4] += w * (a * b);
  }
}

// Vertical pass of `count` interleaved channels of `rows` (H x W x C x count) at (y, x, c).
template <typename T, int count>
GAPS_HD void vertical_pass(const T* rows, const Shape& s, const Window<T>& win, int y, int x, int c, T out[count]) {
  for (int k = 0; k < count; ++k) out[k] = T(0);
  for (int t = 0; t < kWindow; ++t) {
    const int yy = y + t - kRadius;
    if (yy < 0 || yy >= s.height) continue;
    const T* r = rows + ((int64_t(yy) * s.width + x) * s.channels + c) * count;
    for (int k = 0; k < count; ++k) out[k] += win.w[t] * r[k];
  }
}

// S and (dS/dmu_x, dS/dE[x^2], dS/dE[xy]) from the blurred moments.
template <typename T>
GAPS_HD T ssim_value_and_partials(const T m[kMoments], T partials[kPartials]) {
  const T mu_x = m[0], mu_y = m[1];
  const T mu_xx = mu_x * mu_x, mu_yy = mu_y * mu_y, mu_xy = mu_x * mu_y;
  const T var_x = m[2] - mu_xx, var_y = m[3] - mu_yy, cov = m[4] - mu_xy;
  const T n1 = 2 * mu_xy + T(kC1), n2 = 2 * cov + T(kC2);
  const T d1 = mu_xx + mu_yy + T(kC1), d2 = var_x + var_y + T(kC2);
  const T s = (n1 * n2) / (d1 * d2);
  const T inv_d = T(1) / (d1 * d2);
  partials[0] = 2 * mu_y * (n2 - n1) * inv_d - 2 * mu_x * s / d1 + 2 * mu_x * s / d2;
  partials[1] = -s / d2;
  partials[2] = 2 * n1 * inv_d;
  return s;
}

// dL/dS read from an H x W x C array.
template <typename T>
struct MapGradientArray {
  const T* g;
  GAPS_HD T operator()(int64_t i) const { return g[i]; }
};

// Horizontal pass of g * partials at (y, x, c); g_map(i) gives dL/dS at element i (MapGradientArray, or a rule
// that forms it on the fly).
template <typename T, typename MapGradient>
GAPS_HD void horizontal_gradient(const T* partials, const MapGradient& g_map, const Shape& s, const Window<T>& win,
                                 int y, int x, int c, T out[kPartials]) {
  for (int k = 0; k < kPartials; ++k) out[k] = T(0);
  for (int t = 0; t < kWindow; ++t) {
    const int xx = x + t - kRadius;
    if (xx < 0 || xx >= s.width) continue;
    const int64_t i = (int64_t(y) * s.width + xx) * s.channels + c;
    const T wg = win.w[t] * g_map(i);
    for (int k = 0; k < kPartials; ++k) out[k] += wg * partials[i * kPartials + k];
  }
}

// dL/dx at (y, x, c) from the vertically blurred products.
template <typename T>
GAPS_HD T prediction_gradient(const T blurred[kPartials], T x, T y) {
  return blurred[0] + 2 * x * blurred[1] + y * blurred[2];
}

}  // namespace gaps::ssim

#pragma once
// Per-Gaussian and per-pixel maths of the rasterizer, written once for the CPU and CUDA paths so both
// implement the same contract. Scalar type T is float for training and double for gradient checks.
//
// Conventions: pixel (i, j) has its centre at (i + 0.5, j + 0.5); a Gaussian's 2D covariance is dilated
// by kLowPass on the diagonal (the EWA low-pass filter of 3DGS); conics are the inverse 2D covariance
// stored as (a, b, c) = [[a, b], [b, c]]; quaternions are (w, x, y, z), normalised inside.
#include <cmath>
#include <cstdint>

#if defined(__CUDACC__)
#define GAPS_HD __host__ __device__ __forceinline__
#else
#define GAPS_HD inline
#endif

namespace gaps::raster {

constexpr int kTileSize = 16;
constexpr double kLowPass = 0.3;
constexpr double kNearPlane = 0.2;          // Gaussians closer than this (camera z) are culled
constexpr double kMaxAlpha = 0.99;          // per-Gaussian alpha clamp
constexpr double kMinAlpha = 1.0 / 255.0;   // contributions below this are skipped
constexpr double kMinTransmittance = 1e-4;  // compositing stops before T falls below this
constexpr double kFrustumSlack = 0.3;       // projected means are clamped this far (in image widths) outside

template <typename T>
struct Vec2 {
  T x, y;
};
template <typename T>
struct Vec3 {
  T x, y, z;
};
template <typename T>
struct Mat3 {
  T m[3][3];
  GAPS_HD T operator()(int r, int c) const { return m[r][c]; }
  GAPS_HD T& operator()(int r, int c) { return m[r][c]; }
};
// Symmetric 2x2 as (a, b, c) = [[a, b], [b, c]].
template <typename T>
struct Sym2 {
  T a, b, c;
};

template <typename T>
GAPS_HD Mat3<T> matmul(const Mat3<T>& A, const Mat3<T>& B) {
  Mat3<T> C;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) C(i, j) = A(i, 0) * B(0, j) + A(i, 1) * B(1, j) + A(i, 2) * B(2, j);
  return C;
}
template <typename T>
GAPS_HD Mat3<T> transpose(const Mat3<T>& A) {
  Mat3<T> C;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) C(i, j) = A(j, i);
  return C;
}

template <typename T>
GAPS_HD Mat3<T> quat_to_rotmat(T w, T x, T y, T z) {
  Mat3<T> R;
  R(0, 0) = 1 - 2 * (y * y + z * z);
  R(0, 1) = 2 * (x * y - w * z);
  R(0, 2) = 2 * (x * z + w * y);
  R(1, 0) = 2 * (x * y + w * z);
  R(1, 1) = 1 - 2 * (x * x + z * z);
  R(1, 2) = 2 * (y * z - w * x);
  R(2, 0) = 2 * (x * z - w * y);
  R(2, 1) = 2 * (y * z + w * x);
  R(2, 2) = 1 - 2 * (x * x + y * y);
  return R;
}

// dL/d(w,x,y,z) of a *unit* quaternion from dL/dR.
template <typename T>
GAPS_HD void quat_to_rotmat_vjp(T w, T x, T y, T z, const Mat3<T>& G, T out[4]) {
  out[0] = 2 * (-z * G(0, 1) + y * G(0, 2) + z * G(1, 0) - x * G(1, 2) - y * G(2, 0) + x * G(2, 1));
  out[1] = 2 * (y * G(0, 1) + z * G(0, 2) + y * G(1, 0) - 2 * x * G(1, 1) - w * G(1, 2) + z * G(2, 0) + w * G(2, 1) -
                2 * x * G(2, 2));
  out[2] = 2 * (-2 * y * G(0, 0) + x * G(0, 1) + w * G(0, 2) + x * G(1, 0) + z * G(1, 2) - w * G(2, 0) + z * G(2, 1) -
                2 * y * G(2, 2));
  out[3] = 2 * (-2 * z * G(0, 0) - w * G(0, 1) + x * G(0, 2) + w * G(1, 0) - 2 * z * G(1, 1) + y * G(1, 2) +
                x * G(2, 0) + y * G(2, 1));
}

struct Intrinsics {
  double fx, fy, cx, cy;
  int width, height;
};

// Everything the forward projection of one Gaussian produces.
template <typename T>
struct Projected {
  bool visible;
  Vec2<T> mean2d;
  Sym2<T> conic;
  T depth;  // camera-space z, the sort key
  int radius;
};

// The state the backward pass recomputes instead of storing.
template <typename T>
struct ProjectionCache {
  Vec3<T> p;  // camera-space mean
  Vec2<T> u;  // clamped x/z, y/z used by the Jacobian
  bool clamped_x, clamped_y;
  Mat3<T> R;  // rotation of the (normalised) quaternion
  Vec3<T> s;  // scales
  T qn[4];    // normalised quaternion
  T qnorm;
  Mat3<T> Sigma;  // 3D covariance
  T J[2][3];
  T Tm[2][3];     // J * W
  Sym2<T> cov2d;  // dilated
};

template <typename T>
GAPS_HD bool project_one(const T mean[3], const T quat[4], const T scale[3], const Mat3<T>& W, const T tvec[3],
                         const Intrinsics& K, ProjectionCache<T>& c) {
  c.p.x = W(0, 0) * mean[0] + W(0, 1) * mean[1] + W(0, 2) * mean[2] + tvec[0];
  c.p.y = W(1, 0) * mean[0] + W(1, 1) * mean[1] + W(1, 2) * mean[2] + tvec[1];
  c.p.z = W(2, 0) * mean[0] + W(2, 1) * mean[1] + W(2, 2) * mean[2] + tvec[2];
  if (!(c.p.z > T(kNearPlane))) return false;
  c.qnorm = sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]);
  if (!(c.qnorm > T(0))) return false;
  for (int k = 0; k < 4; ++k) c.qn[k] = quat[k] / c.qnorm;
  c.R = quat_to_rotmat(c.qn[0], c.qn[1], c.qn[2], c.qn[3]);
  c.s = {scale[0], scale[1], scale[2]};
  Mat3<T> M;
  for (int i = 0; i < 3; ++i) {
    M(i, 0) = c.R(i, 0) * c.s.x;
    M(i, 1) = c.R(i, 1) * c.s.y;
    M(i, 2) = c.R(i, 2) * c.s.z;
  }
  c.Sigma = matmul(M, transpose(M));

  // The Jacobian is evaluated at a mean clamped slightly outside the image, as in 3DGS, so that
  // Gaussians far off-screen do not get huge, unstable footprints.
  const T lim_x_pos = T((K.width - K.cx) / K.fx + kFrustumSlack * K.width / K.fx);
  const T lim_x_neg = T(K.cx / K.fx + kFrustumSlack * K.width / K.fx);
  const T lim_y_pos = T((K.height - K.cy) / K.fy + kFrustumSlack * K.height / K.fy);
  const T lim_y_neg = T(K.cy / K.fy + kFrustumSlack * K.height / K.fy);
  const T ux = c.p.x / c.p.z, uy = c.p.y / c.p.z;
  c.clamped_x = ux > lim_x_pos || ux < -lim_x_neg;
  c.clamped_y = uy > lim_y_pos || uy < -lim_y_neg;
  c.u.x = ux > lim_x_pos ? lim_x_pos : (ux < -lim_x_neg ? -lim_x_neg : ux);
  c.u.y = uy > lim_y_pos ? lim_y_pos : (uy < -lim_y_neg ? -lim_y_neg : uy);
  const T fx = T(K.fx), fy = T(K.fy), z = c.p.z;
  c.J[0][0] = fx / z;
  c.J[0][1] = 0;
  c.J[0][2] = -fx * c.u.x / z;
  c.J[1][0] = 0;
  c.J[1][1] = fy / z;
  c.J[1][2] = -fy * c.u.y / z;
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j) c.Tm[i][j] = c.J[i][0] * W(0, j) + c.J[i][1] * W(1, j) + c.J[i][2] * W(2, j);
  T TS[2][3];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      TS[i][j] = c.Tm[i][0] * c.Sigma(0, j) + c.Tm[i][1] * c.Sigma(1, j) + c.Tm[i][2] * c.Sigma(2, j);
  c.cov2d.a = TS[0][0] * c.Tm[0][0] + TS[0][1] * c.Tm[0][1] + TS[0][2] * c.Tm[0][2] + T(kLowPass);
  c.cov2d.b = TS[0][0] * c.Tm[1][0] + TS[0][1] * c.Tm[1][1] + TS[0][2] * c.Tm[1][2];
  c.cov2d.c = TS[1][0] * c.Tm[1][0] + TS[1][1] * c.Tm[1][1] + TS[1][2] * c.Tm[1][2] + T(kLowPass);
  return true;
}

template <typename T>
GAPS_HD Projected<T> finish_projection(const ProjectionCache<T>& c, const Intrinsics& K) {
  Projected<T> out{};
  out.visible = false;
  const T det = c.cov2d.a * c.cov2d.c - c.cov2d.b * c.cov2d.b;
  if (!(det > T(0))) return out;
  out.conic = {c.cov2d.c / det, -c.cov2d.b / det, c.cov2d.a / det};
  const T mid = T(0.5) * (c.cov2d.a + c.cov2d.c);
  const T disc = mid * mid - det;
  const T lambda1 = mid + sqrt(disc > T(0.1) ? disc : T(0.1));
  out.radius = static_cast<int>(ceil(3 * sqrt(lambda1)));
  out.mean2d = {T(K.fx) * c.p.x / c.p.z + T(K.cx), T(K.fy) * c.p.y / c.p.z + T(K.cy)};
  out.depth = c.p.z;
  // Cull footprints that touch no tile of the image.
  const T r = T(out.radius);
  if (out.mean2d.x + r <= 0 || out.mean2d.x - r >= K.width || out.mean2d.y + r <= 0 || out.mean2d.y - r >= K.height)
    return out;
  out.visible = true;
  return out;
}

// Backward of the projection: from dL/d(mean2d, conic) to dL/d(mean, quat, scale).
template <typename T>
GAPS_HD void project_one_vjp(const ProjectionCache<T>& c, const Mat3<T>& W, const Intrinsics& K,
                             const Vec2<T>& g_mean2d, const Sym2<T>& g_conic, T g_mean[3], T g_quat[4], T g_scale[3]) {
  const T A = c.cov2d.a, B = c.cov2d.b, C = c.cov2d.c;
  const T det = A * C - B * B, det2 = det * det;
  // conic = (C, -B, A) / det
  const T gA = g_conic.a * (-C * C / det2) + g_conic.b * (B * C / det2) + g_conic.c * (-B * B / det2);
  const T gB =
      g_conic.a * (2 * B * C / det2) + g_conic.b * (-(det + 2 * B * B) / det2) + g_conic.c * (2 * A * B / det2);
  const T gC = g_conic.a * (-B * B / det2) + g_conic.b * (A * B / det2) + g_conic.c * (-A * A / det2);
  // G2 is the symmetric matrix with tr(G2 dSigma2) = dL: the off-diagonal B appears twice.
  const T G2[2][2] = {{gA, gB / 2}, {gB / 2, gC}};

  // Sigma2 = Tm Sigma Tm^T:  dL/dSigma = Tm^T G2 Tm;  dL/dTm = 2 G2 Tm Sigma.
  T G2T[2][3];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j) G2T[i][j] = G2[i][0] * c.Tm[0][j] + G2[i][1] * c.Tm[1][j];
  Mat3<T> gSigma;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) gSigma(i, j) = c.Tm[0][i] * G2T[0][j] + c.Tm[1][i] * G2T[1][j];
  T gTm[2][3];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j)
      gTm[i][j] = 2 * (G2T[i][0] * c.Sigma(0, j) + G2T[i][1] * c.Sigma(1, j) + G2T[i][2] * c.Sigma(2, j));
  // Tm = J W:  dL/dJ = dL/dTm W^T.
  T gJ[2][3];
  for (int i = 0; i < 2; ++i)
    for (int j = 0; j < 3; ++j) gJ[i][j] = gTm[i][0] * W(j, 0) + gTm[i][1] * W(j, 1) + gTm[i][2] * W(j, 2);

  // J depends on z and on the clamped ratios u = x/z, y/z.
  const T fx = T(K.fx), fy = T(K.fy), z = c.p.z, z2 = z * z;
  T gp[3] = {0, 0, 0};
  gp[2] += -fx / z2 * gJ[0][0] - fy / z2 * gJ[1][1] + fx * c.u.x / z2 * gJ[0][2] + fy * c.u.y / z2 * gJ[1][2];
  const T gux = -fx / z * gJ[0][2], guy = -fy / z * gJ[1][2];
  if (!c.clamped_x) {
    gp[0] += gux / z;
    gp[2] += -gux * c.p.x / z2;
  }
  if (!c.clamped_y) {
    gp[1] += guy / z;
    gp[2] += -guy * c.p.y / z2;
  }
  // mean2d = f * p.xy / z + c.
  gp[0] += g_mean2d.x * fx / z;
  gp[1] += g_mean2d.y * fy / z;
  gp[2] += -g_mean2d.x * fx * c.p.x / z2 - g_mean2d.y * fy * c.p.y / z2;
  for (int j = 0; j < 3; ++j) g_mean[j] = W(0, j) * gp[0] + W(1, j) * gp[1] + W(2, j) * gp[2];

  // Sigma = M M^T with M = R diag(s):  dL/dM = 2 gSigma M  (gSigma symmetric).
  Mat3<T> M, gM, gR;
  for (int i = 0; i < 3; ++i) {
    M(i, 0) = c.R(i, 0) * c.s.x;
    M(i, 1) = c.R(i, 1) * c.s.y;
    M(i, 2) = c.R(i, 2) * c.s.z;
  }
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      gM(i, j) = 2 * (gSigma(i, 0) * M(0, j) + gSigma(i, 1) * M(1, j) + gSigma(i, 2) * M(2, j));
  const T s[3] = {c.s.x, c.s.y, c.s.z};
  for (int j = 0; j < 3; ++j) {
    g_scale[j] = c.R(0, j) * gM(0, j) + c.R(1, j) * gM(1, j) + c.R(2, j) * gM(2, j);
    for (int i = 0; i < 3; ++i) gR(i, j) = gM(i, j) * s[j];
  }
  T g_qn[4];
  quat_to_rotmat_vjp(c.qn[0], c.qn[1], c.qn[2], c.qn[3], gR, g_qn);
  // Through the normalisation q / |q|.
  const T dot = g_qn[0] * c.qn[0] + g_qn[1] * c.qn[1] + g_qn[2] * c.qn[2] + g_qn[3] * c.qn[3];
  for (int k = 0; k < 4; ++k) g_quat[k] = (g_qn[k] - c.qn[k] * dot) / c.qnorm;
}

struct TileRect {
  int x0, y0, x1, y1;  // [x0, x1) x [y0, y1) in tiles
};

// Whether a Gaussian of this opacity can reach alpha >= kMinAlpha anywhere (with the rounding slack of 1e-6).
GAPS_HD bool can_reach_min_alpha(double opacity) { return opacity * 255.0 >= 1.0 - 1e-6; }

// The ellipse a dx^2 + 2 b dx dy + c dy^2 <= r2 around the mean (conic (a, b, c)) outside which
// opacity * exp(power) < kMinAlpha, where eval_alpha skips the Gaussian. r2 carries 1e-3 relative plus
// 1e-4 absolute slack so that every pixel whose alpha could round over the threshold lies inside. Only a
// positive definite conic bounds it; otherwise the 3-sigma square is all there is.
struct AlphaEllipse {
  double a, b, c, det, r2;
  GAPS_HD bool bounded() const { return det > 0 && a > 0; }
  GAPS_HD double x_reach() const { return sqrt(r2 * c / det); }  // half its width
  GAPS_HD double y_reach() const { return sqrt(r2 * a / det); }  // half its height
};

template <typename T>
GAPS_HD AlphaEllipse alpha_ellipse(const Sym2<T>& conic, double opacity) {
  const double a = conic.a, b = conic.b, c = conic.c;
  const double l = log(255.0 * opacity);
  return {a, b, c, a * c - b * b, (l > 0 ? 2.0 * l : 0.0) * (1.0 + 1e-3) + 1e-4};
}

// The tiles a Gaussian is listed in, worked out once per Gaussian: a box of tiles, and the ellipse that
// cuts each of its rows down to a span (tile_row_span).
struct TileFootprint {
  TileRect rect;
  double mx, my;  // the mean
  AlphaEllipse ellipse;
};

// The box is the Gaussian's 3-sigma square (`radius`), cut down to the bounding box of its AlphaEllipse.
// The cut changes no image and no gradient, only how many (tile, Gaussian) pairs are sorted and walked: a
// Gaussian of opacity 0.01 (as after an opacity reset) reaches 1.4 sigma, not 3, and an elongated one only
// its own box. Half a pixel of widening on each side keeps the pixels whose centres lie within the ellipse.
// Computed in double on both backends so they list the same tiles.
template <typename T>
GAPS_HD TileFootprint tile_footprint(const Vec2<T>& mean2d, const Sym2<T>& conic, T opacity, int radius, int tiles_x,
                                     int tiles_y) {
  TileFootprint f{};
  const double op = static_cast<double>(opacity);
  if (!can_reach_min_alpha(op)) return f;
  f.mx = mean2d.x;
  f.my = mean2d.y;
  f.ellipse = alpha_ellipse(conic, op);
  double ex = radius, ey = radius;
  if (f.ellipse.bounded()) {
    const double bx = f.ellipse.x_reach() + 0.5, by = f.ellipse.y_reach() + 0.5;
    ex = bx < ex ? bx : ex;
    ey = by < ey ? by : ey;
  }
  const double ts = kTileSize;
  auto clamp_tile = [](double v, int hi) {
    const int t = static_cast<int>(v);
    return t < 0 ? 0 : (t > hi ? hi : t);
  };
  f.rect = {clamp_tile(floor((f.mx - ex) / ts), tiles_x), clamp_tile(floor((f.my - ey) / ts), tiles_y),
            clamp_tile(ceil((f.mx + ex) / ts), tiles_x), clamp_tile(ceil((f.my + ey) / ts), tiles_y)};
  return f;
}

// The ellipse's chord at height dy: dx in [(-b dy - w) / a, (-b dy + w) / a], w = sqrt(a r2 - det dy^2).
GAPS_HD double chord_end(const AlphaEllipse& e, double dy, double side) {
  const double w2 = e.a * e.r2 - e.det * dy * dy;
  return (-e.b * dy + side * sqrt(w2 > 0 ? w2 : 0.0)) / e.a;
}

struct TileSpan {
  int x0, x1;  // [x0, x1) in tiles
};

// The columns of tile row ty (within the footprint's rect) a Gaussian is listed in. A rotated, elongated
// ellipse touches far fewer tiles than its bounding box, and each pair it does not touch would cost a sort
// slot and a shared-memory stage plus a per-pixel test in both compositing passes; dropping those pairs
// changes no image and no gradient, since no pixel of theirs passes eval_alpha. The span is the x-extent
// of the ellipse over the row's band of pixel centres, band and extent widened by half a pixel as in
// tile_footprint: over a horizontal band the ellipse's x-extremes lie at the band's edges, or at its own
// leftmost/rightmost point where that point's height lies inside the band. A conic that bounds no ellipse
// keeps the rect's columns.
GAPS_HD TileSpan tile_row_span(const TileFootprint& f, int ty) {
  TileSpan s{f.rect.x0, f.rect.x1};
  const AlphaEllipse& e = f.ellipse;
  if (!e.bounded()) return s;
  const double ts = kTileSize, y_reach = e.y_reach();
  const double lo = fmax(ty * ts - f.my, -y_reach), hi = fmin((ty + 1) * ts - f.my, y_reach);
  if (!(lo <= hi)) return {s.x0, s.x0};
  const double x_reach = e.x_reach(), y_rightmost = -e.b * x_reach / e.c;  // the leftmost point is at -y_rightmost
  double left = fmin(chord_end(e, lo, -1), chord_end(e, hi, -1));
  double right = fmax(chord_end(e, lo, 1), chord_end(e, hi, 1));
  // Written so that a NaN height (an overflowing conic) counts as inside: the span then stays the rect's.
  if (!(-y_rightmost < lo || -y_rightmost > hi)) left = -x_reach;
  if (!(y_rightmost < lo || y_rightmost > hi)) right = x_reach;
  const double x0 = floor((f.mx + left - 0.5) / ts), x1 = ceil((f.mx + right + 0.5) / ts);
  if (x0 > s.x0) s.x0 = x0 < s.x1 ? static_cast<int>(x0) : s.x1;
  if (x1 < s.x1) s.x1 = x1 > s.x0 ? static_cast<int>(x1) : s.x0;
  return s;
}

// Calls body(tx, ty) for every tile a Gaussian is listed in, row by row (ty outer, tx inner): the order in
// which both backends emit their pairs.
template <typename Body>
GAPS_HD void for_each_footprint_tile(const TileFootprint& f, Body&& body) {
  for (int ty = f.rect.y0; ty < f.rect.y1; ++ty) {
    const TileSpan s = tile_row_span(f, ty);
    for (int tx = s.x0; tx < s.x1; ++tx) body(tx, ty);
  }
}

// How many tiles a Gaussian is listed in.
GAPS_HD int64_t footprint_tile_count(const TileFootprint& f) {
  int64_t count = 0;
  for (int ty = f.rect.y0; ty < f.rect.y1; ++ty) {
    const TileSpan s = tile_row_span(f, ty);
    count += s.x1 - s.x0;
  }
  return count;
}

// The exponent of a projected Gaussian at a pixel centre, and the offsets (dx, dy) = mean - pixel. One
// expression for every caller, so the CPU and CUDA paths round it alike: on the device every float
// operation is an explicitly rounded intrinsic, which nvcc never fuses into an FMA, so the alpha decisions
// taken from it match the CPU's even in kernels compiled with FMA contraction (the backward pass).
template <typename T>
GAPS_HD T gaussian_power(const Vec2<T>& mean2d, const Sym2<T>& conic, T px, T py, T& dx, T& dy) {
  dx = mean2d.x - px;
  dy = mean2d.y - py;
#ifdef __CUDA_ARCH__
  if constexpr (sizeof(T) == sizeof(float)) {
    const float quad = __fadd_rn(__fmul_rn(__fmul_rn(conic.a, dx), dx), __fmul_rn(__fmul_rn(conic.c, dy), dy));
    return __fsub_rn(__fmul_rn(-0.5f, quad), __fmul_rn(__fmul_rn(conic.b, dx), dy));
  }
#endif
  return -T(0.5) * (conic.a * dx * dx + conic.c * dy * dy) - conic.b * dx * dy;
}

// Opacity-weighted Gaussian value at a pixel centre; returns false when the Gaussian is skipped there.
template <typename T>
GAPS_HD bool eval_alpha(const Vec2<T>& mean2d, const Sym2<T>& conic, T opacity, T px, T py, T& alpha, T& gauss, T& dx,
                        T& dy) {
  const T power = gaussian_power(mean2d, conic, px, py, dx, dy);
  if (power > 0) return false;
  gauss = exp(power);
  const T a = opacity * gauss;
  alpha = a < T(kMaxAlpha) ? a : T(kMaxAlpha);
  return alpha >= T(kMinAlpha);
}

// Backward of eval_alpha: from dL/dalpha to dL/d(mean2d, conic, opacity). A clamped alpha has no gradient.
template <typename T>
GAPS_HD void eval_alpha_vjp(const Sym2<T>& conic, T opacity, T gauss, T dx, T dy, T g_alpha, Vec2<T>& g_mean2d,
                            Sym2<T>& g_conic, T& g_opacity) {
  if (opacity * gauss >= T(kMaxAlpha)) {
    g_mean2d = {0, 0};
    g_conic = {0, 0, 0};
    g_opacity = 0;
    return;
  }
  g_opacity = gauss * g_alpha;
  const T g_power = opacity * gauss * g_alpha;
  g_mean2d.x = -g_power * (conic.a * dx + conic.b * dy);
  g_mean2d.y = -g_power * (conic.b * dx + conic.c * dy);
  g_conic.a = -T(0.5) * dx * dx * g_power;
  g_conic.b = -dx * dy * g_power;
  g_conic.c = -T(0.5) * dy * dy * g_power;
}

}  // namespace gaps::raster

namespace gaps::raster {

// The pixel columns of row `py` where a Gaussian can reach alpha >= kMinAlpha, widened by one pixel so
// that the exact per-pixel test (eval_alpha) still decides. Lets tile loops skip pixels a Gaussian cannot
// touch without changing any result. Returns false when the row is out of reach.
template <typename T>
GAPS_HD bool row_span(const Vec2<T>& mean2d, const Sym2<T>& conic, T opacity, T py_centre, int x_lo, int x_hi,
                      int& x_begin, int& x_end) {
  if (!(opacity * T(255) > T(1))) return false;
  // power(dx) = -0.5 a dx^2 - b dy dx - 0.5 c dy^2 >= log(1 / (255 opacity)) =: L
  const T L = log(T(1) / (T(255) * opacity));
  const T dy = mean2d.y - py_centre;
  const T A = T(0.5) * conic.a, B = conic.b * dy, C = T(0.5) * conic.c * dy * dy + L;
  if (!(A > T(0))) {
    x_begin = x_lo;
    x_end = x_hi;
    return true;
  }
  const T disc = B * B - 4 * A * C;
  if (disc < 0) return false;
  const T root = sqrt(disc);
  // dx = mean.x - (px + 0.5) in [(-B - root) / 2A, (-B + root) / 2A]  =>  px range.
  const T dx_min = (-B - root) / (2 * A), dx_max = (-B + root) / (2 * A);
  const T px_min = mean2d.x - dx_max - T(0.5), px_max = mean2d.x - dx_min - T(0.5);
  const int b = static_cast<int>(floor(px_min)) - 1, e = static_cast<int>(ceil(px_max)) + 2;
  x_begin = b > x_lo ? b : x_lo;
  x_end = e < x_hi ? e : x_hi;
  return x_begin < x_end;
}

}  // namespace gaps::raster

namespace gaps::raster {

// eval_alpha as the CUDA kernels evaluate it, with every skip/clamp decision the CPU's.
// For T = float the host compiler resolves the unqualified exp() in eval_alpha to the C library's
// exp(double) (<cmath> leaves only the double overloads in the global namespace), so the CPU reference
// computes gauss = float(exp(double(power))): correctly rounded. nvcc resolves the same call to expf,
// which is within 2 ulp of that. An ulp only moves an output by ~1e-7 relative, except next to the alpha
// thresholds, where it decides whether a whole contribution (>= 1/255) exists or whether the 0.99 clamp
// (and its zero gradient) applies. So this keeps the fast float exp and re-evaluates exp in double only
// when alpha lands within a few ulp of a threshold (rare: a thin ring of each footprint). `power` is
// gaussian_power, as in eval_alpha; the kernels are compiled without FMA contraction (--fmad=false) so it
// rounds like the CPU's. Same contract and outputs as eval_alpha.
template <typename T>
GAPS_HD bool alpha_from_power_host_rounding(T power, T opacity, T& alpha, T& gauss) {
  if (power > 0) return false;
  gauss = exp(power);
  T a = opacity * gauss;
  // 1e-6 relative is ~8 float ulp: covers expf's 2 ulp plus the rounding of the product.
  const T lo = T(1) - T(1e-6), hi = T(1) + T(1e-6);
  const bool near_min = a > T(kMinAlpha) * lo && a < T(kMinAlpha) * hi;
  const bool near_max = a > T(kMaxAlpha) * lo && a < T(kMaxAlpha) * hi;
  if (near_min || near_max) {
    gauss = T(exp(static_cast<double>(power)));
    a = opacity * gauss;
  }
  alpha = a < T(kMaxAlpha) ? a : T(kMaxAlpha);
  return alpha >= T(kMinAlpha);
}

// An exponent below which a Gaussian's alpha is certainly under kMinAlpha: log(kMinAlpha / opacity) less a margin
// (1e-4) far wider than the float error of expf, of the product and of this logarithm. The compositing kernels
// compare each exponent with it before any exponential: most (pixel, Gaussian) pairs of a tile lie outside the
// Gaussian's 1/255 ellipse, and for them this gives eval_alpha's decision (skip) without computing exp.
template <typename T>
GAPS_HD T certain_skip_power(T opacity) {
  return log(T(kMinAlpha) / opacity) - T(1e-4);
}

}  // namespace gaps::raster

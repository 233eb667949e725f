#pragma once
// Per-pixel maths of PatchMatch stereo (patchmatch.h), written once for the CPU loop and the CUDA kernels.
//
// Both paths round alike: the functions below use only +, -, *, /, sqrt, floor and ldexp in float (all
// correctly rounded in IEEE arithmetic on the host and on the device), never exp, sin or cos, whose
// implementations differ between libm and CUDA; the kernels are compiled without FMA contraction and the
// CPU file with -ffp-contract=off (init/CMakeLists.txt). Random numbers come from a counter-based hash, so
// a pixel draws the same numbers whichever path or thread updates it. Given the same inputs the two paths
// therefore compute the same costs and keep the same hypotheses.
//
// Conventions (those of Camera): x right, y down, z forward; pixel (x, y) has its centre at (x + 0.5, y + 0.5);
// depth is camera-frame z; a normal is a unit vector in the reference camera frame that faces the camera
// (normal . viewing ray < 0).
#include <cmath>
#include <cstdint>

#if defined(__CUDACC__)
#define GAPS_PM_HD __host__ __device__ __forceinline__
#else
#define GAPS_PM_HD inline
#endif

namespace gaps::pm {

constexpr int kMaxSources = 16;        // source views per reference view the per-pixel arrays hold
constexpr float kMaxCost = 2.0f;       // cost of a source that cannot judge a hypothesis (1 - NCC is in [0, 2])
constexpr float kMinVariance = 1e-5f;  // grey variance (weighted) below which a window is flat: no NCC
// Rejection-sampling attempts before a fixed fallback (16 misses in a row: about 1e-5 of the draws; the fallback
// keeps a normal unperturbed, or gives a random one facing straight back).
constexpr int kRandomTries = 16;
// Refinement ranges at sweep 0, halved every sweep: relative depth change and normal offset (unit-ball radius).
constexpr float kDepthPerturbation = 0.1f;
constexpr float kNormalPerturbation = 0.5f;

struct V3 {
  float x, y, z;
};
GAPS_PM_HD V3 operator+(V3 a, V3 b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
GAPS_PM_HD V3 operator-(V3 a, V3 b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
GAPS_PM_HD V3 operator*(float s, V3 a) { return {s * a.x, s * a.y, s * a.z}; }
GAPS_PM_HD float dot(V3 a, V3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }

GAPS_PM_HD float pm_sqrt(float x) {
#if defined(__CUDA_ARCH__)
  return sqrtf(x);
#else
  return std::sqrt(x);
#endif
}
GAPS_PM_HD float pm_floor(float x) {
#if defined(__CUDA_ARCH__)
  return floorf(x);
#else
  return std::floor(x);
#endif
}
GAPS_PM_HD float pm_ldexp(float x, int e) {
#if defined(__CUDA_ARCH__)
  return ldexpf(x, e);
#else
  return std::ldexp(x, e);
#endif
}
GAPS_PM_HD V3 normalized(V3 a) { return (1.0f / pm_sqrt(dot(a, a))) * a; }

// Row-major 3x3.
struct M3 {
  float m[9];
};
GAPS_PM_HD V3 mul(const M3& A, V3 v) {
  return {A.m[0] * v.x + A.m[1] * v.y + A.m[2] * v.z, A.m[3] * v.x + A.m[4] * v.y + A.m[5] * v.z,
          A.m[6] * v.x + A.m[7] * v.y + A.m[8] * v.z};
}
GAPS_PM_HD V3 mul_transposed(const M3& A, V3 v) {
  return {A.m[0] * v.x + A.m[3] * v.y + A.m[6] * v.z, A.m[1] * v.x + A.m[4] * v.y + A.m[7] * v.z,
          A.m[2] * v.x + A.m[5] * v.y + A.m[8] * v.z};
}

// e^-x for x >= 0 from correctly rounded operations (e^-x = 2^-k 2^-f, a degree-8 Taylor series for 2^-f on
// [0, 1)), so the same bits on both paths, which libm's and CUDA's expf do not promise. Relative error below
// 2e-6 + 6e-8 x (the second term is the rounding of x log2(e)); 0 below 2^-126.
GAPS_PM_HD float exp_neg(float x) {
  const float y = x * 1.44269504f;  // log2(e)
  if (!(y < 126.0f)) return 0.0f;
  const float k = pm_floor(y);
  const float t = (y - k) * -0.693147181f;  // -f ln 2, in (-0.7, 0]
  float p = 1.0f / 40320.0f;
  p = p * t + 1.0f / 5040.0f;
  p = p * t + 1.0f / 720.0f;
  p = p * t + 1.0f / 120.0f;
  p = p * t + 1.0f / 24.0f;
  p = p * t + 1.0f / 6.0f;
  p = p * t + 0.5f;
  p = p * t + 1.0f;
  p = p * t + 1.0f;
  return pm_ldexp(p, -static_cast<int>(k));
}

// The bilateral weight of a window pixel whose grey differs by `grey_diff` from the centre's.
GAPS_PM_HD float bilateral_weight(float grey_diff, float inv_sigma_color) {
  return exp_neg((grey_diff < 0.0f ? -grey_diff : grey_diff) * inv_sigma_color);
}

// ---- Counter-based random numbers: splitmix64's finaliser over (seed, view, pixel, iteration, draw).
GAPS_PM_HD uint64_t splitmix64(uint64_t x) {
  x += 0x9E3779B97F4A7C15ull;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
  return x ^ (x >> 31);
}

struct Rng {
  uint64_t key;
  uint32_t draw;
  // Uniform in [0, 1) with 24 bits, every value exact in float.
  GAPS_PM_HD float uniform() {
    const uint64_t h = splitmix64(key ^ splitmix64(draw++));
    return static_cast<float>(h >> 40) * (1.0f / 16777216.0f);
  }
  GAPS_PM_HD float symmetric() { return 2.0f * uniform() - 1.0f; }  // [-1, 1)
};

GAPS_PM_HD Rng make_rng(uint64_t seed, uint32_t view, uint32_t pixel, uint32_t iteration) {
  uint64_t k = splitmix64(seed);
  k = splitmix64(k ^ ((static_cast<uint64_t>(view) << 32) | pixel));
  k = splitmix64(k ^ static_cast<uint64_t>(iteration));
  return {k, 0u};
}

// A point uniform in the unit ball (rejection from the cube); `min_norm2` rejects points too close to 0.
GAPS_PM_HD V3 random_in_ball(Rng& rng, float min_norm2) {
  for (int i = 0; i < kRandomTries; ++i) {
    const V3 v{rng.symmetric(), rng.symmetric(), rng.symmetric()};
    const float n2 = dot(v, v);
    if (n2 <= 1.0f && n2 >= min_norm2) return v;
  }
  return {0.0f, 0.0f, 0.0f};
}

// ---- Views.
struct ViewGeometry {
  float fx, fy, cx, cy;
  int width, height;
};

// K^-1 (u, v, 1) of the pixel centre: the camera-frame point at depth d is d * ray.
GAPS_PM_HD V3 pixel_ray(const ViewGeometry& c, int x, int y) {
  return {(static_cast<float>(x) + 0.5f - c.cx) / c.fx, (static_cast<float>(y) + 0.5f - c.cy) / c.fy, 1.0f};
}

struct Pixel2 {
  float u, v;
};
GAPS_PM_HD Pixel2 project(const ViewGeometry& c, V3 p) { return {c.fx * p.x / p.z + c.cx, c.fy * p.y / p.z + c.cy}; }
GAPS_PM_HD bool inside(const ViewGeometry& c, Pixel2 q) {
  return q.u >= 0.0f && q.u < static_cast<float>(c.width) && q.v >= 0.0f && q.v < static_cast<float>(c.height);
}

// Bilinear sample at the continuous pixel position (u, v) (centres at + 0.5), clamped to the border.
GAPS_PM_HD float bilinear(const float* img, int width, int height, float u, float v) {
  float x = u - 0.5f, y = v - 0.5f;
  const float xmax = static_cast<float>(width - 1), ymax = static_cast<float>(height - 1);
  x = x < 0.0f ? 0.0f : (x > xmax ? xmax : x);
  y = y < 0.0f ? 0.0f : (y > ymax ? ymax : y);
  const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
  const int x1 = x0 + 1 < width ? x0 + 1 : x0, y1 = y0 + 1 < height ? y0 + 1 : y0;
  const float ax = x - static_cast<float>(x0), ay = y - static_cast<float>(y0);
  const float top = img[y0 * width + x0] * (1.0f - ax) + img[y0 * width + x1] * ax;
  const float bottom = img[y1 * width + x0] * (1.0f - ax) + img[y1 * width + x1] * ax;
  return top * (1.0f - ay) + bottom * ay;
}

// One source view as the reference sees it: x_src = R x_ref + t for camera-frame points.
struct Source {
  ViewGeometry cam;
  M3 R;
  V3 t;
  V3 centre;           // the source camera's centre in the reference camera frame, -R^T t
  const float* grey;   // cam.height x cam.width
  const float* depth;  // its photometric depth map (geometric sweeps), else nullptr
};

// The homography that the plane through `point` with normal `normal` (reference camera frame) induces from
// reference pixels to source pixels: H = K_s (R - t n^T / d_plane) K_r^-1 with d_plane = -n . point > 0, the
// plane's distance from the reference centre (n faces the camera, so n . point < 0). A point X on the plane
// has n . X / (n . point) = 1, hence R X + t = (R + t n^T / (n . point)) X.
GAPS_PM_HD M3 plane_homography(const ViewGeometry& ref, const Source& src, V3 point, V3 normal) {
  const float inv_c = 1.0f / dot(normal, point);
  M3 A;  // R + t n^T / (n . point), then composed with K_r^-1 on the right and K_s on the left
  const float n[3] = {normal.x, normal.y, normal.z}, t[3] = {src.t.x, src.t.y, src.t.z};
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) A.m[r * 3 + c] = src.R.m[r * 3 + c] + t[r] * n[c] * inv_c;
  M3 H;
  for (int r = 0; r < 3; ++r) {
    // Right: columns of A K_r^-1 are (A0 / fx, A1 / fy, A2 - A0 cx / fx - A1 cy / fy).
    const float a0 = A.m[r * 3] / ref.fx, a1 = A.m[r * 3 + 1] / ref.fy;
    H.m[r * 3] = a0;
    H.m[r * 3 + 1] = a1;
    H.m[r * 3 + 2] = A.m[r * 3 + 2] - a0 * ref.cx - a1 * ref.cy;
  }
  for (int c = 0; c < 3; ++c) {  // Left: K_s = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]].
    H.m[c] = src.cam.fx * H.m[c] + src.cam.cx * H.m[6 + c];
    H.m[3 + c] = src.cam.fy * H.m[3 + c] + src.cam.cy * H.m[6 + c];
  }
  return H;
}

// H (u, v, 1) dehomogenised; false where the plane point lies behind the source (or at infinity).
GAPS_PM_HD bool apply_homography(const M3& H, float u, float v, Pixel2* out) {
  const V3 p = mul(H, V3{u, v, 1.0f});
  if (!(p.z > 0.0f)) return false;
  *out = {p.x / p.z, p.y / p.z};
  return true;
}

// ---- Bilaterally weighted NCC over the window. Values are accumulated relative to the window centre's
// (reference) and to the sample at the centre's image (source): the variances then come from small numbers,
// which keeps float cancellation far below kMinVariance.
struct WindowSums {
  float w = 0, a = 0, b = 0, aa = 0, bb = 0, ab = 0;
  GAPS_PM_HD void add(float weight, float ra, float rb) {
    w += weight;
    a += weight * ra;
    b += weight * rb;
    aa += weight * ra * ra;
    bb += weight * rb * rb;
    ab += weight * ra * rb;
  }
};

// NCC of the weighted sums, or a value below -1 when either window is flat (no correlation to speak of).
GAPS_PM_HD float weighted_ncc(const WindowSums& s) {
  const float w2 = s.w * s.w;
  const float var_a = s.aa * s.w - s.a * s.a, var_b = s.bb * s.w - s.b * s.b;
  if (!(var_a >= kMinVariance * w2) || !(var_b >= kMinVariance * w2)) return -2.0f;
  return (s.ab * s.w - s.a * s.b) / pm_sqrt(var_a * var_b);
}

// 1 - NCC clamped to [0, 2]; kMaxCost for a flat window.
GAPS_PM_HD float ncc_cost(const WindowSums& s) {
  const float ncc = weighted_ncc(s);
  if (ncc < -1.5f) return kMaxCost;
  const float c = 1.0f - ncc;
  return c < 0.0f ? 0.0f : (c > kMaxCost ? kMaxCost : c);
}

// The window around reference pixel (x, y): (2 radius + 1)^2 offsets sampled every `step`, those inside the
// reference image only.
struct Window {
  int radius, step;
  float inv_sigma_color;
};

// Photometric cost of one source for the window around (x, y) mapped through H.
GAPS_PM_HD float window_cost(const ViewGeometry& ref, const float* ref_grey, const Source& src, const M3& H,
                             const Window& win, int x, int y) {
  const float centre_grey = ref_grey[y * ref.width + x];
  Pixel2 q;
  if (!apply_homography(H, static_cast<float>(x) + 0.5f, static_cast<float>(y) + 0.5f, &q)) return kMaxCost;
  const float centre_src = bilinear(src.grey, src.cam.width, src.cam.height, q.u, q.v);
  WindowSums sums;
  for (int dy = -win.radius; dy <= win.radius; dy += win.step) {
    const int yy = y + dy;
    if (yy < 0 || yy >= ref.height) continue;
    for (int dx = -win.radius; dx <= win.radius; dx += win.step) {
      const int xx = x + dx;
      if (xx < 0 || xx >= ref.width) continue;
      if (!apply_homography(H, static_cast<float>(xx) + 0.5f, static_cast<float>(yy) + 0.5f, &q)) return kMaxCost;
      const float a = ref_grey[yy * ref.width + xx] - centre_grey;
      const float b = bilinear(src.grey, src.cam.width, src.cam.height, q.u, q.v) - centre_src;
      sums.add(bilateral_weight(a, win.inv_sigma_color), a, b);
    }
  }
  return ncc_cost(sums);
}

// Whether source `src` can judge the camera-frame point X: in front of it, projecting inside it, and seen
// under a triangulation angle of at least the minimum (cos <= max_cos_triangulation).
GAPS_PM_HD bool source_sees(const Source& src, V3 X, float max_cos_triangulation) {
  const V3 p = mul(src.R, X) + src.t;
  if (!(p.z > 0.0f) || !inside(src.cam, project(src.cam, p))) return false;
  const V3 to_src = X - src.centre;
  const float cos_angle = dot(X, to_src) / pm_sqrt(dot(X, X) * dot(to_src, to_src));
  return cos_angle <= max_cos_triangulation;
}

// Forward-backward reprojection error (pixels, at most max_error) of reference pixel (x, y) at camera-frame
// point X through the source's depth map: X projects into the source, the source's depth at that pixel
// (nearest) puts a point on the same source ray, which projects back into the reference. max_error where
// any step fails (outside, behind, no depth).
GAPS_PM_HD float geometric_error(const ViewGeometry& ref, const Source& src, V3 X, int x, int y, float max_error) {
  const V3 p = mul(src.R, X) + src.t;
  if (!(p.z > 0.0f)) return max_error;
  const Pixel2 q = project(src.cam, p);
  if (!inside(src.cam, q)) return max_error;
  const float d = src.depth[static_cast<int>(q.v) * src.cam.width + static_cast<int>(q.u)];
  if (!(d > 0.0f)) return max_error;
  const V3 back_src{d * (q.u - src.cam.cx) / src.cam.fx, d * (q.v - src.cam.cy) / src.cam.fy, d};
  const V3 back = mul_transposed(src.R, back_src - src.t);
  if (!(back.z > 0.0f)) return max_error;
  const Pixel2 r = project(ref, back);
  const float du = r.u - (static_cast<float>(x) + 0.5f), dv = r.v - (static_cast<float>(y) + 0.5f);
  const float e = pm_sqrt(du * du + dv * dv);
  return e < max_error ? e : max_error;
}

// Mean of the `best` lowest of costs[0..n) (ties: the lower index first); `chosen` gets a bit per source used.
GAPS_PM_HD float mean_of_best(const float* costs, int n, int best, uint32_t* chosen) {
  *chosen = 0u;
  const int k = best < n ? best : n;
  float sum = 0.0f;
  for (int i = 0; i < k; ++i) {
    int arg = -1;
    for (int s = 0; s < n; ++s)
      if (!((*chosen >> s) & 1u) && (arg < 0 || costs[s] < costs[arg])) arg = s;
    *chosen |= 1u << arg;
    sum += costs[arg];
  }
  return k > 0 ? sum / static_cast<float>(k) : kMaxCost;
}

// ---- One view's PatchMatch problem: what a step reads and the state it updates, as raw pointers on the
// device of the run (host memory for the CPU path, device memory for the kernels).
struct Problem {
  ViewGeometry cam;
  const float* grey;  // cam.height x cam.width
  float min_depth, max_depth;
  int num_sources;
  Source sources[kMaxSources];
  Window window;
  int best_views;
  float max_cos_triangulation;
  bool geometric;  // add the geometric term (every source's `depth` is set)
  float geometric_regularizer, geometric_max_error;
  float max_cost;
  uint64_t seed;
  uint32_t view;
  // State, all cam.height x cam.width (normal: x 3).
  float* depth;
  float* normal;
  float* cost;
};

struct Hypothesis {
  float depth;
  V3 normal;
};

GAPS_PM_HD int pixel_index(const Problem& p, int x, int y) { return y * p.cam.width + x; }

// The aggregated cost of hypothesis h at pixel (x, y): the mean of the best_views lowest per-source costs,
// where a source that cannot judge the point (behind, outside, too small a triangulation angle) costs
// kMaxCost, so it is used only when fewer than best_views sources can; plus, in geometric sweeps,
// geometric_regularizer times the mean forward-backward error over those same sources.
GAPS_PM_HD float hypothesis_cost(const Problem& p, int x, int y, const Hypothesis& h) {
  const V3 X = h.depth * pixel_ray(p.cam, x, y);
  if (!(dot(h.normal, X) < 0.0f))
    return kMaxCost + (p.geometric ? p.geometric_regularizer * p.geometric_max_error : 0.0f);
  float costs[kMaxSources];
  for (int s = 0; s < p.num_sources; ++s) {
    const Source& src = p.sources[s];
    costs[s] = source_sees(src, X, p.max_cos_triangulation)
                   ? window_cost(p.cam, p.grey, src, plane_homography(p.cam, src, X, h.normal), p.window, x, y)
                   : kMaxCost;
  }
  uint32_t chosen;
  float cost = mean_of_best(costs, p.num_sources, p.best_views, &chosen);
  if (p.geometric) {
    float sum = 0.0f;
    int used = 0;
    for (int s = 0; s < p.num_sources; ++s) {
      if (!((chosen >> s) & 1u)) continue;
      sum += geometric_error(p.cam, p.sources[s], X, x, y, p.geometric_max_error);
      ++used;
    }
    cost += p.geometric_regularizer * (used > 0 ? sum / static_cast<float>(used) : p.geometric_max_error);
  }
  return cost;
}

// A depth uniform in inverse depth over [min_depth, max_depth]: equal steps in inverse depth are equal steps
// in disparity, i.e. in pixels along the epipolar lines, so the random hypotheses cover the image-space search
// evenly (uniform in depth would leave the near end, where a step moves the most pixels, sparsely sampled).
GAPS_PM_HD float random_depth(const Problem& p, Rng& rng) {
  const float inv_far = 1.0f / p.max_depth, inv_near = 1.0f / p.min_depth;
  return 1.0f / (inv_far + rng.uniform() * (inv_near - inv_far));
}

// A direction uniform on the hemisphere facing the camera along `ray`.
GAPS_PM_HD V3 random_normal(V3 ray, Rng& rng) {
  V3 v = random_in_ball(rng, 1e-4f);
  if (dot(v, v) == 0.0f) return {0.0f, 0.0f, -1.0f};
  v = normalized(v);
  return dot(v, ray) > 0.0f ? -1.0f * v : v;
}

GAPS_PM_HD float clamp_depth(const Problem& p, float d) {
  return d < p.min_depth ? p.min_depth : (d > p.max_depth ? p.max_depth : d);
}

// Refinement range of sweep `iteration` (photometric sweeps first, geometric ones continue the count).
GAPS_PM_HD float perturbation_scale(int iteration) { return pm_ldexp(1.0f, -iteration); }

GAPS_PM_HD float perturbed_depth(const Problem& p, float depth, float scale, Rng& rng) {
  return clamp_depth(p, depth * (1.0f + kDepthPerturbation * scale * rng.symmetric()));
}

// The normal moved by a random offset in a ball of radius kNormalPerturbation * scale; the old one where the
// new one would not face the camera.
GAPS_PM_HD V3 perturbed_normal(V3 normal, V3 ray, float scale, Rng& rng) {
  const V3 n = normalized(normal + (kNormalPerturbation * scale) * random_in_ball(rng, 0.0f));
  return dot(n, ray) < 0.0f ? n : normal;
}

GAPS_PM_HD Hypothesis load(const Problem& p, int i) {
  return {p.depth[i], {p.normal[3 * i], p.normal[3 * i + 1], p.normal[3 * i + 2]}};
}
GAPS_PM_HD void store(const Problem& p, int i, const Hypothesis& h, float cost) {
  p.depth[i] = h.depth;
  p.normal[3 * i] = h.normal.x;
  p.normal[3 * i + 1] = h.normal.y;
  p.normal[3 * i + 2] = h.normal.z;
  p.cost[i] = cost;
}

// Random numbers of the initialisation use this iteration index (sweeps count from 0).
constexpr uint32_t kInitIteration = 0xFFFFFFFFu;

GAPS_PM_HD void init_pixel(const Problem& p, int x, int y) {
  const int i = pixel_index(p, x, y);
  Rng rng = make_rng(p.seed, p.view, static_cast<uint32_t>(i), kInitIteration);
  Hypothesis h;
  h.depth = random_depth(p, rng);
  h.normal = random_normal(pixel_ray(p.cam, x, y), rng);
  store(p, i, h, hypothesis_cost(p, x, y, h));
}

// Recomputes the stored cost of the current hypothesis (the cost function changes when geometric sweeps begin).
GAPS_PM_HD void rescore_pixel(const Problem& p, int x, int y) {
  const int i = pixel_index(p, x, y);
  p.cost[i] = hypothesis_cost(p, x, y, load(p, i));
}

// The propagation pattern of Gipuma's fast red-black scheme (Galliani et al., "Massively Parallel Multiview
// Stereopsis by Surface Normal Diffusion", ICCV 2015): the four adjacent pixels and the four at distance 5
// along the axes. All have the other colour, so a sweep over one colour reads only pixels it does not write.
constexpr int kNeighbours = 8;
GAPS_PM_HD void neighbour_offset(int k, int* dx, int* dy) {
  const int dist = k < 4 ? 1 : 5;
  const int dir = k & 3;
  *dx = dir == 0 ? -dist : (dir == 1 ? dist : 0);
  *dy = dir == 2 ? -dist : (dir == 3 ? dist : 0);
}

// Keeps h when it is cheaper than *best.
GAPS_PM_HD void consider(const Problem& p, int x, int y, const Hypothesis& h, Hypothesis* best, float* best_cost) {
  const float c = hypothesis_cost(p, x, y, h);
  if (c < *best_cost) {
    *best = h;
    *best_cost = c;
  }
}

// One red-black update of pixel (x, y) in sweep `iteration`: the neighbours' planes (each neighbour's plane
// intersected with this pixel's ray), then perturbations of the best so far (depth, normal, both) and a fresh
// random hypothesis; the cheapest wins.
GAPS_PM_HD void update_pixel(const Problem& p, int x, int y, int iteration) {
  const int i = pixel_index(p, x, y);
  const V3 ray = pixel_ray(p.cam, x, y);
  Hypothesis best = load(p, i);
  float best_cost = p.cost[i];
  for (int k = 0; k < kNeighbours; ++k) {
    int dx, dy;
    neighbour_offset(k, &dx, &dy);
    const int nx = x + dx, ny = y + dy;
    if (nx < 0 || ny < 0 || nx >= p.cam.width || ny >= p.cam.height) continue;
    const Hypothesis nb = load(p, pixel_index(p, nx, ny));
    const float facing = dot(nb.normal, ray);
    if (!(facing < 0.0f)) continue;
    const float d = dot(nb.normal, nb.depth * pixel_ray(p.cam, nx, ny)) / facing;
    if (!(d >= p.min_depth && d <= p.max_depth)) continue;
    consider(p, x, y, {d, nb.normal}, &best, &best_cost);
  }
  Rng rng = make_rng(p.seed, p.view, static_cast<uint32_t>(i), static_cast<uint32_t>(iteration));
  const float scale = perturbation_scale(iteration);
  const Hypothesis base = best;
  const float d = perturbed_depth(p, base.depth, scale, rng);
  const V3 n = perturbed_normal(base.normal, ray, scale, rng);
  consider(p, x, y, {d, base.normal}, &best, &best_cost);
  consider(p, x, y, {base.depth, n}, &best, &best_cost);
  consider(p, x, y, {d, n}, &best, &best_cost);
  Hypothesis fresh;
  fresh.depth = random_depth(p, rng);
  fresh.normal = random_normal(ray, rng);
  consider(p, x, y, fresh, &best, &best_cost);
  store(p, i, best, best_cost);
}

// The final filter: no depth (and a zero normal) where the cost is above max_cost or the depth out of range.
GAPS_PM_HD void filter_pixel(const Problem& p, int x, int y) {
  const int i = pixel_index(p, x, y);
  const float d = p.depth[i];
  if (p.cost[i] <= p.max_cost && d >= p.min_depth && d <= p.max_depth) return;
  store(p, i, {0.0f, {0.0f, 0.0f, 0.0f}}, p.cost[i]);
}

// The pixels of one colour of the checkerboard: pixel (x, y) is red (0) when x + y is even. The k-th pixel of
// `colour` in row-major order over rows of ceil(width / 2) slots; false for the slot past a row's end.
GAPS_PM_HD bool checkerboard_pixel(int width, int colour, int k, int* x, int* y) {
  const int half = (width + 1) / 2;
  *y = k / half;
  *x = 2 * (k % half) + ((*y + colour) & 1);
  return *x < width;
}

}  // namespace gaps::pm

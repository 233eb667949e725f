#pragma once
// Synthetic multi-view stereo scenes with known geometry for the PatchMatch tests (CPU and CUDA): planes and
// spheres carrying a procedural texture (hashed value noise at several octaves, so a window has texture at
// every scale), rendered by ray casting with supersampling, from cameras on a ring around the object, and the
// accuracy measures the tests put bars on.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <optional>
#include <vector>

#include <ATen/ATen.h>
#include <Eigen/Dense>

#include "gs_trainer/init/patchmatch.h"
#include "gs_trainer/scene/camera.h"
#include "tests/camera_test_util.h"

namespace gaps::synthetic_stereo {

// ---- Texture: value noise on the integer lattice, trilinear with smoothstep, summed over octaves.
inline double lattice_value(int64_t x, int64_t y, int64_t z) {
  uint64_t h = static_cast<uint64_t>(x) * 0x9E3779B97F4A7C15ull ^ static_cast<uint64_t>(y) * 0xC2B2AE3D27D4EB4Full ^
               static_cast<uint64_t>(z) * 0x165667B19E3779F9ull;
  h = (h ^ (h >> 31)) * 0xBF58476D1CE4E5B9ull;
  h ^= h >> 29;
  return static_cast<double>(h >> 11) / static_cast<double>(uint64_t{1} << 53);
}

inline double value_noise(const Eigen::Vector3d& p) {
  const Eigen::Vector3d f = p.array().floor();
  const Eigen::Vector3d r = p - f;
  const Eigen::Vector3d s = r.array().square() * (3.0 - 2.0 * r.array());
  const auto x = static_cast<int64_t>(f.x()), y = static_cast<int64_t>(f.y()), z = static_cast<int64_t>(f.z());
  double out = 0.0;
  for (int c = 0; c < 8; ++c) {
    const int dx = c & 1, dy = (c >> 1) & 1, dz = c >> 2;
    const double w = (dx ? s.x() : 1 - s.x()) * (dy ? s.y() : 1 - s.y()) * (dz ? s.z() : 1 - s.z());
    out += w * lattice_value(x + dx, y + dy, z + dz);
  }
  return out;
}

// Albedo in [0.1, 0.9] at world point p: four octaves of 3 to 24 lattice cells per unit (a cell of the finest
// is about a pixel at the scenes' scale, averaged by the 3x3 supersampling; the coarser ones carry the match).
inline double texture(const Eigen::Vector3d& p) {
  double sum = 0.0, norm = 0.0, amplitude = 1.0, frequency = 3.0;
  for (int octave = 0; octave < 4; ++octave) {
    sum += amplitude * value_noise(frequency * p + Eigen::Vector3d(17.0 * octave, 5.0, 3.0));
    norm += amplitude;
    amplitude *= 0.75;
    frequency *= 2.0;
  }
  return 0.1 + 0.8 * std::clamp((sum / norm - 0.5) * 2.0 + 0.5, 0.0, 1.0);
}

// ---- Geometry.
struct Plane {
  Eigen::Vector3d point, normal;
};
struct Sphere {
  Eigen::Vector3d centre;
  double radius;
};
struct Scene {
  std::vector<Plane> planes;
  std::vector<Sphere> spheres;
};

struct Hit {
  double s;  // ray parameter: hit = origin + s * direction
  Eigen::Vector3d normal;
  int primitive;  // planes first, then spheres
};

inline std::optional<Hit> intersect(const Scene& scene, const Eigen::Vector3d& o, const Eigen::Vector3d& d) {
  std::optional<Hit> best;
  const auto keep = [&](double s, const Eigen::Vector3d& n, int id) {
    if (s > 1e-9 && (!best || s < best->s)) best = Hit{s, n, id};
  };
  int id = 0;
  for (const Plane& p : scene.planes) {
    const double denom = p.normal.dot(d);
    if (std::abs(denom) > 1e-12) keep(p.normal.dot(p.point - o) / denom, p.normal, id);
    ++id;
  }
  for (const Sphere& sp : scene.spheres) {
    const Eigen::Vector3d oc = o - sp.centre;
    const double b = oc.dot(d), c = oc.squaredNorm() - sp.radius * sp.radius, a = d.squaredNorm();
    const double disc = b * b - a * c;
    if (disc >= 0) {
      const double s = (-b - std::sqrt(disc)) / a;
      keep(s, (o + s * d - sp.centre) / sp.radius, id);
    }
    ++id;
  }
  return best;
}

// OpenCV-convention camera at `centre` looking at `target` (world y points down).
inline Camera look_at(const Eigen::Vector3d& centre, const Eigen::Vector3d& target, int width, int height,
                      double focal) {
  const Eigen::Vector3d z = (target - centre).normalized();
  const Eigen::Vector3d x = Eigen::Vector3d(0, 1, 0).cross(z).normalized();
  const Eigen::Vector3d y = z.cross(x);
  Camera c = test::camera_looking_down_z(width, height, focal, centre);
  c.R.row(0) = x;
  c.R.row(1) = y;
  c.R.row(2) = z;
  c.t = -c.R * centre;
  return c;
}

// `count` cameras on a ring of `radius` around the origin, `step_deg` apart in azimuth, centred on the -z
// axis and a little above the object: views that surround it, as in a 360-degree capture.
inline std::vector<Camera> ring_cameras(int count, double step_deg, double radius, int width, int height,
                                        double focal) {
  std::vector<Camera> cams;
  for (int i = 0; i < count; ++i) {
    const double az = (i - (count - 1) / 2.0) * step_deg * M_PI / 180.0;
    const Eigen::Vector3d centre(radius * std::sin(az), -0.25 * radius, -radius * std::cos(az));
    cams.push_back(look_at(centre, Eigen::Vector3d::Zero(), width, height, focal));
  }
  return cams;
}

// A view with its ground truth at the pixel centres.
struct View {
  Camera camera;
  at::Tensor image;      // HxWx3 float, 3x3 supersampled
  at::Tensor depth;      // HxW float, camera z, 0 where the ray hits nothing
  at::Tensor normal;     // HxWx3 float, camera frame
  at::Tensor primitive;  // HxW int, -1 where nothing
};

inline Eigen::Vector3d world_ray(const Camera& c, double u, double v) {
  return c.R.transpose() * Eigen::Vector3d((u - c.cx) / c.fx, (v - c.cy) / c.fy, 1.0);
}

inline View render(const Scene& scene, const Camera& c) {
  constexpr int kSamples = 3;
  View view{c, at::zeros({c.height, c.width, 3}), at::zeros({c.height, c.width}), at::zeros({c.height, c.width, 3}),
            at::full({c.height, c.width}, -1, at::kInt)};
  auto img = view.image.accessor<float, 3>();
  auto depth = view.depth.accessor<float, 2>();
  auto normal = view.normal.accessor<float, 3>();
  auto prim = view.primitive.accessor<int, 2>();
  const Eigen::Vector3d o = c.center();
  for (int y = 0; y < c.height; ++y)
    for (int x = 0; x < c.width; ++x) {
      double albedo = 0.0;
      for (int k = 0; k < kSamples * kSamples; ++k) {
        const double u = x + (k % kSamples + 0.5) / kSamples, v = y + (k / kSamples + 0.5) / kSamples;
        const Eigen::Vector3d d = world_ray(c, u, v);
        if (const auto hit = intersect(scene, o, d)) albedo += texture(o + hit->s * d);
      }
      albedo /= kSamples * kSamples;
      img[y][x][0] = static_cast<float>(albedo);
      img[y][x][1] = static_cast<float>(0.9 * albedo + 0.05);
      img[y][x][2] = static_cast<float>(0.8 * albedo + 0.1);
      const Eigen::Vector3d d = world_ray(c, x + 0.5, y + 0.5);
      if (const auto hit = intersect(scene, o, d)) {
        depth[y][x] = static_cast<float>(hit->s);  // the camera-frame ray has z = 1
        Eigen::Vector3d n = c.R * hit->normal;
        if (n.dot(c.R * d) > 0) n = -n;
        for (int i = 0; i < 3; ++i) normal[y][x][i] = static_cast<float>(n[i]);
        prim[y][x] = hit->primitive;
      }
    }
  return view;
}

// HxW bool: pixels of views[r] whose surface point some other view sees (inside it, not occluded).
inline at::Tensor covisible(const Scene& scene, const std::vector<View>& views, size_t r) {
  const Camera& c = views[r].camera;
  at::Tensor mask = at::zeros({c.height, c.width}, at::kBool);
  auto m = mask.accessor<bool, 2>();
  auto depth = views[r].depth.accessor<float, 2>();
  for (int y = 0; y < c.height; ++y)
    for (int x = 0; x < c.width; ++x) {
      if (depth[y][x] <= 0) continue;
      const Eigen::Vector3d X = c.center() + depth[y][x] * world_ray(c, x + 0.5, y + 0.5);
      for (size_t s = 0; s < views.size() && !m[y][x]; ++s) {
        if (s == r) continue;
        const Camera& sc = views[s].camera;
        const Eigen::Vector3d p = sc.R * X + sc.t;
        const double u = sc.fx * p.x() / p.z() + sc.cx, v = sc.fy * p.y() / p.z() + sc.cy;
        if (p.z() <= 0 || u < 0 || v < 0 || u >= sc.width || v >= sc.height) continue;
        const auto hit = intersect(scene, sc.center(), X - sc.center());
        m[y][x] = hit && std::abs(hit->s - 1.0) < 1e-4;
      }
    }
  return mask;
}

// The other views ordered by the angle between viewing directions, nearest first.
inline std::vector<int> sources_by_angle(const std::vector<View>& views, size_t r) {
  std::vector<int> order;
  for (size_t s = 0; s < views.size(); ++s)
    if (s != r) order.push_back(static_cast<int>(s));
  const Eigen::Vector3d f = views[r].camera.forward();
  std::stable_sort(order.begin(), order.end(),
                   [&](int a, int b) { return views[a].camera.forward().dot(f) > views[b].camera.forward().dot(f); });
  return order;
}

inline PatchMatchInput stereo_input(const std::vector<View>& views, std::pair<double, double> range) {
  PatchMatchInput in;
  for (size_t i = 0; i < views.size(); ++i) {
    in.cameras.push_back(views[i].camera);
    in.images.push_back(views[i].image);
    in.depth_ranges.push_back(range);
    in.sources.push_back(sources_by_angle(views, i));
  }
  return in;
}

// ---- Scenes: four views 30 degrees apart at 4 units from the object (the outer two see it 90 degrees apart).
constexpr int kWidth = 96, kHeight = 72;
constexpr double kFocal = 100.0;
constexpr std::pair<double, double> kDepthRange{2.0, 10.0};

// A textured plane through the origin, slanted towards the cameras' left and up.
inline Scene slanted_plane() { return {{{Eigen::Vector3d::Zero(), Eigen::Vector3d(0.35, -0.3, -1).normalized()}}, {}}; }

// A textured sphere of radius 1.2 in front of a textured back plane.
inline Scene sphere_before_plane() {
  return {{{Eigen::Vector3d(0, 0, 2.5), Eigen::Vector3d(0, 0, -1)}}, {{Eigen::Vector3d::Zero(), 1.2}}};
}

// PatchMatch settings for these views: a 7x7 window (the default 11x11 suits the 640-pixel working size; on
// views a sixth of that it spans so much of the sphere that its curvature biases the depth by over 1%), and
// the best 2 of the 3 sources (the farthest view, 60 or 90 degrees away, often sees the point occluded or
// grazing).
inline PatchMatchOptions small_view_options() {
  PatchMatchOptions o;
  o.window_radius = 3;
  o.window_step = 1;
  o.best_views = 2;
  return o;
}

inline std::vector<View> render_views(const Scene& scene, int width = kWidth, int height = kHeight) {
  std::vector<View> views;
  for (const Camera& c : ring_cameras(4, 30.0, 4.0, width, height, kFocal * width / kWidth))
    views.push_back(render(scene, c));
  return views;
}

// ---- Measures over the covisible pixels of one view.
struct Accuracy {
  int64_t covisible = 0;
  int64_t valid = 0;     // covisible pixels with a depth
  int64_t accurate = 0;  // of those, within rel_tol of the true depth
  double valid_fraction() const { return covisible ? static_cast<double>(valid) / covisible : 0.0; }
  double accurate_fraction() const { return valid ? static_cast<double>(accurate) / valid : 0.0; }
  std::vector<double> normal_errors_deg;  // accurate pixels on primitive `normal_primitive`
  double median_normal_error_deg() const {
    if (normal_errors_deg.empty()) return 180.0;
    std::vector<double> e = normal_errors_deg;
    std::nth_element(e.begin(), e.begin() + e.size() / 2, e.end());
    return e[e.size() / 2];
  }
};

inline Accuracy measure(const ViewDepthNormal& estimate, const View& truth, const at::Tensor& covisible_mask,
                        double rel_tol = 0.01, int normal_primitive = 0) {
  Accuracy a;
  auto est = estimate.depth.accessor<float, 2>();
  auto est_n = estimate.normal.accessor<float, 3>();
  auto gt = truth.depth.accessor<float, 2>();
  auto gt_n = truth.normal.accessor<float, 3>();
  auto prim = truth.primitive.accessor<int, 2>();
  auto m = covisible_mask.accessor<bool, 2>();
  for (int y = 0; y < truth.camera.height; ++y)
    for (int x = 0; x < truth.camera.width; ++x) {
      if (!m[y][x]) continue;
      ++a.covisible;
      if (est[y][x] <= 0) continue;
      ++a.valid;
      if (std::abs(est[y][x] - gt[y][x]) >= rel_tol * gt[y][x]) continue;
      ++a.accurate;
      if (prim[y][x] != normal_primitive) continue;
      double cos = 0;
      for (int i = 0; i < 3; ++i) cos += est_n[y][x][i] * gt_n[y][x][i];
      a.normal_errors_deg.push_back(std::acos(std::clamp(cos, -1.0, 1.0)) * 180.0 / M_PI);
    }
  return a;
}

// Sum of measure() over all views.
inline Accuracy measure_all(const Scene& scene, const std::vector<View>& views,
                            const std::vector<ViewDepthNormal>& estimates) {
  Accuracy total;
  for (size_t r = 0; r < views.size(); ++r) {
    const Accuracy a = measure(estimates[r], views[r], covisible(scene, views, r));
    total.covisible += a.covisible;
    total.valid += a.valid;
    total.accurate += a.accurate;
    total.normal_errors_deg.insert(total.normal_errors_deg.end(), a.normal_errors_deg.begin(),
                                   a.normal_errors_deg.end());
  }
  return total;
}

}  // namespace gaps::synthetic_stereo

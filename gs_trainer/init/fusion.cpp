#include "gs_trainer/init/fusion.h"

#include <chrono>
#include <cmath>

#include <ATen/ATen.h>
#include <Eigen/Dense>
#include "absl/strings/str_cat.h"
#include "gs_trainer/init/plane_sweep.h"

namespace gaps {
namespace {

// One view's maps as contiguous CPU floats, with what the cluster loop needs of its camera.
struct FusionView {
  const Camera* camera;
  at::Tensor depth, normal, image;  // kept alive for the pointers below
  const float* d;
  const float* n;
  const float* rgb;
  std::vector<char> fused;
};

absl::StatusOr<FusionView> fusion_view(const ViewDepthNormal& m) {
  const Camera& c = m.camera;
  const auto hw = [&](const at::Tensor& t, int channels) {
    return t.defined() && t.dim() == (channels ? 3 : 2) && t.size(0) == c.height && t.size(1) == c.width &&
           (!channels || t.size(2) == channels);
  };
  if (!hw(m.depth, 0) || !hw(m.normal, 3) || !hw(m.image, 3))
    return absl::InvalidArgumentError(absl::StrCat("fusion: the maps of ", c.name, " do not match its ", c.width, "x",
                                                   c.height, " camera (depth HxW, normal and image HxWx3)"));
  FusionView v{&c, m.depth.to(at::kCPU, at::kFloat).contiguous(), m.normal.to(at::kCPU, at::kFloat).contiguous(),
               m.image.to(at::kCPU, at::kFloat).contiguous()};
  v.d = v.depth.data_ptr<float>();
  v.n = v.normal.data_ptr<float>();
  v.rgb = v.image.data_ptr<float>();
  v.fused.assign(static_cast<size_t>(c.width) * c.height, 0);
  return v;
}

Eigen::Vector3d world_point(const FusionView& v, int64_t pixel) {
  const Camera& c = *v.camera;
  const double x = static_cast<double>(pixel % c.width) + 0.5, y = static_cast<double>(pixel / c.width) + 0.5;
  const Eigen::Vector3d cam = v.d[pixel] * Eigen::Vector3d((x - c.cx) / c.fx, (y - c.cy) / c.fy, 1.0);
  return c.R.transpose() * (cam - c.t);
}

Eigen::Vector3d world_normal(const FusionView& v, int64_t pixel) {
  const float* n = v.n + 3 * pixel;
  return v.camera->R.transpose() * Eigen::Vector3d(n[0], n[1], n[2]);
}

// Camera-frame point of X in c: (u, v) in pixels and z.
Eigen::Vector3d project(const Camera& c, const Eigen::Vector3d& X) {
  const Eigen::Vector3d p = c.R * X + c.t;
  return {c.fx * p.x() / p.z() + c.cx, c.fy * p.y() / p.z() + c.cy, p.z()};
}

// Sums over a cluster's pixels.
struct Cluster {
  Eigen::Vector3d xyz = Eigen::Vector3d::Zero(), rgb = Eigen::Vector3d::Zero(), normal = Eigen::Vector3d::Zero();
  std::vector<std::pair<FusionView*, int64_t>> members;

  void add(FusionView* v, int64_t pixel, const Eigen::Vector3d& X, const Eigen::Vector3d& N) {
    xyz += X;
    normal += N;
    const float* c = v->rgb + 3 * pixel;
    rgb += Eigen::Vector3d(c[0], c[1], c[2]);
    members.emplace_back(v, pixel);
  }
};

// The pixel of `s` that joins the cluster of reference pixel `ref_pixel` of `ref` (point X, world normal N),
// or -1 (FusionOptions says when one joins).
int64_t agreeing_pixel(const FusionView& ref, int64_t ref_pixel, const Eigen::Vector3d& X, const Eigen::Vector3d& N,
                       const FusionView& s, const FusionOptions& o, double min_cos_normal) {
  const Camera& sc = *s.camera;
  const Eigen::Vector3d p = project(sc, X);
  if (!(p.z() > 0) || !(p.x() >= 0 && p.x() < sc.width && p.y() >= 0 && p.y() < sc.height)) return -1;
  const int64_t q = static_cast<int64_t>(p.y()) * sc.width + static_cast<int64_t>(p.x());
  const double ds = s.d[q];
  if (s.fused[q] || !(ds > 0) || std::abs(p.z() - ds) > o.max_depth_error * ds) return -1;
  const Eigen::Vector3d back = project(*ref.camera, world_point(s, q));
  const double du = back.x() - (static_cast<double>(ref_pixel % ref.camera->width) + 0.5);
  const double dv = back.y() - (static_cast<double>(ref_pixel / ref.camera->width) + 0.5);
  if (!(back.z() > 0) || du * du + dv * dv > o.max_reprojection_px * o.max_reprojection_px) return -1;
  const Eigen::Vector3d Ns = world_normal(s, q);
  const double norms = N.norm() * Ns.norm();
  if (!(norms > 0) || !(N.dot(Ns) >= min_cos_normal * norms)) return -1;
  return q;
}

at::Tensor to_tensor(std::vector<float>& values) {
  return at::from_blob(values.data(), {static_cast<int64_t>(values.size() / 3), 3}, at::kFloat).clone();
}

}  // namespace

absl::Status validate_fusion_options(const FusionOptions& o) {
  if (o.min_views < 1) return absl::InvalidArgumentError(absl::StrCat("min_views must be >= 1, got ", o.min_views));
  if (!(o.max_depth_error > 0) || !(o.max_reprojection_px > 0))
    return absl::InvalidArgumentError(absl::StrCat("max_depth_error and max_reprojection_px must be > 0, got ",
                                                   o.max_depth_error, " and ", o.max_reprojection_px));
  if (!(o.max_normal_error_deg > 0 && o.max_normal_error_deg <= 180))
    return absl::InvalidArgumentError(
        absl::StrCat("max_normal_error_deg must be in (0, 180], got ", o.max_normal_error_deg));
  if (o.max_points < 0) return absl::InvalidArgumentError(absl::StrCat("max_points must be >= 0, got ", o.max_points));
  return absl::OkStatus();
}

absl::StatusOr<FusedCloud> fuse_patchmatch_maps(const std::vector<ViewDepthNormal>& maps,
                                                const FusionOptions& options) {
  if (absl::Status s = validate_fusion_options(options); !s.ok()) return s;
  const auto start = std::chrono::steady_clock::now();
  FusedCloud out;
  std::vector<FusionView> views;
  for (const ViewDepthNormal& m : maps) {
    absl::StatusOr<FusionView> v = fusion_view(m);
    if (!v.ok()) return v.status();
    out.stats.depth_pixels.push_back((v->depth > 0).sum().item<int64_t>());
    views.push_back(std::move(*v));
  }
  const double min_cos_normal = std::cos(options.max_normal_error_deg * M_PI / 180.0);
  std::vector<float> xyz, rgb, normals;
  for (FusionView& ref : views) {
    const int64_t pixels = static_cast<int64_t>(ref.fused.size());
    for (int64_t pixel = 0; pixel < pixels; ++pixel) {
      if (ref.fused[pixel] || !(ref.d[pixel] > 0)) continue;
      ++out.stats.clusters;
      const Eigen::Vector3d X = world_point(ref, pixel), N = world_normal(ref, pixel);
      Cluster cluster;
      cluster.add(&ref, pixel, X, N);
      for (FusionView& s : views) {
        if (&s == &ref) continue;
        const int64_t q = agreeing_pixel(ref, pixel, X, N, s, options, min_cos_normal);
        if (q >= 0) cluster.add(&s, q, world_point(s, q), world_normal(s, q));
      }
      // One pixel per view at most, so the members count the views.
      const int count = static_cast<int>(cluster.members.size());
      if (count < options.min_views) continue;
      for (const auto& [v, q] : cluster.members) v->fused[q] = 1;
      const Eigen::Vector3d n = cluster.normal.normalized();
      for (int k = 0; k < 3; ++k) {
        xyz.push_back(static_cast<float>(cluster.xyz[k] / count));
        rgb.push_back(static_cast<float>(cluster.rgb[k] / count));
        normals.push_back(static_cast<float>(n[k]));
      }
    }
  }
  out.points = {to_tensor(xyz), to_tensor(rgb)};
  out.normals = to_tensor(normals);
  out.stats.fused_points = out.points.xyz.size(0);
  if (options.max_points > 0) {
    out.stats.voxel_size = capping_voxel_size(out.points.xyz, options.max_points);
    if (out.stats.voxel_size > 0) {
      const std::vector<at::Tensor> means =
          voxel_means(out.points.xyz, out.stats.voxel_size, {out.points.xyz, out.points.rgb, out.normals});
      out.points = {means[0], means[1]};
      // Averaged unit vectors are shorter than one (or nearly zero where a voxel straddles an edge).
      out.normals = means[2] / means[2].norm(2, 1, true).clamp_min(1e-12);
    }
  }
  out.stats.points = out.points.xyz.size(0);
  out.stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return out;
}

}  // namespace gaps

#include "gs_trainer/init/plane_sweep.h"

#include <algorithm>
#include <chrono>
#include <cmath>

#include <ATen/ATen.h>
#include <Eigen/Dense>
#include "absl/strings/str_cat.h"
#include "gs_trainer/init/working_view.h"

namespace gaps {
namespace {

// Per-view tensors shared by the sweep and the fusion, on the images' device.
struct ViewTensors {
  at::Tensor rays;  // HxWx3: K^-1 (u, v, 1) at the pixel centres, so camera point = depth * ray
  at::Tensor R;     // 3x3 world -> camera
  at::Tensor t;     // 3
};

at::Tensor to_tensor(const Eigen::Matrix3d& m, const at::TensorOptions& opt) {
  at::Tensor out = at::empty({3, 3}, at::kFloat);
  auto a = out.accessor<float, 2>();
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) a[r][c] = static_cast<float>(m(r, c));
  return out.to(opt.device());
}

at::Tensor to_tensor(const Eigen::Vector3d& v, const at::TensorOptions& opt) {
  return at::tensor({static_cast<float>(v.x()), static_cast<float>(v.y()), static_cast<float>(v.z())}, at::kFloat)
      .to(opt.device());
}

Eigen::Matrix3d intrinsic_matrix(const Camera& c) {
  Eigen::Matrix3d K;
  K << c.fx, 0, c.cx, 0, c.fy, c.cy, 0, 0, 1;
  return K;
}

at::Tensor pixel_rays(const Camera& c, const at::TensorOptions& opt) {
  const at::Tensor xs = (at::arange(c.width, opt) + 0.5 - c.cx) / c.fx;
  const at::Tensor ys = (at::arange(c.height, opt) + 0.5 - c.cy) / c.fy;
  const at::Tensor x = xs.view({1, -1}).expand({c.height, c.width});
  const at::Tensor y = ys.view({-1, 1}).expand({c.height, c.width});
  return at::stack({x, y, at::ones_like(x)}, 2);
}

ViewTensors view_tensors(const Camera& c, const at::TensorOptions& opt) {
  return {pixel_rays(c, opt), to_tensor(c.R, opt), to_tensor(c.t, opt)};
}

// HxWx3 -> HxW luma, centred on 0: the windowed sums below then stay small, which keeps their float
// rounding far below the variances they are compared with (ZNCC ignores the offset).
at::Tensor centred_grey(const at::Tensor& image) {
  return image.select(2, 0) * 0.299 + image.select(2, 1) * 0.587 + image.select(2, 2) * 0.114 - 0.5;
}

// Sums over the k x k window around each pixel of the last two dimensions (zero outside), from running sums:
// a few passes per element whatever k is, several times faster than pooling on the CPU.
at::Tensor window_sum(const at::Tensor& x, int k) {
  const int r = k / 2;
  const at::Tensor cols = at::constant_pad_nd(x, {r + 1, r, 0, 0}).cumsum(-1);
  const int64_t w = cols.size(-1);
  const at::Tensor h = cols.slice(-1, k, w) - cols.slice(-1, 0, w - k);
  const at::Tensor rows = at::constant_pad_nd(h, {0, 0, r + 1, r}).cumsum(-2);
  const int64_t hh = rows.size(-2);
  return rows.slice(-2, k, hh) - rows.slice(-2, 0, hh - k);
}

// Reference-window statistics reused for every plane and source; sums over the n = k*k window pixels.
struct RefStats {
  at::Tensor grey;  // HxW, centred
  at::Tensor sum;   // HxW: sum of grey
  at::Tensor var;   // HxW: n * sum(grey^2) - sum(grey)^2 = n^2 * variance
  double n = 0;
};

RefStats ref_stats(const at::Tensor& image, int window) {
  RefStats ref;
  ref.grey = centred_grey(image);
  ref.sum = window_sum(ref.grey, window);
  ref.n = static_cast<double>(window) * window;
  ref.var = (ref.n * window_sum(ref.grey * ref.grey, window) - ref.sum * ref.sum).clamp_min(0.0);
  return ref;
}

// One source view prepared for warping. For a reference pixel at depth d, the source's grid_sample
// coordinates are gx = (d A[0] + b[0]) / z, gy = (d A[1] + b[1]) / z with z = d A[2] + b[2] its depth there:
// the plane-induced homography, with the pixel -> [-1, 1] normalisation folded in.
struct SourceWarp {
  at::Tensor A;  // 3xHxW at the reference size
  Eigen::Vector3d b;
  at::Tensor pixels;  // 1x2xHsxWs: centred grey, and ones (sampled, it says how much of a sample is inside)
};

SourceWarp source_warp(const Camera& ref, const at::Tensor& rays, const Camera& src, const at::Tensor& src_image) {
  const Eigen::Matrix3d R = src.R * ref.R.transpose();
  const Eigen::Vector3d t = src.t - R * ref.t;
  // Pixel (u, v, w) = K (R X + t); align_corners=false maps u/w in [0, width] to [-1, 1]: gx = (2u/w)/W - 1.
  Eigen::Matrix3d N;
  N << 2.0 / src.width, 0, -1, 0, 2.0 / src.height, -1, 0, 0, 1;
  const Eigen::Matrix3d M = N * intrinsic_matrix(src);
  SourceWarp w;
  w.A = at::matmul(rays, to_tensor(Eigen::Matrix3d(M * R), rays.options()).t()).permute({2, 0, 1}).contiguous();
  w.b = M * t;
  const at::Tensor g = centred_grey(src_image.to(at::kFloat));
  w.pixels = at::stack({g, at::ones_like(g)}, 0).unsqueeze(0);
  return w;
}

// ZNCC of the reference windows with the source warped by each plane of `depths`: Dc x H x W, -1 where the
// window leaves either image or the source patch is flat. Written to keep the number of passes over the
// Dc x H x W temporaries low: this is where the initialisation spends its time.
at::Tensor zncc_for_planes(const RefStats& ref, const SourceWarp& src, const at::Tensor& depths) {
  const int64_t planes = depths.size(0), H = src.A.size(1), W = src.A.size(2);
  const int window = static_cast<int>(std::lround(std::sqrt(ref.n)));
  const auto opt = src.A.options();
  const at::Tensor d = depths.view({planes, 1, 1});
  const auto affine = [&](int row, double offset) {
    return at::addcmul(at::scalar_tensor(offset, opt), d, src.A[row]);
  };
  // Behind the source camera the depth is clamped to a tiny positive value: the coordinates then land far
  // outside the image, where the sampled ones-channel says "invalid".
  const at::Tensor inv_z = affine(2, src.b.z()).clamp_min_(1e-6).reciprocal_();
  at::Tensor grid = at::empty({planes, H, W, 2}, opt);
  at::Tensor gx = grid.select(3, 0), gy = grid.select(3, 1);  // views: mul_out writes into the grid
  at::mul_out(gx, affine(0, src.b.x()), inv_z);
  at::mul_out(gy, affine(1, src.b.y()), inv_z);
  grid.clamp_(-10.0, 10.0);  // keeps grid_sample's integer pixel indices in range
  // Planes stacked along the height: one grid_sample call for the whole chunk.
  const at::Tensor sampled = at::grid_sampler(src.pixels, grid.view({1, planes * H, W, 2}), /*bilinear*/ 0,
                                              /*zeros*/ 0, false)
                                 .view({2, planes, H, W});
  const at::Tensor s = sampled[0];
  at::Tensor terms = at::empty({4, planes, H, W}, opt);
  terms[0].copy_(s);
  at::Tensor squares = terms[1], products = terms[2];
  at::mul_out(squares, s, s);
  at::mul_out(products, s, ref.grey);
  terms[3].copy_(sampled[1]);
  const at::Tensor sums = window_sum(terms, window);
  const at::Tensor var_s = at::addcmul(ref.n * sums[1], sums[0], sums[0], -1.0);
  at::Tensor zncc = at::addcmul(ref.n * sums[2], sums[0], ref.sum, -1.0);
  zncc.mul_((ref.var * var_s).clamp_min_(1e-12).rsqrt_());
  const at::Tensor bad = (sums[3] < ref.n - 0.01).logical_or_(var_s < 1e-8 * ref.n * ref.n);
  return zncc.masked_fill_(bad, -1.0);
}

// Occlusion-tolerant combination over sources: the mean of the better half of the per-source scores.
at::Tensor aggregate_scores(const at::Tensor& per_source /* S x Dc x H x W */) {
  const int64_t S = per_source.size(0);
  const int64_t k = (S + 1) / 2;
  if (k == S) return per_source.mean(0);
  if (k == 1) return std::get<0>(per_source.max(0));
  // topk along a leading dimension is slow on the CPU: move the sources last first.
  const at::Tensor last = per_source.permute({1, 2, 3, 0}).contiguous();
  return std::get<0>(last.topk(k, 3)).mean(3);
}

// Per-view geometric data for the fusion.
struct FusionView {
  const DepthMap* map;
  ViewTensors tensors;
  at::Tensor depth_flat, image_flat, rays_flat;
  at::Tensor consumed;  // H*W bool: already merged into a fused point
};

struct Projection {
  at::Tensor u, v, z;
};

Projection project(const at::Tensor& world /* M x 3 */, const Camera& c, const ViewTensors& t) {
  const at::Tensor p = at::matmul(world, t.R.t()) + t.t;
  const at::Tensor z = p.select(1, 2);
  return {p.select(1, 0) / z * c.fx + c.cx, p.select(1, 1) / z * c.fy + c.cy, z};
}

at::Tensor to_world(const at::Tensor& cam_points /* M x 3 */, const ViewTensors& t) {
  return at::matmul(cam_points - t.t, t.R);  // R^T (p - t), with points as rows
}

}  // namespace

std::optional<std::pair<double, double>> view_depth_range(const Camera& camera, const at::Tensor& xyz,
                                                          const DenseOptions& options) {
  std::vector<double> depths;
  if (xyz.defined() && xyz.numel() > 0) {
    const at::Tensor pts = xyz.to(at::kCPU, at::kDouble).contiguous();
    const auto a = pts.accessor<double, 2>();
    for (int64_t i = 0; i < pts.size(0); ++i) {
      const Eigen::Vector3d X(a[i][0], a[i][1], a[i][2]);
      const Eigen::Vector3d p = camera.R * X + camera.t;
      if (!(p.z() > 0)) continue;
      const double u = camera.fx * p.x() / p.z() + camera.cx, v = camera.fy * p.y() / p.z() + camera.cy;
      if (u >= 0 && u < camera.width && v >= 0 && v < camera.height) depths.push_back(p.z());
    }
  }
  if (static_cast<int>(depths.size()) >= options.min_points_for_range) {
    std::sort(depths.begin(), depths.end());
    const auto quantile = [&](double q) { return depths[static_cast<size_t>(q * (depths.size() - 1))]; };
    return std::make_pair(quantile(0.01) / (1.0 + options.depth_margin), quantile(0.99) * (1.0 + options.depth_margin));
  }
  if (camera.near > 0 && camera.far > camera.near) return std::make_pair(camera.near, camera.far);
  return std::nullopt;
}

std::vector<int> select_neighbors(int ref, const std::vector<Camera>& cameras,
                                  const std::vector<std::vector<int>>& point_views, int max_neighbors) {
  const int n = static_cast<int>(cameras.size());
  std::vector<double> score(n, 0.0);
  for (const auto& views : point_views)
    if (std::find(views.begin(), views.end(), ref) != views.end())
      for (int v : views) score[v] += 1.0;
  std::vector<int> order;
  for (int s = 0; s < n; ++s)
    if (s != ref && score[s] > 0) order.push_back(s);
  if (order.empty()) {
    // No shared sparse points: views facing the same way and not at the same spot.
    for (int s = 0; s < n; ++s) {
      if (s == ref) continue;
      score[s] = cameras[ref].forward().dot(cameras[s].forward());
      if (score[s] > 0 && (cameras[ref].center() - cameras[s].center()).norm() > 1e-9) order.push_back(s);
    }
  }
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return score[a] > score[b]; });
  if (static_cast<int>(order.size()) > max_neighbors) order.resize(max_neighbors);
  return order;
}

DepthMap plane_sweep(const Camera& ref_camera, const at::Tensor& ref_image, const std::vector<Camera>& src_cameras,
                     const std::vector<at::Tensor>& src_images, double min_depth, double max_depth,
                     const DenseOptions& options) {
  const at::Tensor image = ref_image.to(at::kFloat).contiguous();
  const auto opt = image.options();
  const int64_t D = std::max(options.num_planes, 3), H = ref_camera.height, W = ref_camera.width;
  const RefStats ref = ref_stats(image, options.window);
  const at::Tensor rays = pixel_rays(ref_camera, opt);
  std::vector<SourceWarp> sources;
  for (size_t s = 0; s < src_cameras.size(); ++s)
    sources.push_back(source_warp(ref_camera, rays, src_cameras[s], src_images[s].to(opt.device())));

  // Planes uniform in inverse depth: equal steps in disparity, i.e. in pixels along the epipolar lines.
  const double inv_near = 1.0 / min_depth, inv_far = 1.0 / max_depth;
  const at::Tensor inv = at::linspace(inv_near, inv_far, D, opt);
  const at::Tensor depths = inv.reciprocal();
  at::Tensor scores = at::empty({D, H, W}, opt);
  at::Tensor support = at::empty({D, H, W}, opt.dtype(at::kByte));
  for (int64_t p0 = 0; p0 < D; p0 += options.planes_per_chunk) {
    const int64_t p1 = std::min<int64_t>(D, p0 + options.planes_per_chunk);
    std::vector<at::Tensor> per_source;
    for (const SourceWarp& src : sources) per_source.push_back(zncc_for_planes(ref, src, depths.slice(0, p0, p1)));
    const at::Tensor stacked = at::stack(per_source, 0);
    scores.slice(0, p0, p1).copy_(aggregate_scores(stacked));
    support.slice(0, p0, p1).copy_((stacked >= options.min_score).sum(0).to(at::kByte));
  }

  // Winner-take-all, confidence from the runner-up outside the winner's neighbourhood.
  const auto [best, idx] = scores.max(0);
  const at::Tensor plane = at::arange(D, opt.dtype(at::kLong)).view({D, 1, 1});
  const at::Tensor second = scores.masked_fill((plane - idx.unsqueeze(0)).abs() <= 2, -1.0).amax(0);
  const at::Tensor margin = best - second;
  // Sub-plane refinement: vertex of the parabola through the winner and its two neighbours.
  const at::Tensor c_minus = scores.gather(0, (idx - 1).clamp(0, D - 1).unsqueeze(0)).squeeze(0);
  const at::Tensor c_plus = scores.gather(0, (idx + 1).clamp(0, D - 1).unsqueeze(0)).squeeze(0);
  const at::Tensor denom = c_minus - 2.0 * best + c_plus;
  const at::Tensor offset =
      at::where(denom < -1e-6, 0.5 * (c_minus - c_plus) / denom.clamp_max(-1e-6), at::zeros_like(denom))
          .clamp(-0.5, 0.5);
  const at::Tensor inv_depth = inv_near + (idx.to(at::kFloat) + offset) * ((inv_far - inv_near) / (D - 1));
  const at::Tensor sup = support.gather(0, idx.unsqueeze(0)).squeeze(0);
  // The first and last planes are where out-of-range surfaces end up: no depth there.
  const at::Tensor ok = (best >= options.min_score) & (margin >= options.min_margin) &
                        (ref.var.sqrt() >= options.min_texture_std * ref.n) & (idx > 0) & (idx < D - 1) & (sup >= 1) &
                        (inv_depth > 0);
  DepthMap map;
  map.camera = ref_camera;
  map.image = image;
  map.depth = at::where(ok, inv_depth.reciprocal(), at::zeros_like(inv_depth));
  map.score = best;
  map.margin = margin;
  map.support = sup.to(at::kInt);
  return map;
}

PointCloud fuse_depth_maps(const std::vector<DepthMap>& maps, const DenseOptions& options) {
  std::vector<FusionView> views;
  for (const DepthMap& m : maps) {
    FusionView v{&m, view_tensors(m.camera, m.depth.options()), m.depth.reshape(-1), m.image.reshape({-1, 3}), {}, {}};
    v.rays_flat = v.tensors.rays.reshape({-1, 3});
    v.consumed = at::zeros({m.depth.numel()}, m.depth.options().dtype(at::kBool));
    views.push_back(std::move(v));
  }
  std::vector<at::Tensor> xyz_parts, rgb_parts;
  for (size_t r = 0; r < views.size(); ++r) {
    FusionView& ref = views[r];
    const at::Tensor idx = ((ref.depth_flat > 0) & ~ref.consumed).nonzero().squeeze(1);
    if (idx.numel() == 0) continue;
    const int64_t W = ref.map->camera.width;
    const at::Tensor pu = (idx % W).to(at::kFloat) + 0.5, pv = (idx / W).to(at::kFloat) + 0.5;
    const at::Tensor world =
        to_world(ref.rays_flat.index_select(0, idx) * ref.depth_flat.index_select(0, idx).unsqueeze(1), ref.tensors);
    const at::Tensor colour = ref.image_flat.index_select(0, idx);
    at::Tensor sum_xyz = world.clone(), sum_rgb = colour.clone();
    at::Tensor count = at::ones({idx.numel()}, world.options());
    std::vector<std::pair<at::Tensor, at::Tensor>> agreeing;  // per source: (agrees, its pixel index)
    for (size_t s = 0; s < views.size(); ++s) {
      if (s == r) continue;
      const FusionView& src = views[s];
      const Camera& sc = src.map->camera;
      const Projection p = project(world, sc, src.tensors);
      const at::Tensor px = p.u.floor().to(at::kLong), py = p.v.floor().to(at::kLong);
      const at::Tensor inside = (p.z > 0) & (px >= 0) & (px < sc.width) & (py >= 0) & (py < sc.height);
      const at::Tensor pixel = py.clamp(0, sc.height - 1) * sc.width + px.clamp(0, sc.width - 1);
      const at::Tensor ds = src.depth_flat.index_select(0, pixel);
      // Geometric check both ways: same depth seen from the source, and the source's own 3D point lands
      // back on the reference pixel.
      at::Tensor agrees = inside & (ds > 0) & ((ds - p.z).abs() < options.max_relative_depth_diff * ds);
      const at::Tensor back = to_world(src.rays_flat.index_select(0, pixel) * ds.unsqueeze(1), src.tensors);
      const Projection q = project(back, ref.map->camera, ref.tensors);
      agrees &= (q.z > 0) &
                ((q.u - pu).square() + (q.v - pv).square() < options.max_reprojection_px * options.max_reprojection_px);
      const at::Tensor src_colour = src.image_flat.index_select(0, pixel);
      agrees &= (src_colour - colour).abs().mean(1) < options.max_colour_diff;
      const at::Tensor w = agrees.to(at::kFloat).unsqueeze(1);
      sum_xyz += back * w;
      sum_rgb += src_colour * w;
      count += agrees.to(at::kFloat);
      agreeing.emplace_back(agrees, pixel);
    }
    const at::Tensor keep = count >= 1.0 + options.min_consistent_views;
    xyz_parts.push_back((sum_xyz / count.unsqueeze(1)).index({keep}));
    rgb_parts.push_back((sum_rgb / count.unsqueeze(1)).index({keep}));
    // The source pixels that joined a kept point are that point already: they will not seed another.
    size_t k = 0;
    for (size_t s = 0; s < views.size(); ++s) {
      if (s == r) continue;
      const auto& [agrees, pixel] = agreeing[k++];
      views[s].consumed.index_fill_(0, pixel.index({agrees & keep}), true);
    }
  }
  if (xyz_parts.empty()) {
    const auto opt = maps.empty() ? at::TensorOptions(at::kFloat) : maps[0].depth.options();
    return {at::zeros({0, 3}, opt), at::zeros({0, 3}, opt)};
  }
  return {at::cat(xyz_parts, 0), at::cat(rgb_parts, 0).clamp(0.0, 1.0)};
}

namespace {

// Voxel key of every point: 21 bits per axis in one int64; outliers beyond that range share the edge voxels.
at::Tensor voxel_keys(const at::Tensor& xyz, double voxel_size) {
  const at::Tensor lo = std::get<0>(xyz.min(0));
  const at::Tensor cell = ((xyz - lo) / voxel_size).floor().to(at::kLong).clamp(0, (1 << 21) - 1);
  return cell.select(1, 0) * (int64_t{1} << 42) + cell.select(1, 1) * (int64_t{1} << 21) + cell.select(1, 2);
}

int64_t occupied_voxels(const at::Tensor& xyz, double voxel_size) {
  return std::get<0>(at::_unique2(voxel_keys(xyz, voxel_size), /*sorted=*/false)).size(0);
}

}  // namespace

std::vector<at::Tensor> voxel_means(const at::Tensor& xyz, double voxel_size, const std::vector<at::Tensor>& values) {
  if (xyz.size(0) == 0) return values;
  const auto [unique, inverse, counts] = at::_unique2(voxel_keys(xyz, voxel_size), /*sorted=*/true,
                                                      /*return_inverse=*/true, /*return_counts=*/true);
  std::vector<at::Tensor> means;
  for (const at::Tensor& v : values) {
    const at::Tensor c = counts.to(v.scalar_type()).unsqueeze(1);
    means.push_back(at::zeros({unique.size(0), v.size(1)}, v.options()).index_add_(0, inverse, v) / c);
  }
  return means;
}

PointCloud voxel_downsample(const PointCloud& points, double voxel_size) {
  const std::vector<at::Tensor> means = voxel_means(points.xyz, voxel_size, {points.xyz, points.rgb});
  return {means[0], means[1]};
}

double capping_voxel_size(const at::Tensor& xyz, int64_t max_points) {
  if (xyz.size(0) <= max_points) return 0.0;
  const auto count = [&](double size) { return occupied_voxels(xyz, size); };
  // Robust extent (1%..99% per axis) so that a few far points do not set the scale. Fused points lie on
  // surfaces, so the occupied voxel count goes like extent^2 / size^2: start near that size, bracket the
  // cap, then bisect (in log size) for the smallest voxel that meets it, keeping as much detail as allowed.
  const at::Tensor q = at::tensor({0.01, 0.99}, xyz.options());
  const at::Tensor bounds = at::quantile(xyz, q, 0);
  const double extent = std::max((bounds[1] - bounds[0]).norm().item<double>(), 1e-9);
  double hi = extent / std::sqrt(static_cast<double>(max_points));
  while (count(hi) > max_points) hi *= 2.0;
  double lo = hi / 2.0;
  for (int i = 0; i < 30 && count(lo) <= max_points; ++i) lo /= 2.0;
  for (int i = 0; i < 8; ++i) {
    const double mid = std::sqrt(lo * hi);
    (count(mid) > max_points ? lo : hi) = mid;
  }
  return hi;
}

PointCloud cap_points(const PointCloud& points, int64_t max_points, double* voxel_size) {
  *voxel_size = capping_voxel_size(points.xyz, max_points);
  return *voxel_size > 0 ? voxel_downsample(points, *voxel_size) : points;
}

absl::StatusOr<DenseResult> dense_reconstruct(const std::vector<Camera>& cameras, const std::vector<at::Tensor>& images,
                                              const SparseResult& sparse, const DenseOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  if (cameras.size() != images.size())
    return absl::InvalidArgumentError(absl::StrCat(cameras.size(), " cameras but ", images.size(), " images"));
  if (cameras.size() < 2) return absl::FailedPreconditionError("multi-view stereo needs at least two views");
  if (options.window < 3 || options.window % 2 == 0)
    return absl::InvalidArgumentError(absl::StrCat("ZNCC window must be odd and >= 3, got ", options.window));
  for (size_t i = 0; i < cameras.size(); ++i)
    if (images[i].dim() != 3 || images[i].size(0) != cameras[i].height || images[i].size(1) != cameras[i].width)
      return absl::InvalidArgumentError(absl::StrCat("image of ", cameras[i].name, " does not match its camera"));
  const auto [cams, imgs] = working_views(cameras, images, options.max_image_side);

  DenseResult result;
  for (size_t r = 0; r < cams.size(); ++r) {
    const auto range = view_depth_range(cameras[r], sparse.points.xyz, options);
    const std::vector<int> neighbors =
        select_neighbors(static_cast<int>(r), cams, sparse.point_views, options.max_neighbors);
    if (!range || neighbors.empty()) {
      result.stats.depth_pixels.push_back(0);
      continue;
    }
    std::vector<Camera> src_cams;
    std::vector<at::Tensor> src_imgs;
    for (int s : neighbors) {
      src_cams.push_back(cams[s]);
      src_imgs.push_back(imgs[s]);
    }
    result.depth_maps.push_back(
        plane_sweep(cams[r], imgs[r], src_cams, src_imgs, range->first, range->second, options));
    result.stats.depth_pixels.push_back((result.depth_maps.back().depth > 0).sum().item<int64_t>());
  }
  if (result.depth_maps.empty())
    return absl::FailedPreconditionError("no view has a depth range (no sparse points, no near/far) or a neighbour");

  const PointCloud fused = fuse_depth_maps(result.depth_maps, options);

  result.stats.fused_before_voxel = fused.xyz.size(0);
  result.points = cap_points(fused, options.max_points, &result.stats.voxel_size);
  result.points.xyz = result.points.xyz.to(at::kCPU);
  result.points.rgb = result.points.rgb.to(at::kCPU);
  result.stats.points = result.points.xyz.size(0);
  result.stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return result;
}

}  // namespace gaps

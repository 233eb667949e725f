#include "gs_trainer/init/sparse.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <numeric>

#include <ATen/ATen.h>
#include <Eigen/Dense>
#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include "absl/strings/str_cat.h"
#include "gs_trainer/init/working_view.h"

namespace gaps {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kRadToDeg = 180.0 / 3.14159265358979323846;

Eigen::Matrix3d intrinsic_matrix(const Camera& c) {
  Eigen::Matrix3d K;
  K << c.fx, 0, c.cx, 0, c.fy, c.cy, 0, 0, 1;
  return K;
}

Eigen::Matrix3d skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

// Centres closer than this (relative to their distance from the origin) give no usable epipolar geometry.
bool degenerate_baseline(const Camera& a, const Camera& b) {
  const double scale = 1.0 + a.center().norm() + b.center().norm();
  return (a.center() - b.center()).norm() < 1e-9 * scale;
}

double reprojection_error(const Camera& camera, const Observation& o, const Eigen::Vector3d& xyz) {
  const auto p = project_point(camera, xyz);
  return p ? (*p - o.xy).norm() : kInf;  // behind the camera: never acceptable
}

double summed_squared_error(const std::vector<Camera>& cameras, const std::vector<Observation>& obs,
                            const Eigen::Vector3d& xyz) {
  double sum = 0;
  for (const Observation& o : obs) {
    const double e = reprojection_error(cameras[o.view], o, xyz);
    sum += e * e;
  }
  return sum;
}

// HxWx3 float in [0, 1] -> 8-bit grey CPU tensor (kept alive by the caller while a cv::Mat wraps it).
at::Tensor grey_u8(const at::Tensor& image) {
  const at::Tensor rgb = image.to(at::kCPU, at::kFloat);
  const at::Tensor grey = rgb.select(2, 0) * 0.299 + rgb.select(2, 1) * 0.587 + rgb.select(2, 2) * 0.114;
  return (grey * 255.0).round().clamp(0, 255).to(at::kByte).contiguous();
}

// Nearest-pixel colour of every observation, averaged: matches are sub-pixel, colours need not be.
Eigen::Vector3f mean_colour(const std::vector<at::TensorAccessor<float, 3>>& images,
                            const std::vector<Observation>& obs) {
  Eigen::Vector3f sum = Eigen::Vector3f::Zero();
  for (const Observation& o : obs) {
    const auto& img = images[o.view];
    const int x = std::clamp(static_cast<int>(std::floor(o.xy.x())), 0, static_cast<int>(img.size(1)) - 1);
    const int y = std::clamp(static_cast<int>(std::floor(o.xy.y())), 0, static_cast<int>(img.size(0)) - 1);
    for (int c = 0; c < 3; ++c) sum(c) += img[y][x][c];
  }
  return sum / static_cast<float>(obs.size());
}

double median(std::vector<double> values) {
  if (values.empty()) return 0.0;
  const size_t mid = values.size() / 2;
  std::nth_element(values.begin(), values.begin() + mid, values.end());
  return values[mid];
}

// Homogeneous pixel positions as an Nx3 float tensor.
at::Tensor homogeneous(const std::vector<Eigen::Vector2d>& xy) {
  at::Tensor h = at::ones({static_cast<int64_t>(xy.size()), 3}, at::kFloat);
  auto a = h.accessor<float, 2>();
  for (size_t i = 0; i < xy.size(); ++i) {
    a[i][0] = static_cast<float>(xy[i].x());
    a[i][1] = static_cast<float>(xy[i].y());
  }
  return h;
}

// epipolar_distance for every pair (rows: xa, columns: xb), as a float tensor.
at::Tensor epipolar_distances(const Eigen::Matrix3d& F, const std::vector<Eigen::Vector2d>& xa,
                              const std::vector<Eigen::Vector2d>& xb) {
  const Eigen::Matrix3d Fn = F / std::max(F.norm(), 1e-300);  // scale-free: keeps float products in range
  at::Tensor f = at::empty({3, 3}, at::kFloat);
  for (int i = 0; i < 9; ++i) f.view(-1)[i] = static_cast<float>(Fn(i / 3, i % 3));
  const at::Tensor ha = homogeneous(xa), hb = homogeneous(xb);
  const at::Tensor lines_b = at::mm(ha, f.t());  // F xa: each a's line in b
  const at::Tensor lines_a = at::mm(hb, f);      // F^T xb: each b's line in a
  const at::Tensor algebraic = at::mm(lines_b, hb.t()).abs();
  const at::Tensor norm_b = lines_b.slice(1, 0, 2).norm(2, 1).clamp_min(1e-30).unsqueeze(1);
  const at::Tensor norm_a = lines_a.slice(1, 0, 2).norm(2, 1).clamp_min(1e-30).unsqueeze(0);
  return at::maximum(algebraic / norm_b, algebraic / norm_a);
}

struct UnionFind {
  std::vector<int> parent;
  explicit UnionFind(int n) : parent(n) { std::iota(parent.begin(), parent.end(), 0); }
  int find(int x) {
    while (parent[x] != x) x = parent[x] = parent[parent[x]];
    return x;
  }
  void unite(int a, int b) { parent[find(a)] = find(b); }
};

}  // namespace

absl::Status check_view_images(const std::vector<Camera>& cameras, const std::vector<at::Tensor>& images) {
  if (cameras.size() != images.size())
    return absl::InvalidArgumentError(
        absl::StrCat(cameras.size(), " cameras but ", images.size(), " images for the initialisation"));
  for (size_t i = 0; i < cameras.size(); ++i) {
    const at::Tensor& im = images[i];
    if (im.dim() != 3 || im.size(2) != 3 || im.size(0) != cameras[i].height || im.size(1) != cameras[i].width)
      return absl::InvalidArgumentError(
          absl::StrCat("image of ", cameras[i].name, " is not ", cameras[i].height, "x", cameras[i].width, "x3"));
  }
  return absl::OkStatus();
}

std::optional<Eigen::Vector2d> project_point(const Camera& camera, const Eigen::Vector3d& xyz) {
  const Eigen::Vector3d p = camera.R * xyz + camera.t;
  if (!(p.z() > 0)) return std::nullopt;
  return Eigen::Vector2d(camera.fx * p.x() / p.z() + camera.cx, camera.fy * p.y() / p.z() + camera.cy);
}

Eigen::Matrix3d fundamental_matrix(const Camera& a, const Camera& b) {
  const Eigen::Matrix3d R = b.R * a.R.transpose();  // camera a -> camera b
  const Eigen::Vector3d t = b.t - R * a.t;
  const Eigen::Matrix3d E = skew(t) * R;
  return intrinsic_matrix(b).inverse().transpose() * E * intrinsic_matrix(a).inverse();
}

double epipolar_distance(const Eigen::Matrix3d& F, const Eigen::Vector2d& xa, const Eigen::Vector2d& xb) {
  const Eigen::Vector3d ha = xa.homogeneous(), hb = xb.homogeneous();
  const Eigen::Vector3d line_b = F * ha, line_a = F.transpose() * hb;
  const double algebraic = std::abs(hb.dot(line_b));
  const double db = algebraic / std::max(line_b.head<2>().norm(), 1e-300);
  const double da = algebraic / std::max(line_a.head<2>().norm(), 1e-300);
  return std::max(da, db);
}

std::vector<Match> epipolar_filter(const Camera& ca, const Camera& cb, const std::vector<Eigen::Vector2d>& xa,
                                   const std::vector<Eigen::Vector2d>& xb, const std::vector<Match>& matches,
                                   double max_px) {
  const Eigen::Matrix3d F = fundamental_matrix(ca, cb);
  std::vector<Match> kept;
  for (const Match& m : matches)
    if (epipolar_distance(F, xa[m.a], xb[m.b]) < max_px) kept.push_back(m);
  return kept;
}

Features detect_features(const at::Tensor& image, const SparseOptions& options) {
  const at::Tensor grey = grey_u8(image);
  const cv::Mat mat(static_cast<int>(grey.size(0)), static_cast<int>(grey.size(1)), CV_8U, grey.data_ptr());
  cv::Ptr<cv::SIFT> sift = cv::SIFT::create(options.max_features, 3, options.contrast_threshold);
  std::vector<cv::KeyPoint> keypoints;
  cv::Mat descriptors;
  sift->detectAndCompute(mat, cv::noArray(), keypoints, descriptors);
  Features f;
  for (const cv::KeyPoint& k : keypoints) f.xy.emplace_back(k.pt.x + 0.5, k.pt.y + 0.5);  // OpenCV: centres at integers
  if (keypoints.empty()) {
    f.descriptors = at::zeros({0, 128}, at::kFloat);
  } else {
    const at::Tensor raw = at::from_blob(descriptors.ptr<float>(), {descriptors.rows, descriptors.cols}, at::kFloat);
    f.descriptors = raw / raw.norm(2, 1, true).clamp_min(1e-12);
  }
  return f;
}

std::vector<Match> match_features(const Features& a, const Features& b, const SparseOptions& options,
                                  const Eigen::Matrix3d* F) {
  const at::Tensor& da = a.descriptors;
  const at::Tensor& db = b.descriptors;
  if (da.size(0) < 1 || db.size(0) < 1) return {};
  // All squared distances of unit descriptors with one matrix product: exact nearest neighbours in both
  // directions at once.
  at::Tensor d2 = (2.0 - 2.0 * at::mm(da, db.t())).clamp_min(0.0);
  const double max_d2 = 2.0 - 2.0 * std::cos(options.max_descriptor_angle);
  d2.masked_fill_(d2 > max_d2, INFINITY);
  if (F) d2.masked_fill_(epipolar_distances(*F, a.xy, b.xy) >= options.max_epipolar_px, INFINITY);
  // A missing second neighbour counts as infinitely far: the ratio test then passes.
  const at::Tensor pad_b = at::full({da.size(0), 1}, INFINITY, d2.options());
  const at::Tensor pad_a = at::full({1, db.size(0) + 1}, INFINITY, d2.options());
  const at::Tensor padded = at::cat({at::cat({d2, pad_b}, 1), pad_a}, 0);
  const auto [dist_ab, idx_ab] = padded.topk(2, 1, /*largest=*/false);  // per keypoint of a: two nearest of b
  const auto [dist_ba, idx_ba] = padded.topk(2, 0, /*largest=*/false);  // per keypoint of b: two nearest of a
  const double r2 = options.ratio * options.ratio;
  const auto dab = dist_ab.accessor<float, 2>();
  const auto iab = idx_ab.accessor<int64_t, 2>();
  const auto dba = dist_ba.accessor<float, 2>();
  const auto iba = idx_ba.accessor<int64_t, 2>();
  std::vector<Match> matches;
  for (int64_t i = 0; i < da.size(0); ++i) {
    const int64_t j = iab[i][0];
    if (!std::isfinite(dab[i][0]) || !(dab[i][0] < r2 * dab[i][1])) continue;
    if (iba[0][j] != i || !(dba[0][j] < r2 * dba[1][j])) continue;
    matches.push_back({static_cast<int>(i), static_cast<int>(j)});
  }
  return matches;
}

std::vector<std::vector<std::pair<int, int>>> build_tracks(
    const std::vector<int>& keypoints_per_view, const std::vector<std::vector<std::vector<Match>>>& matches) {
  const int views = static_cast<int>(keypoints_per_view.size());
  std::vector<int> offset(views + 1, 0);
  for (int v = 0; v < views; ++v) offset[v + 1] = offset[v] + keypoints_per_view[v];
  UnionFind uf(offset[views]);
  for (int i = 0; i < views; ++i)
    for (int j = i + 1; j < views; ++j)
      for (const Match& m : matches[i][j]) uf.unite(offset[i] + m.a, offset[j] + m.b);

  std::vector<std::vector<std::pair<int, int>>> components(offset[views]);
  for (int v = 0; v < views; ++v)
    for (int k = 0; k < keypoints_per_view[v]; ++k) components[uf.find(offset[v] + k)].push_back({v, k});

  std::vector<std::vector<std::pair<int, int>>> tracks;
  for (auto& c : components) {
    if (c.size() < 2) continue;
    std::vector<int> per_view(views, 0);
    for (const auto& [v, k] : c) ++per_view[v];
    std::vector<std::pair<int, int>> track;
    for (const auto& node : c)
      if (per_view[node.first] == 1) track.push_back(node);
    if (track.size() >= 2) tracks.push_back(std::move(track));
  }
  return tracks;
}

Eigen::Vector3d triangulate_dlt(const std::vector<Camera>& cameras, const std::vector<Observation>& observations) {
  // Normalised coordinates (K^-1 x) keep the system well conditioned without Hartley scaling.
  Eigen::MatrixXd A(2 * observations.size(), 4);
  for (size_t i = 0; i < observations.size(); ++i) {
    const Camera& c = cameras[observations[i].view];
    const double nx = (observations[i].xy.x() - c.cx) / c.fx;
    const double ny = (observations[i].xy.y() - c.cy) / c.fy;
    Eigen::Matrix<double, 3, 4> P;
    P << c.R, c.t;
    A.row(2 * i) = nx * P.row(2) - P.row(0);
    A.row(2 * i + 1) = ny * P.row(2) - P.row(1);
  }
  const Eigen::JacobiSVD<Eigen::MatrixXd> svd(A, Eigen::ComputeFullV);
  const Eigen::Vector4d X = svd.matrixV().col(3);
  const double w = std::abs(X(3)) < 1e-15 ? std::copysign(1e-15, X(3)) : X(3);  // at infinity: far away
  return X.head<3>() / w;
}

Eigen::Vector3d refine_point(const std::vector<Camera>& cameras, const std::vector<Observation>& observations,
                             const Eigen::Vector3d& xyz, int iterations) {
  Eigen::Vector3d X = xyz;
  double cost = summed_squared_error(cameras, observations, X);
  for (int it = 0; it < iterations && std::isfinite(cost); ++it) {
    Eigen::Matrix3d JtJ = Eigen::Matrix3d::Zero();
    Eigen::Vector3d Jtr = Eigen::Vector3d::Zero();
    for (const Observation& o : observations) {
      const Camera& c = cameras[o.view];
      const Eigen::Vector3d p = c.R * X + c.t;
      const double iz = 1.0 / p.z();
      const Eigen::Vector2d r(c.fx * p.x() * iz + c.cx - o.xy.x(), c.fy * p.y() * iz + c.cy - o.xy.y());
      Eigen::Matrix<double, 2, 3> dp;  // d(pixel)/d(camera point)
      dp << c.fx * iz, 0, -c.fx * p.x() * iz * iz, 0, c.fy * iz, -c.fy * p.y() * iz * iz;
      const Eigen::Matrix<double, 2, 3> J = dp * c.R;
      JtJ += J.transpose() * J;
      Jtr += J.transpose() * r;
    }
    const Eigen::Vector3d step = -JtJ.ldlt().solve(Jtr);
    if (!step.allFinite()) break;
    // Plain Gauss-Newton can overshoot on near-degenerate rays: halve the step until the cost drops.
    bool improved = false;
    for (double s = 1.0; s > 1e-3 && !improved; s *= 0.5) {
      const double c = summed_squared_error(cameras, observations, X + s * step);
      if (c < cost) {
        X += s * step;
        cost = c;
        improved = true;
      }
    }
    if (!improved) break;
  }
  return X;
}

double triangulation_angle_deg(const std::vector<Camera>& cameras, const std::vector<Observation>& observations,
                               const Eigen::Vector3d& xyz) {
  double best = 0;
  for (size_t i = 0; i < observations.size(); ++i) {
    const Eigen::Vector3d ri = (xyz - cameras[observations[i].view].center()).normalized();
    for (size_t j = i + 1; j < observations.size(); ++j) {
      const Eigen::Vector3d rj = (xyz - cameras[observations[j].view].center()).normalized();
      best = std::max(best, std::acos(std::clamp(ri.dot(rj), -1.0, 1.0)) * kRadToDeg);
    }
  }
  return best;
}

TrackVerdict triangulate_track(const std::vector<Camera>& cameras, std::vector<Observation> observations,
                               const SparseOptions& options, TriangulatedPoint* out) {
  while (observations.size() >= 2) {
    const Eigen::Vector3d X =
        refine_point(cameras, observations, triangulate_dlt(cameras, observations), options.refine_iterations);
    std::vector<double> errors;
    for (const Observation& o : observations) errors.push_back(reprojection_error(cameras[o.view], o, X));
    const size_t worst = std::max_element(errors.begin(), errors.end()) - errors.begin();
    if (errors[worst] < options.max_reprojection_px) {
      if (triangulation_angle_deg(cameras, observations, X) < options.min_angle_deg) return TrackVerdict::kAngle;
      out->xyz = X;
      out->observations = std::move(observations);
      out->errors_px = std::move(errors);
      return TrackVerdict::kKept;
    }
    if (observations.size() == 2)
      return std::isinf(errors[worst]) ? TrackVerdict::kCheirality : TrackVerdict::kReprojection;
    observations.erase(observations.begin() + worst);
  }
  return TrackVerdict::kReprojection;
}

absl::Status validate_sparse_options(const SparseOptions& options) {
  if (options.max_image_side != 0 && options.max_image_side < kMinSparseImageSide)
    return absl::InvalidArgumentError(absl::StrCat("max_image_side must be 0 (the views as given) or at least ",
                                                   kMinSparseImageSide, ", got ", options.max_image_side));
  return absl::OkStatus();
}

absl::StatusOr<SparseResult> sparse_reconstruct(const std::vector<Camera>& cameras,
                                                const std::vector<at::Tensor>& images, const SparseOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  if (absl::Status s = check_view_images(cameras, images); !s.ok()) return s;
  if (absl::Status s = validate_sparse_options(options); !s.ok()) return s;
  if (options.max_image_side > 0) {
    const WorkingViews small = working_views(cameras, images, options.max_image_side);
    SparseOptions as_given = options;
    as_given.max_image_side = 0;
    absl::StatusOr<SparseResult> result = sparse_reconstruct(small.cameras, small.images, as_given);
    if (result.ok())
      result->stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    return result;
  }
  const int views = static_cast<int>(cameras.size());
  SparseResult result;
  SparseStats& stats = result.stats;

  std::vector<Features> features;
  std::vector<int> counts;
  for (const at::Tensor& image : images) {
    features.push_back(detect_features(image, options));
    counts.push_back(static_cast<int>(features.back().xy.size()));
    stats.keypoints += counts.back();
  }

  std::vector<std::vector<std::vector<Match>>> matches(views, std::vector<std::vector<Match>>(views));
  for (int i = 0; i < views; ++i) {
    for (int j = i + 1; j < views; ++j) {
      if (degenerate_baseline(cameras[i], cameras[j])) {
        ++stats.degenerate_pairs;
        continue;
      }
      const Eigen::Matrix3d F = fundamental_matrix(cameras[i], cameras[j]);
      const std::vector<Match> raw =
          match_features(features[i], features[j], options, options.guided_matching ? &F : nullptr);
      stats.ratio_matches += static_cast<int64_t>(raw.size());
      matches[i][j] =
          epipolar_filter(cameras[i], cameras[j], features[i].xy, features[j].xy, raw, options.max_epipolar_px);
      stats.epipolar_matches += static_cast<int64_t>(matches[i][j].size());
    }
  }

  const auto tracks = build_tracks(counts, matches);
  stats.tracks = static_cast<int64_t>(tracks.size());
  std::vector<at::Tensor> cpu_images;
  std::vector<at::TensorAccessor<float, 3>> pixels;
  for (const at::Tensor& im : images) cpu_images.push_back(im.to(at::kCPU, at::kFloat).contiguous());
  for (const at::Tensor& im : cpu_images) pixels.push_back(im.accessor<float, 3>());

  std::vector<float> xyz, rgb;
  std::vector<double> all_errors;
  for (const auto& track : tracks) {
    std::vector<Observation> obs;
    for (const auto& [v, k] : track) obs.push_back({v, features[v].xy[k]});
    TriangulatedPoint p;
    switch (triangulate_track(cameras, obs, options, &p)) {
      case TrackVerdict::kCheirality:
        ++stats.rejected_cheirality;
        continue;
      case TrackVerdict::kReprojection:
        ++stats.rejected_reprojection;
        continue;
      case TrackVerdict::kAngle:
        ++stats.rejected_angle;
        continue;
      case TrackVerdict::kKept:
        break;
    }
    const Eigen::Vector3f colour = mean_colour(pixels, p.observations);
    for (int c = 0; c < 3; ++c) {
      xyz.push_back(static_cast<float>(p.xyz(c)));
      rgb.push_back(colour(c));
    }
    std::vector<int> seen;
    for (const Observation& o : p.observations) seen.push_back(o.view);
    result.point_views.push_back(std::move(seen));
    all_errors.insert(all_errors.end(), p.errors_px.begin(), p.errors_px.end());
  }
  const int64_t n = static_cast<int64_t>(xyz.size() / 3);
  result.points.xyz = n > 0 ? at::from_blob(xyz.data(), {n, 3}, at::kFloat).clone() : at::zeros({0, 3}, at::kFloat);
  result.points.rgb = n > 0 ? at::from_blob(rgb.data(), {n, 3}, at::kFloat).clone() : at::zeros({0, 3}, at::kFloat);
  stats.points = n;
  stats.median_reprojection_px = median(all_errors);
  stats.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return result;
}

}  // namespace gaps

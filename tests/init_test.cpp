// Point-cloud initialisation from the training views: triangulation, epipolar filtering, plane sweep,
// fusion, the methods, the fallback chain and the cache on synthetic scenes, then the whole pipeline on LLFF
// fern (plane sweep and PatchMatch). PatchMatch's fusion and export have their own tests (fusion_test.cpp).
#include "gs_trainer/init/initializer.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <random>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <unistd.h>
#include <Eigen/Dense>
#include <nlohmann/json.hpp>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/ply.h"
#include "gs_trainer/init/colmap_dense.h"
#include "gs_trainer/init/plane_sweep.h"
#include "gs_trainer/init/sparse.h"
#include "gs_trainer/init/working_view.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/scene/colmap.h"
#include "gs_trainer/train/budget.h"
#include "tests/synthetic_stereo.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

// synthetic_stereo's camera at `centre` looking at `target`, named.
Camera look_at(const std::string& name, const Eigen::Vector3d& centre, const Eigen::Vector3d& target, int width,
               int height, double focal) {
  Camera c = synthetic_stereo::look_at(centre, target, width, height, focal);
  c.name = name;
  return c;
}

// Three views of the region around (0, 0, 4) from a ~0.6 wide baseline.
std::vector<Camera> three_cameras(int width, int height, double focal) {
  const Eigen::Vector3d target(0, 0, 4);
  return {look_at("a.png", {0, 0, 0}, target, width, height, focal),
          look_at("b.png", {0.35, 0.05, 0.1}, target, width, height, focal),
          look_at("c.png", {-0.3, -0.1, -0.05}, target, width, height, focal)};
}

// A textured plane through (0, 0, depth) with a slight tilt, rendered by ray casting.
struct TexturedPlane {
  Eigen::Vector3d point{0, 0, 4};
  Eigen::Vector3d normal = Eigen::Vector3d(0.15, -0.1, -1).normalized();
  at::Tensor texture;  // 1x3xTxT
  double half_extent = 4.0;

  explicit TexturedPlane(double depth = 4.0, uint64_t seed = 7) {
    point.z() = depth;
    at::manual_seed(seed);
    // Two octaves of noise: blobs for SIFT at this scale, fine grain for ZNCC.
    const at::Tensor coarse = at::rand({1, 3, 32, 32});
    const at::Tensor fine = at::rand({1, 3, 128, 128});
    texture = 0.6 * at::upsample_bilinear2d(coarse, {128, 128}, false) + 0.4 * fine;
  }

  // HxWx3 image and HxW depth (camera z) of the plane seen from `c`.
  std::pair<at::Tensor, at::Tensor> render(const Camera& c) const {
    const at::Tensor xs = (at::arange(c.width, at::kDouble) + 0.5 - c.cx) / c.fx;
    const at::Tensor ys = (at::arange(c.height, at::kDouble) + 0.5 - c.cy) / c.fy;
    const at::Tensor cam_rays =
        at::stack({xs.view({1, -1}).expand({c.height, c.width}), ys.view({-1, 1}).expand({c.height, c.width}),
                   at::ones({c.height, c.width}, at::kDouble)},
                  2);
    at::Tensor R = at::empty({3, 3}, at::kDouble);
    for (int i = 0; i < 9; ++i) R.view(-1)[i] = c.R(i / 3, i % 3);
    const at::Tensor rays = at::matmul(cam_rays, R);  // world directions R^T r, with rays as rows
    const Eigen::Vector3d C = c.center();
    const at::Tensor n = at::tensor({normal.x(), normal.y(), normal.z()}, at::kDouble);
    const double offset = normal.dot(point - C);
    const at::Tensor s = offset / at::matmul(rays, n);  // ray parameter; camera depth = s (ray z = 1)
    const Eigen::Vector3d e1 = normal.cross(Eigen::Vector3d(0, 1, 0)).normalized(), e2 = normal.cross(e1);
    const at::Tensor rel =
        rays * s.unsqueeze(2) + at::tensor({C.x() - point.x(), C.y() - point.y(), C.z() - point.z()}, at::kDouble);
    const at::Tensor a = at::matmul(rel, at::tensor({e1.x(), e1.y(), e1.z()}, at::kDouble)) / half_extent;
    const at::Tensor b = at::matmul(rel, at::tensor({e2.x(), e2.y(), e2.z()}, at::kDouble)) / half_extent;
    const at::Tensor grid = at::stack({a, b}, 2).unsqueeze(0).to(at::kFloat);
    const at::Tensor img = at::grid_sampler(texture, grid, 0, 2, false).squeeze(0).permute({1, 2, 0});
    return {img.contiguous(), s.to(at::kFloat)};
  }
};

std::vector<at::Tensor> render_all(const TexturedPlane& plane, const std::vector<Camera>& cams) {
  std::vector<at::Tensor> images;
  for (const Camera& c : cams) images.push_back(plane.render(c).first);
  return images;
}

TEST(Triangulation, RecoversKnownPointsExactlyAndUnderNoise) {
  const std::vector<Camera> cams = three_cameras(640, 480, 500);
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> box(-1.0, 1.0);
  std::normal_distribution<double> noise(0.0, 0.3);
  for (const double sigma : {0.0, 0.3}) {
    std::vector<double> errors_3d, errors_px;
    for (int i = 0; i < 200; ++i) {
      const Eigen::Vector3d X(box(rng), box(rng), 4.0 + box(rng));
      std::vector<Observation> obs;
      for (int v = 0; v < 3; ++v) {
        const auto p = project_point(cams[v], X);
        ASSERT_TRUE(p);
        obs.push_back({v, *p + sigma * Eigen::Vector2d(noise(rng), noise(rng))});
      }
      TriangulatedPoint t;
      ASSERT_EQ(triangulate_track(cams, obs, SparseOptions{}, &t), TrackVerdict::kKept) << X.transpose();
      ASSERT_EQ(t.observations.size(), 3u);
      errors_3d.push_back((t.xyz - X).norm());
      errors_px.insert(errors_px.end(), t.errors_px.begin(), t.errors_px.end());
    }
    std::sort(errors_3d.begin(), errors_3d.end());
    std::sort(errors_px.begin(), errors_px.end());
    if (sigma == 0.0) {
      EXPECT_LT(errors_3d.back(), 1e-6);
      EXPECT_LT(errors_px.back(), 1e-6);
    } else {
      // Depth noise ~ z^2 / (f b) * sigma = 16 / (500 * 0.6) * 0.3 ~ 0.016 at this geometry.
      EXPECT_LT(errors_3d[errors_3d.size() / 2], 0.03);
      EXPECT_LT(errors_px[errors_px.size() / 2], 0.5);
      EXPECT_LT(errors_px.back(), 1.5);
    }
  }
}

TEST(Triangulation, FiltersCheiralityAngleAndDropsOutlierObservations) {
  const std::vector<Camera> cams = three_cameras(640, 480, 500);
  const Eigen::Vector3d X(0.2, -0.1, 4.2);
  std::vector<Observation> obs;
  for (int v = 0; v < 3; ++v) obs.push_back({v, *project_point(cams[v], X)});

  // One corrupted observation of three: dropped, the point still kept from the other two.
  std::vector<Observation> bad = obs;
  bad[2].xy += Eigen::Vector2d(25, -10);
  TriangulatedPoint t;
  ASSERT_EQ(triangulate_track(cams, bad, SparseOptions{}, &t), TrackVerdict::kKept);
  EXPECT_EQ(t.observations.size(), 2u);
  EXPECT_LT((t.xyz - X).norm(), 1e-6);

  // A point far away relative to the baseline: tiny triangulation angle.
  const Eigen::Vector3d far_point(0, 0, 400);
  std::vector<Observation> far_obs;
  for (int v = 0; v < 2; ++v) far_obs.push_back({v, *project_point(cams[v], far_point)});
  EXPECT_EQ(triangulate_track(cams, far_obs, SparseOptions{}, &t), TrackVerdict::kAngle);

  // Two rays that meet behind the cameras (both observations pushed outwards past the vanishing direction).
  Camera left = look_at("l", {-1, 0, 0}, {-1, 0, 5}, 640, 480, 500);
  Camera right = look_at("r", {1, 0, 0}, {1, 0, 5}, 640, 480, 500);
  const std::vector<Camera> pair = {left, right};
  const std::vector<Observation> diverging = {{0, {220, 240}}, {1, {420, 240}}};
  EXPECT_EQ(triangulate_track(pair, diverging, SparseOptions{}, &t), TrackVerdict::kCheirality);
}

TEST(Epipolar, FilterKeepsTrueAndRejectsWrongMatches) {
  const std::vector<Camera> cams = three_cameras(640, 480, 500);
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> box(-1.0, 1.0);
  std::vector<Eigen::Vector2d> xa, xb;
  for (int i = 0; i < 300; ++i) {
    const Eigen::Vector3d X(box(rng), box(rng), 4.0 + box(rng));
    xa.push_back(*project_point(cams[0], X));
    xb.push_back(*project_point(cams[1], X));
  }
  const Eigen::Matrix3d F = fundamental_matrix(cams[0], cams[1]);
  for (int i = 0; i < 300; ++i) EXPECT_LT(epipolar_distance(F, xa[i], xb[i]), 1e-6);

  std::vector<Match> right, wrong;
  for (int i = 0; i < 300; ++i) {
    right.push_back({i, i});
    wrong.push_back({i, (i * 7 + 13) % 300});
  }
  EXPECT_EQ(epipolar_filter(cams[0], cams[1], xa, xb, right, 2.0).size(), 300u);
  const size_t survivors = epipolar_filter(cams[0], cams[1], xa, xb, wrong, 2.0).size();
  EXPECT_LT(survivors, 15u) << "wrong matches should rarely lie within 2 px of the epipolar line";
}

TEST(Tracks, UnionFindMergesChainsAndDropsAmbiguousViews) {
  // 0:0 - 1:0 - 2:0 forms one track; 0:1 - 1:1 and 0:2 - 1:1 put two keypoints of view 0 in one component.
  std::vector<std::vector<std::vector<Match>>> m(3, std::vector<std::vector<Match>>(3));
  m[0][1] = {{0, 0}, {1, 1}, {2, 1}};
  m[1][2] = {{0, 0}, {1, 1}};
  const auto tracks = build_tracks({3, 2, 2}, m);
  ASSERT_EQ(tracks.size(), 2u);
  for (const auto& t : tracks) {
    if (t.size() == 3) {
      EXPECT_EQ(t[0], std::make_pair(0, 0));
    } else {
      ASSERT_EQ(t.size(), 2u);  // view 0 was ambiguous: only views 1 and 2 remain
      EXPECT_EQ(t[0].first, 1);
      EXPECT_EQ(t[1].first, 2);
    }
  }
}

TEST(Sparse, TriangulatesASyntheticPlane) {
  const TexturedPlane plane;
  const std::vector<Camera> cams = three_cameras(320, 240, 300);
  auto result = sparse_reconstruct(cams, render_all(plane, cams));
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_GT(result->stats.points, 50) << result->stats.keypoints << " keypoints";
  EXPECT_LT(result->stats.median_reprojection_px, 0.5);
  const auto xyz = result->points.xyz.accessor<float, 2>();
  int on_plane = 0;
  for (int64_t i = 0; i < result->points.xyz.size(0); ++i) {
    const Eigen::Vector3d X(xyz[i][0], xyz[i][1], xyz[i][2]);
    on_plane += std::abs(plane.normal.dot(X - plane.point)) < 0.04;
  }
  EXPECT_GT(on_plane, 0.95 * result->stats.points);
}

// SparseOptions::max_image_side: SIFT and triangulation on the views brought down to a longest side give the
// points those smaller views give, in world units (on the plane), and the option's range is checked.
TEST(Sparse, DownsampledViewsTriangulateInWorldUnits) {
  const TexturedPlane plane;
  const std::vector<Camera> cams = three_cameras(640, 480, 600);
  const std::vector<at::Tensor> images = render_all(plane, cams);
  SparseOptions capped;
  capped.max_image_side = 320;
  auto result = sparse_reconstruct(cams, images, capped);
  ASSERT_TRUE(result.ok()) << result.status();
  const WorkingViews views = working_views(cams, images, 320);
  for (const Camera& c : views.cameras) EXPECT_EQ(c.width, 320);
  auto small = sparse_reconstruct(views.cameras, views.images);
  ASSERT_TRUE(small.ok()) << small.status();
  EXPECT_GT(result->stats.points, 50);
  EXPECT_EQ(result->stats.points, small->stats.points);
  EXPECT_TRUE(at::equal(result->points.xyz, small->points.xyz));
  const auto xyz = result->points.xyz.accessor<float, 2>();
  int on_plane = 0;
  for (int64_t i = 0; i < result->points.xyz.size(0); ++i)
    on_plane += std::abs(plane.normal.dot(Eigen::Vector3d(xyz[i][0], xyz[i][1], xyz[i][2]) - plane.point)) < 0.04;
  EXPECT_GT(on_plane, 0.95 * result->stats.points);

  capped.max_image_side = 16;
  const auto refused = sparse_reconstruct(cams, images, capped);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(test::contains(std::string(refused.status().message()), "max_image_side must be 0")) << refused.status();
}

TEST(PlaneSweep, RecoversTheDepthOfATexturedPlane) {
  const TexturedPlane plane;
  const std::vector<Camera> cams = three_cameras(160, 120, 150);
  std::vector<at::Tensor> images;
  at::Tensor truth;
  for (const Camera& c : cams) {
    auto [img, depth] = plane.render(c);
    images.push_back(img);
    if (!truth.defined()) truth = depth;
  }
  DenseOptions o;
  o.num_planes = 64;
  const DepthMap map = plane_sweep(cams[0], images[0], {cams[1], cams[2]}, {images[1], images[2]}, 2.0, 8.0, o);
  const at::Tensor valid = map.depth > 0;
  const double fraction = valid.to(at::kFloat).mean().item<double>();
  EXPECT_GT(fraction, 0.5);
  const at::Tensor rel = ((map.depth - truth).abs() / truth).index({valid});
  const double median = rel.median().item<double>();
  EXPECT_LT(median, 0.01) << "valid fraction " << fraction;
  // Inverse-depth plane spacing here is ~1.2% of depth at 4 units: the parabola refines below a plane.
  EXPECT_LT(median, 0.005);
}

DepthMap map_from_truth(const Camera& c, const at::Tensor& image, const at::Tensor& depth) {
  DepthMap m;
  m.camera = c;
  m.image = image;
  m.depth = depth;
  m.score = at::ones_like(depth);
  m.margin = at::ones_like(depth);
  m.support = at::ones_like(depth, at::kInt);
  return m;
}

TEST(Fusion, KeepsConsistentAndRejectsContradictingDepths) {
  const TexturedPlane plane(4.0), other(5.0);
  const std::vector<Camera> cams = three_cameras(160, 120, 150);
  auto [img_a, depth_a] = plane.render(cams[0]);
  auto [img_b, depth_b] = plane.render(cams[1]);
  const DenseOptions o;
  const PointCloud agree =
      fuse_depth_maps({map_from_truth(cams[0], img_a, depth_a), map_from_truth(cams[1], img_b, depth_b)}, o);
  EXPECT_GT(agree.xyz.size(0), 0.5 * 160 * 120);
  // Fused points lie on the plane.
  const at::Tensor n = at::tensor({plane.normal.x(), plane.normal.y(), plane.normal.z()}, at::kFloat);
  const double p0 = plane.normal.dot(plane.point);
  EXPECT_LT((at::matmul(agree.xyz, n) - p0).abs().max().item<double>(), 0.02);

  // View b claims a plane one unit further away (same colours, so only geometry can object): nothing fuses.
  const at::Tensor wrong_b = other.render(cams[1]).second;
  const PointCloud contradict =
      fuse_depth_maps({map_from_truth(cams[0], img_a, depth_a), map_from_truth(cams[1], img_b, wrong_b)}, o);
  EXPECT_EQ(contradict.xyz.size(0), 0);
}

TEST(Voxel, CapsThePointCount) {
  at::manual_seed(1);
  PointCloud pc{at::rand({50000, 3}), at::rand({50000, 3})};
  pc.xyz.select(1, 2).zero_();  // a surface, as fused points are
  double voxel = 0;
  const PointCloud capped = cap_points(pc, 5000, &voxel);
  EXPECT_LE(capped.xyz.size(0), 5000);
  EXPECT_GT(capped.xyz.size(0), 4500);  // about the smallest voxel that meets the cap
  EXPECT_GT(voxel, 0);
  EXPECT_EQ(cap_points(pc, 100000, &voxel).xyz.size(0), 50000);
  EXPECT_EQ(voxel, 0);
}

TEST(Initializer, SingleViewFallsBackToRandomWithAWarning) {
  const TexturedPlane plane;
  const std::vector<Camera> cams = three_cameras(160, 120, 150);
  InitOptions o;
  o.random_points = 1234;
  std::string report;
  auto points = initialize_points("mvs", {cams[0]}, {plane.render(cams[0]).first}, o, &report);
  ASSERT_TRUE(points.ok()) << points.status();
  EXPECT_EQ(points->xyz.size(0), 1234);
  EXPECT_NE(report.find("warning: init: mvs needs at least two views"), std::string::npos) << report;
  EXPECT_NE(report.find("init: random, 1234 points"), std::string::npos) << report;

  // Same centre, different directions: nothing can be triangulated.
  Camera turned = look_at("t.png", {0, 0, 0}, {1, 0, 4}, 160, 120, 150);
  const std::vector<Camera> pivot = {cams[0], turned};
  report.clear();
  auto pivoted = initialize_points("sparse", pivot, render_all(plane, pivot), o, &report);
  ASSERT_TRUE(pivoted.ok());
  EXPECT_EQ(pivoted->xyz.size(0), 1234);
  EXPECT_NE(report.find("degenerate baseline"), std::string::npos) << report;

  EXPECT_FALSE(initialize_points("colmap", cams, render_all(plane, cams), o, nullptr).ok());
}

TEST(Initializer, MethodsAndTheirErrors) {
  for (const char* m : {"auto", "mvs", "sweep", "sparse", "random"}) EXPECT_TRUE(is_init_method(m)) << m;
  EXPECT_FALSE(is_init_method("colmap"));
  EXPECT_FALSE(is_init_method(""));
  const TexturedPlane plane;
  const std::vector<Camera> cams = three_cameras(80, 60, 75);
  auto unknown = run_initialization("colmap", cams, render_all(plane, cams), InitOptions{});
  EXPECT_EQ(unknown.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(unknown.status().message(), "unknown initialisation 'colmap' (auto, mvs, sweep, sparse, random)");
}

TEST(Initializer, SweepOnASyntheticPlaneAndTheCacheReturnsIdenticalPoints) {
  const TexturedPlane plane;
  const std::vector<Camera> cams = three_cameras(320, 240, 300);
  const std::vector<at::Tensor> images = render_all(plane, cams);
  const fs::path dir = fs::temp_directory_path() / ("gaps_init_test_" + std::to_string(::getpid()));
  InitOptions o;
  o.cache_dir = dir;
  o.dense.max_image_side = 200;  // small sweep: this test is about the plumbing
  o.dense.num_planes = 48;
  auto first = run_initialization("sweep", cams, images, o);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(first->method, "sweep") << (first->warnings.empty() ? "" : first->warnings[0]);
  EXPECT_FALSE(first->from_cache);
  EXPECT_GT(first->points.xyz.size(0), 5000);
  ASSERT_TRUE(first->dense);
  EXPECT_FALSE(first->mvs);
  ASSERT_TRUE(fs::exists(first->cache_file));

  auto second = run_initialization("sweep", cams, images, o);
  ASSERT_TRUE(second.ok());
  EXPECT_TRUE(second->from_cache);
  EXPECT_EQ(second->method, "sweep");
  EXPECT_TRUE(at::equal(first->points.xyz, second->points.xyz));
  EXPECT_TRUE(at::equal(first->points.rgb, second->points.rgb));
  // initialize_points says whether its points came from the cache (metrics.json's init_from_cache).
  bool from_cache = false;
  std::string method;
  ASSERT_TRUE(initialize_points("sweep", cams, images, o, nullptr, &method, &from_cache).ok());
  EXPECT_TRUE(from_cache);
  InitOptions uncached = o;
  uncached.cache_dir.clear();
  ASSERT_TRUE(initialize_points("sparse", cams, images, uncached, nullptr, &method, &from_cache).ok());
  EXPECT_FALSE(from_cache);
  // Another method, other views or other PatchMatch or fusion options get another key.
  EXPECT_NE(init_cache_key("sparse", cams, images, o), init_cache_key("sweep", cams, images, o));
  EXPECT_NE(init_cache_key("mvs", cams, images, o), init_cache_key("sweep", cams, images, o));
  // The first and last of the mvs key's fields count too (a format one conversion short once dropped the
  // depth-coverage bar, so "auto" and "mvs" shared clouds).
  InitOptions changed = o;
  changed.patchmatch.best_views = o.patchmatch.best_views + 1;
  EXPECT_NE(init_cache_key("mvs", cams, images, o), init_cache_key("mvs", cams, images, changed));
  changed = o;
  changed.fusion.add_sparse_points = !o.fusion.add_sparse_points;
  EXPECT_NE(init_cache_key("mvs", cams, images, o), init_cache_key("mvs", cams, images, changed));
  changed = o;
  changed.sparse.max_image_side = 320;
  EXPECT_NE(init_cache_key("sparse", cams, images, o), init_cache_key("sparse", cams, images, changed));
  changed = o;
  changed.min_depth_coverage = 0.25;
  EXPECT_NE(init_cache_key("mvs", cams, images, o), init_cache_key("mvs", cams, images, changed));
  EXPECT_NE(init_cache_key("sweep", {cams[0], cams[1]}, {images[0], images[1]}, o),
            init_cache_key("sweep", cams, images, o));
  InitOptions other = o;
  other.patchmatch.iterations += 1;
  EXPECT_NE(init_cache_key("mvs", cams, images, other), init_cache_key("mvs", cams, images, o));
  other = o;
  other.fusion.max_points = 1234;
  EXPECT_NE(init_cache_key("mvs", cams, images, other), init_cache_key("mvs", cams, images, o));
  // The sparse points do not depend on them (nor on the Gaussian budget that caps the fusion).
  EXPECT_EQ(init_cache_key("sparse", cams, images, other), init_cache_key("sparse", cams, images, o));

  // sweep that cannot deliver (here: an unreachable point count) falls back to the sparse points, saying why.
  InitOptions strict = o;
  strict.cache_dir.clear();
  strict.min_dense_points = int64_t{1} << 40;
  std::string report;
  auto fallback = initialize_points("sweep", cams, images, strict, &report);
  ASSERT_TRUE(fallback.ok());
  EXPECT_NE(report.find("warning: init: sweep failed: too few fused points"), std::string::npos) << report;
  EXPECT_NE(report.find("init: sparse, "), std::string::npos) << report;

  // COLMAP interop: the text model reads back with our cameras and points.
  ASSERT_TRUE(write_init_as_colmap(dir / "colmap", cams, first->points).ok());
  auto model = read_colmap_model(dir / "colmap");
  ASSERT_TRUE(model.ok()) << model.status();
  EXPECT_EQ(model->images.size(), 3u);
  EXPECT_EQ(static_cast<int64_t>(model->points.size()), first->points.xyz.size(0));
  remove_tree(dir);
}

// PatchMatch kept small: the tests below are about the plumbing, not the depths.
InitOptions small_patchmatch() {
  InitOptions o;
  o.patchmatch.max_image_side = 160;
  o.patchmatch.iterations = 2;
  o.patchmatch.geometric_iterations = 1;
  return o;
}

TEST(Initializer, MvsOnASyntheticPlaneIsWhatAutoTakesAndWritesTheWorkspace) {
  const TexturedPlane plane;
  const std::vector<Camera> cams = three_cameras(320, 240, 300);
  const std::vector<at::Tensor> images = render_all(plane, cams);
  const fs::path dir = fs::temp_directory_path() / ("gaps_init_mvs_test_" + std::to_string(::getpid()));
  InitOptions o = small_patchmatch();
  o.cache_dir = dir;
  auto first = run_initialization("mvs", cams, images, o);
  ASSERT_TRUE(first.ok()) << first.status();
  for (const std::string& n : first->notes) std::cout << n << "\n";
  ASSERT_EQ(first->method, "mvs") << (first->warnings.empty() ? "" : first->warnings[0]);
  ASSERT_TRUE(first->mvs);
  EXPECT_FALSE(first->dense);
  EXPECT_EQ(first->mvs->views_with_sources, 3);
  EXPECT_EQ(first->mvs->fusion.points, first->points.xyz.size(0));
  EXPECT_TRUE(std::any_of(first->notes.begin(), first->notes.end(),
                          [](const std::string& n) { return n.rfind("mvs: PatchMatch on 3 views", 0) == 0; }));
  // Most fused points lie on the plane.
  const at::Tensor n = at::tensor({plane.normal.x(), plane.normal.y(), plane.normal.z()}, at::kFloat);
  const at::Tensor distance = (at::matmul(first->points.xyz, n) - plane.normal.dot(plane.point)).abs();
  EXPECT_LT(distance.median().item<double>(), 0.05);

  // "auto" is PatchMatch too (these maps cover far more than its 25 %), and says what it asks.
  auto chosen = run_initialization("auto", cams, images, o);
  ASSERT_TRUE(chosen.ok()) << chosen.status();
  EXPECT_EQ(chosen->method, "mvs");
  ASSERT_FALSE(chosen->notes.empty());
  EXPECT_EQ(chosen->notes[0], "auto: mvs, the sparse points if its depth maps cover under 25% of the pixels");

  // A dense workspace needs the maps: computed again, not read from the cache.
  o.dense_workspace = dir / "workspace";
  auto again = run_initialization("mvs", cams, images, o);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_FALSE(again->from_cache);
  EXPECT_TRUE(fs::exists(o.dense_workspace / "fused.ply"));
  EXPECT_TRUE(fs::exists(o.dense_workspace / "stereo" / "depth_maps" / "a.png.geometric.bin"));
  EXPECT_TRUE(fs::exists(o.dense_workspace / "sparse" / "cameras.txt"));

  // mvs that cannot deliver falls back to the sparse points, saying why, and writes no workspace.
  InitOptions strict = o;
  strict.cache_dir.clear();
  strict.dense_workspace = dir / "no_workspace";
  strict.min_dense_points = int64_t{1} << 40;
  std::string report;
  auto fallback = initialize_points("mvs", cams, images, strict, &report);
  ASSERT_TRUE(fallback.ok());
  EXPECT_NE(report.find("warning: init: mvs failed: too few fused points"), std::string::npos) << report;
  EXPECT_NE(report.find("init: sparse, "), std::string::npos) << report;
  EXPECT_FALSE(fs::exists(strict.dense_workspace));

  // So does mvs whose maps leave too many pixels without a depth (what "auto" asks).
  InitOptions covering = o;
  covering.cache_dir.clear();
  covering.dense_workspace.clear();
  covering.min_depth_coverage = 0.999;
  report.clear();
  ASSERT_TRUE(initialize_points("mvs", cams, images, covering, &report).ok());
  EXPECT_NE(report.find("warning: init: mvs failed: depth for "), std::string::npos) << report;
  EXPECT_NE(report.find("(< 100%); falling back to the sparse points"), std::string::npos) << report;
  covering.min_depth_coverage = 0.05;
  auto covered = run_initialization("mvs", cams, images, covering);
  ASSERT_TRUE(covered.ok()) << covered.status();
  EXPECT_EQ(covered->method, "mvs");
  remove_tree(dir);
}

// FusionOptions::add_sparse_points: the cloud is the fused points plus every triangulated point, and the cap
// applies to the two together; the sparse points' positions are kept exactly when there is no cap.
// A stopped initialisation ends CANCELLED, whatever stage it is in: no fallback to other points (a
// cancelled job must not train on them) and nothing cached (the next run computes the whole thing).
TEST(Initializer, AStopEndsItCancelledWithoutFallbackOrCache) {
  const TexturedPlane plane;
  const std::vector<Camera> cams = three_cameras(320, 240, 300);
  const std::vector<at::Tensor> images = render_all(plane, cams);
  const fs::path dir = fs::temp_directory_path() / ("gaps_init_stop_test_" + std::to_string(::getpid()));
  InitOptions o = small_patchmatch();
  o.cache_dir = dir;
  for (const int stop_at : {1, 2, 3, 5}) {  // before and after the sparse points, then in PatchMatch's sweeps
    int asked = 0;
    o.should_stop = [&] { return ++asked == stop_at; };
    for (const std::string method : {"auto", "mvs"}) {
      asked = 0;
      const auto r = run_initialization(method, cams, images, o);
      EXPECT_EQ(r.status().code(), absl::StatusCode::kCancelled) << method << " " << stop_at << ": " << r.status();
      EXPECT_EQ(asked, stop_at) << method;
    }
  }
  EXPECT_FALSE(fs::exists(dir) && !fs::is_empty(dir));
  o.should_stop = [] { return false; };
  const auto whole = run_initialization("mvs", cams, images, o);
  ASSERT_TRUE(whole.ok()) << whole.status();
  EXPECT_EQ(whole->method, "mvs");
  EXPECT_FALSE(whole->from_cache);
  remove_tree(dir);
}

// The long stages say how far they have come, in order: the sparse points, every PatchMatch sweep (counted
// up to the total announced first), fusion; the plane sweep as one stage. A cached result says nothing.
TEST(Initializer, TheStagesReportTheirProgressInOrder) {
  const TexturedPlane plane;
  const std::vector<Camera> cams = three_cameras(320, 240, 300);
  const std::vector<at::Tensor> images = render_all(plane, cams);
  const fs::path dir = fs::temp_directory_path() / ("gaps_init_progress_test_" + std::to_string(::getpid()));
  InitOptions o = small_patchmatch();
  o.cache_dir = dir;
  std::vector<std::string> heard;
  o.on_progress = [&](const std::string& stage, int done, int total) {
    heard.push_back(stage + " " + std::to_string(done) + "/" + std::to_string(total));
  };
  ASSERT_TRUE(run_initialization("mvs", cams, images, o).ok());
  const int sweeps =
      3 * (o.patchmatch.iterations + (o.patchmatch.geometric_consistency ? o.patchmatch.geometric_iterations : 0));
  std::vector<std::string> expected = {"sparse 0/1", "sparse 1/1"};
  for (int k = 0; k <= sweeps; ++k)
    expected.push_back("patchmatch " + std::to_string(k) + "/" + std::to_string(sweeps));
  expected.insert(expected.end(), {"fusion 0/1", "fusion 1/1"});
  EXPECT_EQ(heard, expected);
  heard.clear();
  const auto cached = run_initialization("mvs", cams, images, o);
  ASSERT_TRUE(cached.ok() && cached->from_cache);
  EXPECT_TRUE(heard.empty()) << heard.size();
  // A reused result says so before the statistics it was computed with.
  std::string report;
  ASSERT_TRUE(initialize_points("mvs", cams, images, o, &report).ok());
  EXPECT_TRUE(absl::StartsWith(report, "init: reusing ")) << report;
  // The same views under another scene folder's name (a service job's upload is "scene") reuse it too.
  std::vector<Camera> renamed = cams;
  for (Camera& c : renamed) c.image_path = fs::path("/elsewhere/job-1/scene") / (c.name + ".png");
  ASSERT_NE(init_cache_key("mvs", renamed, images, o), init_cache_key("mvs", cams, images, o));
  const auto reused = run_initialization("mvs", renamed, images, o);
  ASSERT_TRUE(reused.ok()) << reused.status();
  EXPECT_TRUE(reused->from_cache);
  ASSERT_TRUE(run_initialization("sweep", cams, images, o).ok());
  EXPECT_EQ(heard, (std::vector<std::string>{"sparse 0/1", "sparse 1/1", "sweep 0/1", "sweep 1/1"}));
  remove_tree(dir);
}

// The lines a run prints from that progress: each stage's start and end, PatchMatch at every tenth.
TEST(Initializer, StageProgressLinesSayEachStageAndEveryTenthOfPatchMatch) {
  std::vector<std::string> lines;
  const auto progress = stage_progress_lines([&](const std::string& line) { lines.push_back(line); });
  progress("sparse", 0, 1);
  progress("sparse", 1, 1);
  for (int k = 0; k <= 40; ++k) progress("patchmatch", k, 40);
  progress("fusion", 0, 1);
  progress("fusion", 1, 1);
  ASSERT_EQ(lines.size(), 2u + 11u + 2u) << absl::StrJoin(lines, "\n");
  EXPECT_EQ(lines[0], "init: sparse points (SIFT, matching, triangulation)...");
  EXPECT_TRUE(absl::StartsWith(lines[1], "init: sparse points (SIFT, matching, triangulation): done in ")) << lines[1];
  EXPECT_EQ(lines[2], "init: PatchMatch: 0/40 sweeps");
  EXPECT_TRUE(absl::StartsWith(lines[3], "init: PatchMatch: 4/40 sweeps (10%, ")) << lines[3];
  EXPECT_TRUE(absl::StartsWith(lines[12], "init: PatchMatch: 40/40 sweeps, done in ")) << lines[12];
  EXPECT_EQ(lines[13], "init: fusion of the depth maps...");
}

TEST(Initializer, MvsAddsTheSparsePointsUnderTheCap) {
  const TexturedPlane plane;
  const std::vector<Camera> cams = three_cameras(320, 240, 300);
  const std::vector<at::Tensor> images = render_all(plane, cams);
  InitOptions o = small_patchmatch();
  auto fused_only = run_initialization("mvs", cams, images, o);
  ASSERT_TRUE(fused_only.ok()) << fused_only.status();
  ASSERT_EQ(fused_only->method, "mvs");
  ASSERT_TRUE(fused_only->sparse);
  const int64_t fused = fused_only->points.xyz.size(0), sparse = fused_only->sparse->points;
  ASSERT_GT(sparse, 0);

  o.fusion.add_sparse_points = true;
  auto both = run_initialization("mvs", cams, images, o);
  ASSERT_TRUE(both.ok()) << both.status();
  EXPECT_EQ(both->method, "mvs");
  ASSERT_EQ(both->points.xyz.size(0), fused + sparse);
  EXPECT_TRUE(at::equal(both->points.xyz.narrow(0, 0, fused), fused_only->points.xyz));
  EXPECT_EQ(both->points.rgb.size(0), fused + sparse);
  const std::string note = absl::StrCat("mvs: ", fused, " fused + ", sparse, " sparse points -> ", fused + sparse);
  EXPECT_TRUE(std::any_of(both->notes.begin(), both->notes.end(), [&](const std::string& n) {
    return n.rfind(note, 0) == 0;
  })) << absl::StrJoin(both->notes, "\n");

  o.fusion.max_points = fused / 2;
  auto capped = run_initialization("mvs", cams, images, o);
  ASSERT_TRUE(capped.ok()) << capped.status();
  EXPECT_LE(capped->points.xyz.size(0), fused / 2);
  EXPECT_GT(capped->points.xyz.size(0), fused / 4);
}

TEST(AutoInitialisation, ViewingDirectionSpreadIsTheLargestPairwiseAngle) {
  const Eigen::Vector3d origin(0, 0, 0);
  const Camera ahead = look_at("ahead", {0, 0, -4}, origin, 64, 48, 50);
  const Camera side = look_at("side", {4, 0, 0}, origin, 64, 48, 50);
  const Camera behind = look_at("behind", {0, 0, 4}, origin, 64, 48, 50);
  EXPECT_NEAR(viewing_direction_spread_degrees({ahead}), 0.0, 1e-9);
  EXPECT_NEAR(viewing_direction_spread_degrees({ahead, side}), 90.0, 1e-6);
  EXPECT_NEAR(viewing_direction_spread_degrees({ahead, side, behind}), 180.0, 1e-6);
  // Forward-facing: centres on a 1-unit line, all looking at a point 10 units ahead (about 5.7 degrees apart).
  const Camera left = look_at("left", {-0.5, 0, 0}, {0, 0, 10}, 64, 48, 50);
  const Camera right = look_at("right", {0.5, 0, 0}, {0, 0, 10}, 64, 48, 50);
  EXPECT_NEAR(viewing_direction_spread_degrees({left, right}), 2.0 * std::atan(0.05) * 180.0 / M_PI, 1e-6);
  EXPECT_FALSE(views_surround_scene({left, right}));
  EXPECT_TRUE(views_surround_scene({ahead, side, behind}));
}

// The benchmark scenes: fern is forward-facing, bonsai's training views surround the tree.
TEST(AutoInitialisation, FernFacesOneWayAndBonsaiIsSurrounded) {
  const fs::path data(GAPS_DATA_DIR);
  const struct {
    const char* path;
    int views;
    bool surround;
  } cases[] = {{"llff/fern", 3, false},
               {"llff/fern", 9, false},
               {"mipnerf360/bonsai", 12, true},
               {"mipnerf360/bonsai", 24, true}};
  for (const auto& c : cases) {
    if (!fs::exists(data / c.path)) GTEST_SKIP() << "no benchmark data at " << data / c.path;
    SceneLoadOptions load;
    load.resolution = 8;
    auto scene = load_scene(data / c.path, load);
    ASSERT_TRUE(scene.ok()) << scene.status();
    auto split = benchmark_split(static_cast<int>(scene->cameras.size()), c.views);
    ASSERT_TRUE(split.ok()) << split.status();
    std::vector<Camera> cams;
    for (int i : split->train) cams.push_back(scene->cameras[i]);
    std::cout << c.path << ", " << c.views << " views: viewing directions span "
              << viewing_direction_spread_degrees(cams) << " degrees\n";
    EXPECT_EQ(views_surround_scene(cams), c.surround) << c.path << ", " << c.views << " views";
  }
}

TEST(Initializer, FernThreeViewsSweep) {
  const fs::path root = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!fs::exists(root)) GTEST_SKIP() << "no benchmark data at " << root;
  SceneLoadOptions load;
  load.resolution = 8;
  auto scene = load_scene(root, load);
  ASSERT_TRUE(scene.ok()) << scene.status();
  auto split = benchmark_split(static_cast<int>(scene->cameras.size()), 3);
  ASSERT_TRUE(split.ok());
  ASSERT_EQ(split->train, (std::vector<int>{1, 10, 19}));
  std::vector<Camera> cams;
  std::vector<at::Tensor> images;
  for (int i : split->train) {
    auto image = load_camera_image(scene->cameras[i]);
    ASSERT_TRUE(image.ok()) << image.status();
    cams.push_back(scene->cameras[i]);
    images.push_back(*image);
  }
  const auto start = std::chrono::steady_clock::now();
  auto result = run_initialization("sweep", cams, images, InitOptions{});
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  ASSERT_TRUE(result.ok()) << result.status();
  for (const std::string& n : result->notes) std::cout << n << "\n";
  ASSERT_EQ(result->method, "sweep") << (result->warnings.empty() ? "" : result->warnings[0]);
  ASSERT_TRUE(result->sparse);
  EXPECT_GT(result->sparse->points, 300);
  EXPECT_LT(result->sparse->median_reprojection_px, 1.5);
  EXPECT_GT(result->points.xyz.size(0), 5000);
  for (int i : {0, 8, 16}) {
    const double coverage = view_coverage(scene->cameras[i], result->points.xyz);
    std::cout << "test view " << i << " coverage " << coverage << "\n";
    EXPECT_GT(coverage, 0.5) << "test view " << i;
  }
  std::cout << "fern 3 views: " << result->points.xyz.size(0) << " points in " << seconds << " s\n";
}

// `--init mvs` on fern, 3 views at -r 16 (252x189, to keep PatchMatch on the CPU short).
class MvsInit : public test::TempDirTest {
 protected:
  void SetUp() override {
    TempDirTest::SetUp();
    if (!fs::exists(fern_)) GTEST_SKIP() << "no benchmark data at " << fern_;
  }

  RunOptions fern_mvs() const {
    RunOptions o;
    o.scene_dir = fern_;
    o.views = 3;
    o.resolution = 16;
    o.init = "mvs";
    o.config.device = "cpu";
    return o;
  }

  const fs::path fern_ = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
};

// `gaps init --init mvs`: the points, and the COLMAP dense workspace beside them.
TEST_F(MvsInit, FernThreeViewsWritesPointsAndADenseWorkspace) {
  RunOptions o = fern_mvs();
  o.out_dir = dir_ / "init";
  std::string log;
  const absl::Status done = run_init_only(o, [&](const std::string& line) { log += line + "\n"; });
  std::cout << log;
  ASSERT_TRUE(done.ok()) << done;
  EXPECT_TRUE(test::contains(log, "init: mvs, ")) << log;
  EXPECT_TRUE(test::contains(log, "COLMAP dense workspace in " + (o.out_dir / "dense").string())) << log;
  auto points = read_point_cloud_ply(o.out_dir / "points.ply");
  ASSERT_TRUE(points.ok()) << points.status();
  EXPECT_GT(points->xyz.size(0), 2000);

  const fs::path dense = o.out_dir / "dense";
  auto model = read_colmap_model(dense / "sparse");
  ASSERT_TRUE(model.ok()) << model.status();
  ASSERT_EQ(model->images.size(), 3u);
  for (const auto& [id, image] : model->images) {
    const ColmapCamera& camera = model->cameras.at(image.camera_id);
    EXPECT_TRUE(fs::exists(dense / "images" / image.name)) << image.name;
    auto depth = read_colmap_mat(dense / "stereo" / "depth_maps" / (image.name + ".geometric.bin"));
    ASSERT_TRUE(depth.ok()) << depth.status();
    EXPECT_EQ(depth->sizes(), (std::vector<int64_t>{camera.height, camera.width}));
    const double valid = (*depth > 0).to(at::kFloat).mean().item<double>();
    std::cout << image.name << ": depth at " << valid << " of the pixels\n";
    EXPECT_GT(valid, 0.2) << image.name;
    auto normal = read_colmap_mat(dense / "stereo" / "normal_maps" / (image.name + ".geometric.bin"));
    ASSERT_TRUE(normal.ok()) << normal.status();
    EXPECT_EQ(normal->sizes(), (std::vector<int64_t>{camera.height, camera.width, 3}));
  }
  auto fused = read_ply_vertices(dense / "fused.ply");
  ASSERT_TRUE(fused.ok()) << fused.status();
  EXPECT_EQ(fused->count, points->xyz.size(0));
  EXPECT_TRUE(fused->has("nx"));

  SceneLoadOptions load;
  load.resolution = 16;
  auto scene = load_scene(fern_, load);
  ASSERT_TRUE(scene.ok()) << scene.status();
  for (int i : {0, 8, 16}) {
    const double coverage = view_coverage(scene->cameras[i], points->xyz);
    std::cout << "test view " << i << " coverage " << coverage << "\n";
    EXPECT_GT(coverage, 0.5) << "test view " << i;
  }
}

// The run's PatchMatch and fusion settings reach the initialisation: on the same depth maps, a looser normal
// check in fusion (30 degrees instead of 10) keeps more points. PatchMatch is made cheap for the CPU (fewer
// sweeps, no geometric pass), which the settings also carry. Settings out of range are refused first.
TEST_F(MvsInit, FernSettingsReachTheInitialisationAndAreChecked) {
  RunOptions o = fern_mvs();
  o.patchmatch.iterations = 3;
  o.patchmatch.geometric_consistency = false;
  const auto points_with = [&](double max_normal_error_deg) -> int64_t {
    RunOptions run = o;
    run.fusion.max_normal_error_deg = max_normal_error_deg;
    run.out_dir = dir_ / ("normal_error_" + std::to_string(static_cast<int>(max_normal_error_deg)));
    std::string log;
    const absl::Status done = run_init_only(run, [&](const std::string& line) { log += line + "\n"; });
    EXPECT_TRUE(done.ok()) << done;
    EXPECT_TRUE(test::contains(log, "init: mvs, ")) << log;
    auto points = read_point_cloud_ply(run.out_dir / "points.ply");
    EXPECT_TRUE(points.ok()) << points.status();
    return points.ok() ? points->xyz.size(0) : 0;
  };
  const int64_t strict = points_with(10), loose = points_with(30);
  std::cout << "fern 3 views at -r 16: " << strict << " points with normals within 10 degrees, " << loose
            << " within 30\n";
  EXPECT_GT(strict, 0);
  EXPECT_GT(loose, strict);

  const auto refusal = [&](RunOptions bad) {
    bad.out_dir = dir_ / "refused";
    return run_init_only(bad, [](const std::string&) {});
  };
  RunOptions bad = o;
  bad.patchmatch.max_cost = 0;
  absl::Status refused = refusal(bad);
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(test::contains(std::string(refused.message()), "PatchMatch: max_cost must be > 0")) << refused;
  bad = o;
  bad.fusion.min_views = 0;
  refused = refusal(bad);
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(test::contains(std::string(refused.message()), "fusion: min_views must be >= 1")) << refused;
  EXPECT_FALSE(fs::exists(dir_ / "refused" / "points.ply"));
}

class InitResolution : public test::TempDirTest {
 protected:
  // "auto" on 3 views of `scene` at -r 16, PatchMatch made cheap for the CPU (auto leaves the settings other than
  // the views' sizes alone).
  static RunOptions cheap_auto(const fs::path& scene) {
    RunOptions o;
    o.scene_dir = scene;
    o.views = 3;
    o.resolution = 16;
    o.patchmatch.iterations = 3;
    o.patchmatch.geometric_consistency = false;
    o.config.device = "cpu";
    return o;
  }
};

// The initialisation may read larger images than training uses: fern at -r 8 triangulated from its -r 4
// images. Same views, same poses, more pixels: more points; unless the sparse stage brings them back down
// (--sparse-max-image-side, which "sparse" reads, so it is not reported unused).
TEST_F(InitResolution, FernTriangulatesMoreFromLargerImages) {
  const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!fs::exists(fern)) GTEST_SKIP() << "no benchmark data at " << fern;
  const auto points_at = [&](int init_resolution, std::string* log, int sparse_max_image_side = 0) -> int64_t {
    RunOptions o;
    o.scene_dir = fern;
    o.views = 3;
    o.resolution = 8;
    o.init = "sparse";
    o.init_resolution = init_resolution;
    o.sparse.max_image_side = sparse_max_image_side;
    o.config.device = "cpu";
    o.out_dir = dir_ / absl::StrCat("init_r", init_resolution, "_", sparse_max_image_side);
    const absl::Status done = run_init_only(o, [&](const std::string& line) { *log += line + "\n"; });
    EXPECT_TRUE(done.ok()) << done;
    auto points = read_point_cloud_ply(o.out_dir / "points.ply");
    EXPECT_TRUE(points.ok()) << points.status();
    return points.ok() ? points->xyz.size(0) : 0;
  };
  std::string training_log, larger_log;
  const int64_t at_training = points_at(0, &training_log);
  const int64_t from_larger = points_at(4, &larger_log);
  std::cout << "fern 3 views, sparse points: " << at_training << " from 504x378, " << from_larger << " from 1008x756\n";
  EXPECT_EQ(training_log.find("init: reading the training views at"), std::string::npos) << training_log;
  EXPECT_NE(larger_log.find("init: reading the training views at 1008x756 (init resolution 4)"), std::string::npos)
      << larger_log;
  EXPECT_GT(from_larger, at_training);
  std::string capped_log;
  const int64_t capped = points_at(4, &capped_log, 504);
  std::cout << "from 1008x756 with SIFT at 504x378: " << capped << "\n";
  EXPECT_GT(capped, 0);
  EXPECT_LT(capped, from_larger);
  EXPECT_EQ(capped_log.find("not used"), std::string::npos) << capped_log;

  RunOptions negative;
  negative.scene_dir = fern;
  negative.init = "sparse";
  negative.init_resolution = -2;
  negative.config.device = "cpu";
  negative.out_dir = dir_ / "negative";
  const absl::Status refused = run_init_only(negative, [](const std::string&) {});
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(refused.message()).find("init resolution must be >= 0"), std::string::npos) << refused;
}

// "auto" on fern (forward-facing) at -r 16: PatchMatch reads the -r 8 views (504x378), SIFT stays at the training
// size, and metrics.json records the resolution and settings as used. A user's own --init-resolution keeps them.
TEST_F(InitResolution, AutoGivesPatchMatchTwiceTheTrainingSizeOnForwardFacingCaptures) {
  const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!fs::exists(fern)) GTEST_SKIP() << "no benchmark data at " << fern;
  RunOptions o = cheap_auto(fern);
  o.config.iterations = 10;
  o.html_report = false;
  o.save_renders = false;
  o.out_dir = dir_ / "auto";
  std::string log;
  const auto logged = [&](const std::string& line) { log += line + "\n"; };
  const absl::StatusOr<RunResult> run = run_pipeline(o, {}, logged);
  ASSERT_TRUE(run.ok()) << run.status() << "\n" << log;
  EXPECT_TRUE(test::contains(log,
                             "init: auto: the views face one way, so PatchMatch reads them at twice the "
                             "training size (504 pixels on the longest side)"))
      << log;
  EXPECT_TRUE(test::contains(log, "init: reading the training views at 504x378 (init resolution 8)")) << log;
  EXPECT_EQ(run->init.method, "mvs") << log;
  EXPECT_DOUBLE_EQ(run->init.resolution, 8.0);
  EXPECT_EQ(run->init.patchmatch.max_image_side, 504);
  EXPECT_EQ(run->init.sparse.max_image_side, 252);
  EXPECT_EQ(run->init.patchmatch.iterations, 3);
  EXPECT_FALSE(test::contains(log, "not used")) << log;
  EXPECT_TRUE(test::contains(log, "budget: auto: the views face one way, so 2 Gaussians per unit")) << log;
  EXPECT_TRUE(test::contains(log, absl::StrCat("automatic budget: ", run->max_gaussians, " Gaussians (2 per unit")))
      << log;
  EXPECT_EQ(run->config.gaussians_per_variation, kAutoLargerViewsGaussiansPerVariation);
  std::ifstream file(o.out_dir / "metrics.json");
  const nlohmann::json metrics = nlohmann::json::parse(file);
  EXPECT_EQ(metrics["config"]["gaussians_per_variation"], kAutoLargerViewsGaussiansPerVariation) << metrics["config"];
  EXPECT_EQ(metrics["init_resolution"], 8) << metrics;
  EXPECT_EQ(metrics["init_options"]["patchmatch_max_image_side"], 504) << metrics["init_options"];
  EXPECT_EQ(metrics["init_options"]["sparse_max_image_side"], 252) << metrics["init_options"];
  // What the initialisation gave and cost: the initial Gaussians as logged, its seconds, computed (no cache here).
  EXPECT_GT(run->init.points, 0);
  EXPECT_TRUE(test::contains(log, absl::StrCat("initial points: ", run->init.points, "\n"))) << log;
  EXPECT_EQ(metrics["init_points"], run->init.points) << metrics;
  EXPECT_GT(metrics["init_seconds"].get<double>(), 0.0) << metrics;
  EXPECT_DOUBLE_EQ(metrics["init_seconds"].get<double>(), run->init.seconds);
  EXPECT_EQ(metrics["init_from_cache"], false) << metrics;

  RunOptions own = o;
  own.init_resolution = 16;
  own.out_dir = dir_ / "own";
  std::string own_log;
  ASSERT_TRUE(run_init_only(own, [&](const std::string& line) { own_log += line + "\n"; }).ok()) << own_log;
  EXPECT_FALSE(test::contains(own_log, "twice the training size")) << own_log;
  EXPECT_FALSE(test::contains(own_log, "budget: auto")) << own_log;
  EXPECT_TRUE(test::contains(own_log, "init: mvs, ")) << own_log;
}

// The cameras of a benchmark scene's training views at a resolution (none, with a failure, if it cannot be read).
std::vector<Camera> training_cameras(const fs::path& root, int resolution, int views) {
  SceneLoadOptions load;
  load.resolution = resolution;
  const absl::StatusOr<Scene> scene = load_scene(root, load);
  EXPECT_TRUE(scene.ok()) << scene.status();
  std::vector<Camera> cameras;
  if (!scene.ok()) return cameras;
  const absl::StatusOr<Split> split = benchmark_split(static_cast<int>(scene->cameras.size()), views);
  EXPECT_TRUE(split.ok()) << split.status();
  if (!split.ok()) return cameras;
  for (int i : split->train) cameras.push_back(scene->cameras[i]);
  return cameras;
}

// The rule of auto_reads_larger_views on the benchmark scenes' cameras: fern's training views (forward-facing,
// 504 pixels at -r 8) are read larger, bonsai's (surrounding) are not; nor fern's when a user sets the views'
// sizes, when another method is asked for, or when twice the views would exceed kAutoLargerViewsMaxSide.
TEST(AutoInitialisation, LargerViewsForForwardFacingSmallViewsOnly) {
  const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  const fs::path bonsai = fs::path(GAPS_DATA_DIR) / "mipnerf360" / "bonsai";
  if (!fs::exists(fern) || !fs::exists(bonsai)) GTEST_SKIP() << "no benchmark data under " << GAPS_DATA_DIR;
  const RunOptions defaults;
  const std::vector<Camera> fern3 = training_cameras(fern, 8, 3);
  EXPECT_TRUE(auto_reads_larger_views(defaults, fern3));
  EXPECT_TRUE(auto_reads_larger_views(defaults, training_cameras(fern, 8, 9)));
  EXPECT_FALSE(auto_reads_larger_views(defaults, training_cameras(bonsai, 8, 12)));
  EXPECT_FALSE(auto_reads_larger_views(defaults, training_cameras(bonsai, 8, 24)));
  EXPECT_FALSE(auto_reads_larger_views(defaults, training_cameras(fern, 4, 3))) << "2016 pixels: above the limit";
  EXPECT_FALSE(auto_reads_larger_views(defaults, {}));
  for (const auto& set : std::vector<std::function<void(RunOptions&)>>{
           [](RunOptions& o) { o.init = "mvs"; }, [](RunOptions& o) { o.init_resolution = 8; },
           [](RunOptions& o) { o.patchmatch.max_image_side = 1008; },
           [](RunOptions& o) { o.sparse.max_image_side = 504; }}) {
    RunOptions o;
    set(o);
    EXPECT_FALSE(auto_reads_larger_views(o, fern3));
  }
  RunOptions other_settings;
  other_settings.patchmatch.iterations = 3;
  other_settings.fusion.add_sparse_points = true;
  EXPECT_TRUE(auto_reads_larger_views(other_settings, fern3)) << "settings other than the sizes leave the rule alone";
}

// The automatic budget density (TrainConfig's default, < 0) is kAutoLargerViewsGaussiansPerVariation where auto
// reads the larger views (fern), kDefaultGaussiansPerVariation elsewhere (bonsai, another method, a count given);
// a density the user gives is kept, the default's own value too.
TEST(AutoInitialisation, ASmallerBudgetWhereItReadsLargerViews) {
  const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  const fs::path bonsai = fs::path(GAPS_DATA_DIR) / "mipnerf360" / "bonsai";
  if (!fs::exists(fern) || !fs::exists(bonsai)) GTEST_SKIP() << "no benchmark data under " << GAPS_DATA_DIR;
  const std::vector<Camera> fern3 = training_cameras(fern, 8, 3);
  const auto density = [&](const RunOptions& o, const std::vector<Camera>& cameras) {
    return with_auto_budget(o, cameras).config.gaussians_per_variation;
  };
  const RunOptions defaults;
  EXPECT_EQ(density(defaults, fern3), kAutoLargerViewsGaussiansPerVariation);
  EXPECT_EQ(density(defaults, training_cameras(bonsai, 8, 24)), kDefaultGaussiansPerVariation);
  RunOptions mvs;
  mvs.init = "mvs";
  EXPECT_EQ(density(mvs, fern3), kDefaultGaussiansPerVariation);
  for (const double given : {kDefaultGaussiansPerVariation, 5.0, 0.0}) {
    RunOptions own;
    own.config.gaussians_per_variation = given;
    EXPECT_EQ(density(own, fern3), given);
  }
  RunOptions own_count;
  own_count.config.max_gaussians = 50000;
  const RunOptions counted = with_auto_budget(own_count, fern3);
  EXPECT_EQ(counted.config.gaussians_per_variation, kDefaultGaussiansPerVariation);
  EXPECT_EQ(counted.config.max_gaussians, 50000);
}

// A scene without views at twice the training size (here fern with its -r 16 images alone) trains from the
// training views, and says so.
TEST_F(InitResolution, AutoWithoutLargerViewsReadsTheTrainingViews) {
  const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
  if (!fs::exists(fern)) GTEST_SKIP() << "no benchmark data at " << fern;
  SceneLoadOptions load;
  load.resolution = 16;
  const absl::StatusOr<Scene> scene = load_scene(fern, load);
  ASSERT_TRUE(scene.ok()) << scene.status();
  const fs::path small = dir_ / "fern_small";
  fs::create_directories(small / "images_16");
  fs::copy_file(fern / "poses_bounds.npy", small / "poses_bounds.npy");
  for (const Camera& camera : scene->cameras) {
    const absl::StatusOr<at::Tensor> image = load_camera_image(camera);
    ASSERT_TRUE(image.ok()) << image.status();
    ASSERT_TRUE(write_png(small / "images_16" / fs::path(camera.name).filename(), *image).ok());
  }
  RunOptions o = cheap_auto(small);
  o.out_dir = dir_ / "small";
  std::string log;
  ASSERT_TRUE(run_init_only(o, [&](const std::string& line) { log += line + "\n"; }).ok()) << log;
  EXPECT_TRUE(test::contains(log, "init: auto: no views at twice the training size for PatchMatch (")) << log;
  EXPECT_FALSE(test::contains(log, "PatchMatch reads them at twice")) << log;
  EXPECT_TRUE(test::contains(log, "): it reads the training views")) << log;
  EXPECT_TRUE(test::contains(log, "init: mvs, ")) << log;
}

}  // namespace
}  // namespace gaps

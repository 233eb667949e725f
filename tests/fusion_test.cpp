// Fusion of per-view depth and normal maps (init/fusion.h) on maps built analytically, and their export as a
// COLMAP dense workspace (init/colmap_dense.h).
#include "gs_trainer/init/fusion.h"

#include <cmath>
#include <cstring>
#include <filesystem>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <Eigen/Dense>

#include "common/io_util.h"
#include "common/ply.h"
#include "gs_trainer/init/colmap_dense.h"
#include "gs_trainer/scene/camera_path.h"
#include "gs_trainer/scene/colmap.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

constexpr int kWidth = 80, kHeight = 60;

// Three views of the region around (0, 0, 4) from a ~0.6 wide baseline (world y points down).
std::vector<Camera> three_cameras() {
  Camera intrinsics;
  intrinsics.width = kWidth;
  intrinsics.height = kHeight;
  intrinsics.fx = intrinsics.fy = 80;
  intrinsics.cx = kWidth / 2.0;
  intrinsics.cy = kHeight / 2.0;
  const Eigen::Vector3d target(0, 0, 4), up(0, -1, 0);
  std::vector<Camera> cams = {look_at(intrinsics, {0, 0, 0}, target, up),
                              look_at(intrinsics, {0.35, 0.05, 0.1}, target, up),
                              look_at(intrinsics, {-0.3, -0.1, -0.05}, target, up)};
  for (size_t i = 0; i < cams.size(); ++i) cams[i].name = "view" + std::to_string(i) + ".jpg";
  return cams;
}

// Maps with no depth anywhere; tests then set the pixels they need.
std::vector<ViewDepthNormal> empty_maps(const std::vector<Camera>& cams) {
  std::vector<ViewDepthNormal> maps;
  for (const Camera& c : cams) {
    ViewDepthNormal m;
    m.camera = c;
    m.image = at::zeros({c.height, c.width, 3});
    m.depth = at::zeros({c.height, c.width});
    m.normal = at::zeros({c.height, c.width, 3});
    m.cost = at::zeros({c.height, c.width});
    maps.push_back(m);
  }
  return maps;
}

// The world point at the centre of pixel (x, y) of `c` at camera depth z.
Eigen::Vector3d pixel_point(const Camera& c, int x, int y, double z) {
  const Eigen::Vector3d cam = z * Eigen::Vector3d((x + 0.5 - c.cx) / c.fx, (y + 0.5 - c.cy) / c.fy, 1.0);
  return c.R.transpose() * (cam - c.t);
}

// Writes what view `m` sees of world point X (with world normal N and colour rgb) into the pixel X falls in,
// its depth scaled by depth_scale.
void observe(ViewDepthNormal* m, const Eigen::Vector3d& X, const Eigen::Vector3d& N, const Eigen::Vector3d& rgb,
             double depth_scale = 1.0) {
  const Camera& c = m->camera;
  const Eigen::Vector3d p = c.R * X + c.t;
  const int x = static_cast<int>(std::floor(c.fx * p.x() / p.z() + c.cx));
  const int y = static_cast<int>(std::floor(c.fy * p.y() / p.z() + c.cy));
  ASSERT_TRUE(x >= 0 && x < c.width && y >= 0 && y < c.height);
  const Eigen::Vector3d n = c.R * N;
  m->depth[y][x] = p.z() * depth_scale;
  for (int k = 0; k < 3; ++k) {
    m->normal[y][x][k] = n[k];
    m->image[y][x][k] = rgb[k];
  }
}

Eigen::Vector3d row(const at::Tensor& t, int64_t i) {
  const at::Tensor r = t[i].to(at::kDouble).contiguous();
  return Eigen::Vector3d(r[0].item<double>(), r[1].item<double>(), r[2].item<double>());
}

// Three points at the centres of view 0's pixels: the first seen by view 0 only, the second by views 0 and 1,
// the third by all three, each view with its own colour and a normal a few degrees off the others'.
struct ThreePoints {
  std::vector<Camera> cams = three_cameras();
  std::vector<ViewDepthNormal> maps = empty_maps(cams);
  Eigen::Vector3d points[3] = {pixel_point(cams[0], 20, 20, 4.0), pixel_point(cams[0], 40, 30, 4.2),
                               pixel_point(cams[0], 55, 40, 3.8)};
  // Facing the cameras (-z), tilted per view by up to ~5 degrees.
  Eigen::Vector3d normals[3] = {Eigen::Vector3d(0.05, 0, -1).normalized(),
                                Eigen::Vector3d(-0.05, 0.04, -1).normalized(),
                                Eigen::Vector3d(0, -0.06, -1).normalized()};
  Eigen::Vector3d colours[3] = {{0.2, 0.4, 0.6}, {0.5, 0.1, 0.9}, {0.8, 0.7, 0.0}};

  // view_scale: the depth factor of view 2's observation of the third point.
  explicit ThreePoints(double view2_scale = 1.0) {
    for (int p = 0; p < 3; ++p)
      for (int v = 0; v <= p; ++v)
        observe(&maps[v], points[p], normals[v], colours[v], p == 2 && v == 2 ? view2_scale : 1.0);
  }
};

FusedCloud fuse(const std::vector<ViewDepthNormal>& maps, int min_views) {
  FusionOptions o;
  o.min_views = min_views;
  auto fused = fuse_patchmatch_maps(maps, o);
  EXPECT_TRUE(fused.ok()) << fused.status();
  return fused.ok() ? *fused : FusedCloud{};
}

TEST(Fusion, KeepsOnlyPointsThatMinViewsSupport) {
  const ThreePoints scene;
  const FusedCloud three = fuse(scene.maps, 3);
  ASSERT_EQ(three.points.xyz.size(0), 1);
  // The mean of three pixel points, each within half a pixel (about 0.03 units at depth 4) of the truth.
  EXPECT_LT((row(three.points.xyz, 0) - scene.points[2]).norm(), 0.03);
  EXPECT_EQ(three.stats.depth_pixels, (std::vector<int64_t>{3, 2, 1}));
  EXPECT_EQ(three.stats.fused_points, 1);
  EXPECT_EQ(three.stats.points, 1);

  const FusedCloud two = fuse(scene.maps, 2);
  ASSERT_EQ(two.points.xyz.size(0), 2);
  EXPECT_LT((row(two.points.xyz, 0) - scene.points[1]).norm(), 0.03);
  EXPECT_LT((row(two.points.xyz, 1) - scene.points[2]).norm(), 0.03);
  // Views 1 and 2 add no cluster of their own: their pixels joined view 0's.
  EXPECT_EQ(two.stats.clusters, 3);
  EXPECT_EQ(fuse(scene.maps, 1).points.xyz.size(0), 3);
}

TEST(Fusion, AveragesColoursAndNormals) {
  const ThreePoints scene;
  const FusedCloud fused = fuse(scene.maps, 3);
  ASSERT_EQ(fused.points.xyz.size(0), 1);
  const Eigen::Vector3d mean_colour = (scene.colours[0] + scene.colours[1] + scene.colours[2]) / 3.0;
  EXPECT_LT((row(fused.points.rgb, 0) - mean_colour).norm(), 1e-6);
  const Eigen::Vector3d mean_normal = (scene.normals[0] + scene.normals[1] + scene.normals[2]).normalized();
  EXPECT_LT((row(fused.normals, 0) - mean_normal).norm(), 1e-5);
  EXPECT_NEAR(row(fused.normals, 0).norm(), 1.0, 1e-6);
}

TEST(Fusion, ADepthFivePercentOffDoesNotCount) {
  const ThreePoints scene(/*view2_scale=*/1.05);
  EXPECT_EQ(fuse(scene.maps, 3).points.xyz.size(0), 0);
  // Views 0 and 1 still agree on the third point.
  EXPECT_EQ(fuse(scene.maps, 2).points.xyz.size(0), 2);
  // Half a percent is within max_depth_error (1 %).
  EXPECT_EQ(fuse(ThreePoints(1.005).maps, 3).points.xyz.size(0), 1);
}

TEST(Fusion, ANormalOffByMoreThanTheLimitDoesNotCount) {
  ThreePoints scene;
  // View 2's normal of the third point turned by 20 degrees about the camera's x axis.
  const Eigen::Vector3d X = scene.points[2];
  const Eigen::Vector3d turned = Eigen::AngleAxisd(20.0 * M_PI / 180.0, Eigen::Vector3d::UnitX()) * scene.normals[2];
  observe(&scene.maps[2], X, turned, scene.colours[2]);
  EXPECT_EQ(fuse(scene.maps, 3).points.xyz.size(0), 0);
}

TEST(Fusion, ViewsWithoutDepthContributeNothing) {
  const ThreePoints scene;
  const FusedCloud reference = fuse(scene.maps, 2);
  std::vector<ViewDepthNormal> with_empty = scene.maps;
  Camera extra = scene.cams[1];
  extra.name = "empty.jpg";
  with_empty.push_back(empty_maps({extra})[0]);
  const FusedCloud same = fuse(with_empty, 2);
  EXPECT_TRUE(at::equal(same.points.xyz, reference.points.xyz));
  EXPECT_EQ(same.stats.depth_pixels.back(), 0);

  const FusedCloud nothing = fuse(empty_maps(scene.cams), 1);
  EXPECT_EQ(nothing.points.xyz.size(0), 0);
  EXPECT_EQ(nothing.normals.size(0), 0);
  EXPECT_EQ(nothing.stats.clusters, 0);
}

// A plane seen by two views at every pixel: a dense cloud, capped by voxel averaging.
TEST(Fusion, CapsThePointCountAndKeepsNormalsUnit) {
  const std::vector<Camera> cams = three_cameras();
  std::vector<ViewDepthNormal> maps = empty_maps({cams[0], cams[1]});
  const Eigen::Vector3d N = Eigen::Vector3d(0.1, -0.1, -1).normalized(), P(0, 0, 4);
  for (ViewDepthNormal& m : maps) {
    const Camera& c = m.camera;
    for (int y = 0; y < c.height; ++y)
      for (int x = 0; x < c.width; ++x) {
        // Ray-plane intersection at the pixel centre (camera z of the hit point).
        const Eigen::Vector3d ray =
            c.R.transpose() * Eigen::Vector3d((x + 0.5 - c.cx) / c.fx, (y + 0.5 - c.cy) / c.fy, 1);
        const double s = N.dot(P - c.center()) / N.dot(ray);
        m.depth[y][x] = s;
        const Eigen::Vector3d n = c.R * N;
        for (int k = 0; k < 3; ++k) m.normal[y][x][k] = n[k];
      }
  }
  FusionOptions o;
  auto all = fuse_patchmatch_maps(maps, o);
  ASSERT_TRUE(all.ok()) << all.status();
  EXPECT_GT(all->stats.fused_points, kWidth * kHeight / 2);
  EXPECT_EQ(all->stats.voxel_size, 0.0);
  o.max_points = 500;
  auto capped = fuse_patchmatch_maps(maps, o);
  ASSERT_TRUE(capped.ok()) << capped.status();
  EXPECT_EQ(capped->stats.fused_points, all->stats.fused_points);
  EXPECT_LE(capped->points.xyz.size(0), 500);
  EXPECT_GT(capped->points.xyz.size(0), 250);
  EXPECT_EQ(capped->stats.points, capped->points.xyz.size(0));
  EXPECT_GT(capped->stats.voxel_size, 0.0);
  EXPECT_EQ(capped->normals.size(0), capped->points.xyz.size(0));
  EXPECT_LT((capped->normals.norm(2, 1) - 1.0).abs().max().item<double>(), 1e-5);
  // Points on the plane, normals its normal.
  const at::Tensor n = at::tensor({N.x(), N.y(), N.z()}, at::kFloat);
  EXPECT_LT((at::matmul(capped->points.xyz, n) - N.dot(P)).abs().max().item<double>(), 1e-3);
  EXPECT_GT(at::matmul(capped->normals, n).min().item<double>(), 0.9999);
}

TEST(Fusion, MapsThatDoNotMatchTheirCameraAreRefused) {
  std::vector<ViewDepthNormal> maps = empty_maps(three_cameras());
  maps[1].depth = at::zeros({kHeight, kWidth + 1});
  auto fused = fuse_patchmatch_maps(maps);
  ASSERT_FALSE(fused.ok());
  EXPECT_TRUE(test::contains(std::string(fused.status().message()), "view1.jpg")) << fused.status();
}

class ColmapDense : public test::TempDirTest {};

TEST_F(ColmapDense, MatRoundTripsInCOLMAPsLayout) {
  // value = channel * 1e6 + row * 1000 + column: no two elements alike, rows differ from columns.
  const int64_t H = 3, W = 5, C = 2;
  const at::Tensor r = at::arange(H, at::kFloat).view({H, 1, 1}), x = at::arange(W, at::kFloat).view({1, W, 1});
  const at::Tensor c = at::arange(C, at::kFloat).view({1, 1, C});
  const at::Tensor map = c * 1e6 + r * 1000 + x;
  const fs::path file = dir_ / "normal.bin";
  ASSERT_TRUE(write_colmap_mat(file, map).ok());
  const std::string bytes = test::read_text(file);
  const std::string header = "5&3&2&";
  ASSERT_EQ(bytes.substr(0, header.size()), header);
  ASSERT_EQ(bytes.size(), header.size() + H * W * C * sizeof(float));
  // COLMAP's Mat: channel-major planes, rows of `width` values (element c * W * H + r * W + x).
  const auto element = [&](int64_t i) {
    float v;
    std::memcpy(&v, bytes.data() + header.size() + i * sizeof(float), sizeof(float));
    return v;
  };
  EXPECT_EQ(element(0), 0.0f);
  EXPECT_EQ(element(1), 1.0f);             // row 0, column 1
  EXPECT_EQ(element(W), 1000.0f);          // row 1, column 0
  EXPECT_EQ(element(2 * W + 4), 2004.0f);  // row 2, column 4
  EXPECT_EQ(element(W * H), 1e6f);         // channel 1, row 0, column 0
  EXPECT_EQ(element(W * H + 1 * W + 3), 1001003.0f);
  auto back = read_colmap_mat(file);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_TRUE(at::equal(*back, map));

  // One channel: an HxW map, header "W&H&1&".
  const at::Tensor depth = (r * 1000 + x).squeeze(2);
  ASSERT_TRUE(write_colmap_mat(dir_ / "depth.bin", depth).ok());
  EXPECT_EQ(test::read_text(dir_ / "depth.bin").substr(0, 6), "5&3&1&");
  auto depth_back = read_colmap_mat(dir_ / "depth.bin");
  ASSERT_TRUE(depth_back.ok()) << depth_back.status();
  EXPECT_TRUE(at::equal(*depth_back, depth));
}

TEST_F(ColmapDense, ReaderRefusesBrokenFiles) {
  for (const auto& [name, bytes] : std::vector<std::pair<std::string, std::string>>{
           {"no_header.bin", "hello"},
           {"zero.bin", "0&3&1&"},
           {"short.bin", "2&2&1&" + std::string(12, '\0')},
           {"huge.bin", "99999999999&99999999999&99999999&" + std::string(8, '\0')}}) {
    const auto read = read_colmap_mat(write(name, bytes));
    EXPECT_EQ(read.status().code(), absl::StatusCode::kInvalidArgument) << name;
    EXPECT_TRUE(test::contains(std::string(read.status().message()), name)) << read.status();
  }
}

TEST_F(ColmapDense, WorkspaceHoldsMapsImagesModelAndFusedCloud) {
  ThreePoints scene;
  for (ViewDepthNormal& m : scene.maps) m.image = at::rand({kHeight, kWidth, 3});
  FusionOptions o;
  o.min_views = 2;
  auto fused = fuse_patchmatch_maps(scene.maps, o);
  ASSERT_TRUE(fused.ok()) << fused.status();
  ASSERT_EQ(fused->points.xyz.size(0), 2);
  const PointCloud sparse{at::rand({7, 3}), at::rand({7, 3})};
  const fs::path ws = dir_ / "dense";
  ASSERT_TRUE(write_colmap_dense_workspace(ws, scene.maps, *fused, sparse).ok());

  for (const ViewDepthNormal& m : scene.maps) {
    const std::string name = dense_image_name(m.camera);
    EXPECT_EQ(name, fs::path(m.camera.name).stem().string() + ".png");
    EXPECT_TRUE(fs::exists(ws / "images" / name)) << name;
    auto depth = read_colmap_mat(ws / "stereo" / "depth_maps" / (name + ".geometric.bin"));
    ASSERT_TRUE(depth.ok()) << depth.status();
    EXPECT_TRUE(at::equal(*depth, m.depth));
    auto normal = read_colmap_mat(ws / "stereo" / "normal_maps" / (name + ".geometric.bin"));
    ASSERT_TRUE(normal.ok()) << normal.status();
    EXPECT_TRUE(at::equal(*normal, m.normal));
  }
  EXPECT_EQ(test::read_text(ws / "stereo" / "fusion.cfg"), "view0.png\nview1.png\nview2.png\n");

  // The sparse model: cameras at the maps' size, images named as the files, the sparse points.
  auto model = read_colmap_model(ws / "sparse");
  ASSERT_TRUE(model.ok()) << model.status();
  ASSERT_EQ(model->images.size(), 3u);
  EXPECT_EQ(model->images.at(1).name, "view0.png");
  EXPECT_EQ(model->cameras.at(1).width, kWidth);
  EXPECT_EQ(model->points.size(), 7u);

  // fused.ply: COLMAP's header, and it reads back with the points, normals and 8-bit colours.
  const std::string ply = test::read_text(ws / "fused.ply");
  EXPECT_EQ(ply.substr(0, ply.find("end_header\n") + 11),
            "ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
            "property float z\nproperty float nx\nproperty float ny\nproperty float nz\nproperty uchar red\n"
            "property uchar green\nproperty uchar blue\nend_header\n");
  auto vertices = read_ply_vertices(ws / "fused.ply");
  ASSERT_TRUE(vertices.ok()) << vertices.status();
  ASSERT_EQ(vertices->count, 2);
  EXPECT_TRUE(at::allclose(vertices->properties.at("nx"), fused->normals.select(1, 0)));
  auto cloud = read_point_cloud_ply(ws / "fused.ply");
  ASSERT_TRUE(cloud.ok()) << cloud.status();
  EXPECT_TRUE(at::allclose(cloud->xyz, fused->points.xyz));
  EXPECT_LE((cloud->rgb - fused->points.rgb).abs().max().item<double>(), 0.5 / 255 + 1e-6);
}

}  // namespace
}  // namespace gaps

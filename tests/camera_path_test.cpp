// The camera paths of `gaps render` (gs_trainer/scene/camera_path.h): frame counts, and every frame's pose on
// the path it belongs to (orbit: radius, centre, height and look-at; spiral: focus and radii; interp: through
// the training cameras at their frames; test: the test cameras; a cameras.json file read back as written).
#include <cmath>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <Eigen/Geometry>

#include "gs_trainer/scene/camera_path.h"
#include "gs_trainer/scene/cameras_json.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

constexpr double kPi = 3.14159265358979323846;

Camera base_camera() {
  Camera c;
  c.width = 64;
  c.height = 48;
  c.fx = c.fy = 60;
  c.cx = 32;
  c.cy = 24;
  return c;
}

// Cameras on a tilted ring around `centre`, above it along `up`, each looking at it.
std::vector<Camera> ring(const Eigen::Vector3d& centre, const Eigen::Vector3d& up, int n, double radius,
                         double height) {
  const Eigen::Vector3d e1 = up.unitOrthogonal(), e2 = up.cross(e1);
  std::vector<Camera> cameras;
  for (int i = 0; i < n; ++i) {
    const double a = 2 * kPi * i / n + 0.3;
    const Eigen::Vector3d p = centre + height * up + radius * (std::cos(a) * e1 + std::sin(a) * e2);
    cameras.push_back(look_at(base_camera(), p, centre, up));
  }
  return cameras;
}

// A forward-facing capture: cameras spread on a plane, all looking along +z (up is -y), with depth bounds.
std::vector<Camera> forward_facing() {
  std::vector<Camera> cameras;
  const double xs[] = {-0.4, -0.1, 0.2, 0.5, -0.3, 0.35};
  const double ys[] = {0.1, -0.2, 0.15, -0.05, 0.25, -0.3};
  for (int i = 0; i < 6; ++i) {
    Camera c = base_camera();
    const Eigen::Vector3d p(xs[i], ys[i], 0.02 * i);
    c.t = -c.R * p;
    c.near = 2.0;
    c.far = 10.0;
    cameras.push_back(c);
  }
  return cameras;
}

// The sine of the angle between the camera's viewing direction and the direction to `target` (1 and more
// when `target` is behind the camera).
double look_error(const Camera& c, const Eigen::Vector3d& target) {
  const Eigen::Vector3d to_target = (target - c.center()).normalized();
  if (c.forward().dot(to_target) <= 0) return 1.0 + c.forward().cross(to_target).norm();
  return c.forward().cross(to_target).norm();
}

TEST(CameraPath, OrbitCirclesTheCentreAtTheCamerasMeanDistanceAndHeightLookingAtIt) {
  const Eigen::Vector3d centre(0.5, -1.0, 2.0), up = Eigen::Vector3d(0.1, -1.0, 0.2).normalized();
  PathScene scene;
  scene.train = ring(centre, up, 5, 3.0, 1.0);
  EXPECT_LT((scene_centre(scene) - centre).norm(), 1e-9);
  const auto path = camera_path("orbit", scene, 24);
  ASSERT_TRUE(path.ok()) << path.status();
  ASSERT_EQ(path->size(), 24u);
  for (const Camera& c : *path) {
    EXPECT_NEAR((c.center() - centre).norm(), std::sqrt(10.0), 1e-9);
    EXPECT_NEAR((c.center() - centre).dot(up), 1.0, 1e-9);  // in the plane orthogonal to the mean up
    EXPECT_LT(look_error(c, centre), 1e-9);
    EXPECT_GT(-c.R.row(1).dot(up), 0.9);  // upright
    EXPECT_EQ(c.width, 64);
    EXPECT_DOUBLE_EQ(c.fx, 60);
    EXPECT_NEAR(c.R.determinant(), 1.0, 1e-12);
  }
  // Evenly around the full circle, starting at the first camera's azimuth.
  const Eigen::Vector3d a = (*path)[0].center() - centre - up, b = (*path)[6].center() - centre - up;
  EXPECT_NEAR(std::acos(a.normalized().dot(b.normalized())), kPi / 2, 1e-9);
  const Eigen::Vector3d first = scene.train[0].center() - centre - up;
  EXPECT_NEAR(a.normalized().dot(first.normalized()), 1.0, 1e-9);
  EXPECT_EQ((*path)[0].name, "00000.png");
  EXPECT_EQ((*path)[23].name, "00023.png");
}

TEST(CameraPath, SpiralLooksAtTheFocusDepthFromTheBoundsWithinTheCamerasSpread) {
  PathScene scene;
  scene.train = forward_facing();
  scene.near = 2.0;
  scene.far = 10.0;
  const double focus_depth = 1.0 / (0.25 / 1.8 + 0.75 / 50.0);
  EXPECT_NEAR(spiral_focus_depth(2.0, 10.0), focus_depth, 1e-12);
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const Camera& c : scene.train) mean += c.center();
  mean /= 6.0;
  const Eigen::Vector3d focus = mean + focus_depth * Eigen::Vector3d::UnitZ();
  const auto path = camera_path("spiral", scene, 30);
  ASSERT_TRUE(path.ok()) << path.status();
  ASSERT_EQ(path->size(), 30u);
  // Radii: the 90th percentiles of |x|, |y|, |z| about the mean (the cameras' axes are the world's here).
  const double rx = 0.5 - 0.25 / 6, ry = 0.3 - 0.05 / 6;
  double max_x = 0, max_y = 0;
  for (const Camera& c : *path) {
    EXPECT_LT(look_error(c, focus), 1e-9);
    const Eigen::Vector3d d = c.center() - mean;
    EXPECT_LE(std::abs(d.x()), rx + 1e-9);
    EXPECT_LE(std::abs(d.y()), ry + 1e-9);
    max_x = std::max(max_x, std::abs(d.x()));
    max_y = std::max(max_y, std::abs(d.y()));
  }
  EXPECT_NEAR((*path)[0].center().x() - mean.x(), rx, 1e-9);  // θ = 0: (r_x, 0, 0)
  EXPECT_GT(max_x, 0.95 * rx);
  EXPECT_GT(max_y, 0.95 * ry);
}

TEST(CameraPath, ForwardFacingCentreIsAtTheFocusDepthAlongTheMeanView) {
  PathScene scene;
  scene.train = forward_facing();
  scene.near = 2.0;
  scene.far = 10.0;
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const Camera& c : scene.train) mean += c.center();
  mean /= 6.0;
  EXPECT_LT((scene_centre(scene) - (mean + spiral_focus_depth(2.0, 10.0) * Eigen::Vector3d::UnitZ())).norm(), 1e-9);
}

TEST(CameraPath, InterpPassesThroughTheTrainingCamerasAtTheirFrames) {
  PathScene scene;
  scene.train = ring(Eigen::Vector3d::Zero(), -Eigen::Vector3d::UnitY(), 4, 2.0, 0.5);
  scene.train[2].fx = 90;  // only the first camera's intrinsics are used
  const int frames = 3 * 3 + 1;
  const auto path = camera_path("interp", scene, frames);
  ASSERT_TRUE(path.ok()) << path.status();
  ASSERT_EQ(path->size(), static_cast<size_t>(frames));
  for (int i = 0; i < 4; ++i) {
    const Camera& c = (*path)[3 * i];
    EXPECT_LT((c.center() - scene.train[i].center()).norm(), 1e-9) << "camera " << i;
    EXPECT_LT((c.R - scene.train[i].R).norm(), 1e-9) << "camera " << i;
    EXPECT_DOUBLE_EQ(c.fx, 60);
  }
  // Between two cameras: rotation on the geodesic (equal angles to both at the midpoint of a segment would
  // need an odd count; here a third of the way: a third of the angle), position off the chord (a spline).
  const Eigen::Quaterniond q0(scene.train[0].R), q1(scene.train[1].R), q(((*path)[1]).R);
  EXPECT_NEAR(q.angularDistance(q0), q0.angularDistance(q1) / 3, 1e-9);
  EXPECT_NEAR(q.angularDistance(q1), 2 * q0.angularDistance(q1) / 3, 1e-9);
}

TEST(CameraPath, TestIsTheTestCamerasAndAFileIsReadBack) {
  PathScene scene;
  scene.train = forward_facing();
  scene.test = ring(Eigen::Vector3d::Zero(), -Eigen::Vector3d::UnitY(), 3, 2.0, 0.5);
  scene.test[1].fx = 70;
  const auto test = camera_path("test", scene, 99);
  ASSERT_TRUE(test.ok()) << test.status();
  ASSERT_EQ(test->size(), 3u);
  for (size_t i = 0; i < 3; ++i) {
    EXPECT_EQ((*test)[i].R, scene.test[i].R);
    EXPECT_EQ((*test)[i].t, scene.test[i].t);
    EXPECT_EQ((*test)[i].fx, scene.test[i].fx);
  }
  const auto dir = std::filesystem::path(::testing::TempDir()) / "gaps_camera_path_test";
  std::filesystem::create_directories(dir);
  const auto file = dir / "my_path.json";
  std::vector<CameraRecord> records;
  for (const Camera& c : scene.test) records.push_back({c, "path"});
  ASSERT_TRUE(write_cameras_json(file, records).ok());
  const auto read = camera_path(file.string(), scene, 5);
  ASSERT_TRUE(read.ok()) << read.status();
  ASSERT_EQ(read->size(), 3u);
  for (size_t i = 0; i < 3; ++i) {
    EXPECT_LT(((*read)[i].R - scene.test[i].R).norm(), 1e-9);
    EXPECT_LT(((*read)[i].center() - scene.test[i].center()).norm(), 1e-9);
    EXPECT_NEAR((*read)[i].fx, scene.test[i].fx, 1e-9);
  }
  EXPECT_EQ(camera_path_name(file.string()), "my_path");
  std::filesystem::remove(file);
  EXPECT_FALSE(camera_path((dir / "missing.json").string(), scene, 5).ok());
}

TEST(CameraPath, RefusesUnknownPathsAndEmptyInputs) {
  PathScene scene;
  scene.train = forward_facing();
  scene.near = 2;
  scene.far = 10;
  EXPECT_EQ(camera_path("circle", scene, 5).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(camera_path("orbit", scene, 0).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(camera_path("test", scene, 5).status().code(), absl::StatusCode::kInvalidArgument);  // no test cameras
  EXPECT_EQ(camera_path("interp", PathScene(), 5).status().code(), absl::StatusCode::kInvalidArgument);
  const auto one = camera_path("interp", scene, 1);
  ASSERT_TRUE(one.ok());
  EXPECT_LT((one->front().center() - scene.train[0].center()).norm(), 1e-12);
}

TEST(CameraPath, DepthBoundsComeFromTheCamerasElseFromThePointsInFront) {
  std::vector<Camera> cameras = forward_facing();
  auto given = path_depth_bounds(cameras, at::Tensor());
  ASSERT_TRUE(given.ok());
  EXPECT_EQ(*given, std::make_pair(2.0, 10.0));
  for (Camera& c : cameras) c.near = c.far = 0;
  EXPECT_FALSE(path_depth_bounds(cameras, at::Tensor()).ok());
  // Points at depths 1..100 in front of one camera at the origin, and some behind it (ignored).
  std::vector<Camera> one = {base_camera()};
  at::Tensor points = at::zeros({110, 3});
  points.select(1, 2).slice(0, 0, 100).copy_(at::arange(1, 101, at::kFloat));
  points.select(1, 2).slice(0, 100).fill_(-5);
  auto bounds = path_depth_bounds(one, points);
  ASSERT_TRUE(bounds.ok()) << bounds.status();
  EXPECT_NEAR(bounds->first, 2.0, 1e-6);    // the 1st percentile (nearest rank of 100 values)
  EXPECT_NEAR(bounds->second, 99.0, 1e-6);  // the 99th
}

}  // namespace
}  // namespace gaps

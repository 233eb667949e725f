#include "gs_trainer/scene/scene.h"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <Eigen/Dense>

#include <nlohmann/json.hpp>
#include "tests/test_util.h"

#include "common/image_io.h"
#include "common/npy.h"
#include "gs_trainer/scene/cameras_json.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

constexpr double kPi = 3.14159265358979323846;

bool contains(const absl::Status& status, const std::string& text) {
  return status.message().find(text) != absl::string_view::npos;
}

// The point closest (least squares) to every camera's optical axis, i.e. what the cameras look at.
Eigen::Vector3d look_at_point(const std::vector<Camera>& cameras) {
  Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
  Eigen::Vector3d b = Eigen::Vector3d::Zero();
  for (const Camera& c : cameras) {
    const Eigen::Matrix3d P = Eigen::Matrix3d::Identity() - c.forward() * c.forward().transpose();
    A += P;
    b += P * c.center();
  }
  return A.ldlt().solve(b);
}

// Every camera must have that point in front of it and near its optical axis: a wrong axis convention
// (a flipped forward, swapped x/y) puts it behind the cameras or far off-axis.
void expect_cameras_look_at_common_point(const std::vector<Camera>& cameras, double max_angle_deg) {
  const Eigen::Vector3d target = look_at_point(cameras);
  for (const Camera& c : cameras) {
    const Eigen::Vector3d to_target = target - c.center();
    EXPECT_GT(to_target.dot(c.forward()), 0.0) << c.name << " has the scene centre behind it";
    const double angle = std::acos(std::clamp(to_target.normalized().dot(c.forward()), -1.0, 1.0)) * 180 / kPi;
    EXPECT_LT(angle, max_angle_deg) << c.name;
    EXPECT_TRUE((c.R * c.R.transpose()).isIdentity(1e-9)) << c.name;
    EXPECT_NEAR(c.R.determinant(), 1.0, 1e-9) << c.name;
  }
}

// --- The benchmark split -------------------------------------------------------------------------------

// The protocol written out plainly: test = multiples of 8; train = remaining[round(linspace(0, M-1, N))]
// with numpy's half-to-even rounding.
std::vector<int> protocol_train(int num_images, int num_train) {
  std::vector<int> remaining;
  for (int i = 0; i < num_images; ++i) {
    if (i % 8 != 0) remaining.push_back(i);
  }
  const int m = static_cast<int>(remaining.size());
  std::vector<int> train;
  for (int i = 0; i < num_train; ++i) {
    const double x = num_train == 1 ? 0.0 : i * (static_cast<double>(m - 1) / (num_train - 1));
    train.push_back(remaining[static_cast<int>(std::nearbyint(i == num_train - 1 ? m - 1 : x))]);
  }
  return train;
}

TEST(BenchmarkSplitTest, FernFollowsTheProtocol) {
  // Fern has 20 images: test {0, 8, 16}; M = 17 remaining = 1..7, 9..15, 17..19.
  // N = 3: linspace(0, 16, 3) = 0, 8, 16 -> remaining[0, 8, 16] = 1, 10, 19.
  // N = 6: step 3.2 -> 0, 3.2, 6.4, 9.6, 12.8, 16 -> 0, 3, 6, 10, 13, 16 -> 1, 4, 7, 12, 15, 19.
  // N = 9: step 2 -> 0, 2, ..., 16 -> 1, 3, 5, 7, 10, 12, 14, 17, 19.
  const std::vector<std::pair<int, std::vector<int>>> by_hand = {
      {3, {1, 10, 19}}, {6, {1, 4, 7, 12, 15, 19}}, {9, {1, 3, 5, 7, 10, 12, 14, 17, 19}}};
  for (const auto& [n, train] : by_hand) {
    absl::StatusOr<Split> split = benchmark_split(20, n);
    ASSERT_TRUE(split.ok()) << split.status();
    EXPECT_EQ(split->test, (std::vector<int>{0, 8, 16}));
    EXPECT_EQ(split->train, train) << n << " views";
    EXPECT_EQ(split->train, protocol_train(20, n)) << n << " views";
  }
}

TEST(BenchmarkSplitTest, BonsaiFollowsTheProtocol) {
  // 292 images: 37 test views (0, 8, ..., 288), M = 255. remaining[k] = 8 * (k / 7) + k % 7 + 1.
  // N = 12: linspace(0, 254, 12) rounds to 0, 23, 46, 69, 92, 115, 139, 162, 185, 208, 231, 254.
  absl::StatusOr<Split> split = benchmark_split(292, 12);
  ASSERT_TRUE(split.ok()) << split.status();
  EXPECT_EQ(split->test.size(), 37u);
  EXPECT_EQ(split->test.back(), 288);
  EXPECT_EQ(split->train, (std::vector<int>{1, 27, 53, 79, 106, 132, 159, 186, 212, 238, 265, 291}));
  for (int n : {12, 24}) {
    split = benchmark_split(292, n);
    ASSERT_TRUE(split.ok());
    EXPECT_EQ(split->train, protocol_train(292, n)) << n;
  }
}

TEST(BenchmarkSplitTest, RoundsHalvesToEvenLikeNumpy) {
  // 7 images: test {0}, M = 6; linspace(0, 5, 3) = 0, 2.5, 5 and np.round(2.5) = 2 (not 3).
  absl::StatusOr<Split> split = benchmark_split(7, 3);
  ASSERT_TRUE(split.ok()) << split.status();
  EXPECT_EQ(split->train, (std::vector<int>{1, 3, 6}));
}

TEST(BenchmarkSplitTest, EdgeCasesAndErrors) {
  absl::StatusOr<Split> all = benchmark_split(10, 0);
  ASSERT_TRUE(all.ok());
  EXPECT_EQ(all->train, (std::vector<int>{1, 2, 3, 4, 5, 6, 7, 9}));
  EXPECT_EQ(all->test, (std::vector<int>{0, 8}));
  EXPECT_EQ(benchmark_split(20, 1)->train, (std::vector<int>{1}));
  EXPECT_EQ(benchmark_split(20, 17)->train.size(), 17u);
  EXPECT_EQ(benchmark_split(6, 2, 3)->test, (std::vector<int>{0, 3}));

  absl::StatusOr<Split> too_many = benchmark_split(20, 18);
  ASSERT_FALSE(too_many.ok());
  EXPECT_TRUE(contains(too_many.status(), "18")) << too_many.status();
  EXPECT_TRUE(contains(too_many.status(), "17")) << too_many.status();
  EXPECT_FALSE(benchmark_split(0, 3).ok());
  EXPECT_FALSE(benchmark_split(-4, 3).ok());
  EXPECT_FALSE(benchmark_split(20, 3, 0).ok());
  EXPECT_FALSE(benchmark_split(1, 0).ok()) << "a single image is a test view, leaving nothing to train on";
}

// --- The real benchmark scenes ---------------------------------------------------------------------------

fs::path data_scene(const std::string& relative) { return fs::path(GAPS_DATA_DIR) / relative; }

#define SKIP_WITHOUT(path) \
  if (!fs::exists(path)) GTEST_SKIP() << "no benchmark data at " << (path)

TEST(RealSceneTest, FernAtResolution8) {
  const fs::path root = data_scene("llff/fern");
  SKIP_WITHOUT(root);
  absl::StatusOr<Scene> scene = load_scene(root, SceneLoadOptions{8, ""});
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->format, "llff");
  EXPECT_FALSE(scene->points.has_value());
  ASSERT_EQ(scene->cameras.size(), 20u);
  for (const Camera& c : scene->cameras) {
    EXPECT_EQ(c.width, 504);
    EXPECT_EQ(c.height, 378);
    // focal 3260.526 px at 4032 x 3024 (poses_bounds.npy), an eighth at 504 x 378.
    EXPECT_NEAR(c.fx, 3260.5263328805895 / 8, 1e-9);
    EXPECT_NEAR(c.fy, 3260.5263328805895 / 8, 1e-9);
    EXPECT_EQ(c.cx, 252.0);
    EXPECT_EQ(c.cy, 189.0);
    EXPECT_GT(c.near, 10.0);
    EXPECT_LT(c.far, 100.0);
  }
  EXPECT_EQ(scene->cameras[0].name, "image000.png");
  EXPECT_EQ(scene->cameras[19].image_path, root / "images_8" / "image019.png");
  EXPECT_NEAR(scene->cameras[0].near, 17.74708748, 1e-6);
  EXPECT_NEAR(scene->cameras[0].far, 78.25748707, 1e-6);
  // Forward-facing capture: every camera looks within a few degrees of the common point.
  expect_cameras_look_at_common_point(scene->cameras, 5.0);

  absl::StatusOr<at::Tensor> image = load_camera_image(scene->cameras[3]);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_EQ(image->sizes().vec(), (std::vector<int64_t>{378, 504, 3}));
  EXPECT_GE(image->min().item<float>(), 0.0f);
  EXPECT_LE(image->max().item<float>(), 1.0f);
  EXPECT_GT(image->mean().item<float>(), 0.1f);

  absl::StatusOr<Split> split = benchmark_split(static_cast<int>(scene->cameras.size()), 3);
  ASSERT_TRUE(split.ok());
  const std::string text = describe(*scene, *split);
  std::cout << text;
  for (const char* expected : {"llff", "20 images", "504x378", "image000.png", "fx 407.566", "cx 252.000",
                               "3 train [1, 10, 19]", "3 test [0, 8, 16]", "near 16.99"})
    EXPECT_NE(text.find(expected), std::string::npos) << expected << " missing from:\n" << text;
}

TEST(RealSceneTest, FernOtherResolutions) {
  const fs::path root = data_scene("llff/fern");
  SKIP_WITHOUT(root);
  absl::StatusOr<Scene> quarter = load_scene(root, SceneLoadOptions{4, ""});
  ASSERT_TRUE(quarter.ok()) << quarter.status();
  EXPECT_EQ(quarter->cameras[0].width, 1008);
  EXPECT_NEAR(quarter->cameras[0].fx, 3260.5263328805895 / 4, 1e-9);
  // No images/ folder: "full resolution" is the largest one shipped, images_4.
  absl::StatusOr<Scene> full = load_scene(root);
  ASSERT_TRUE(full.ok()) << full.status();
  EXPECT_EQ(full->cameras[0].image_path.parent_path(), root / "images_4");
  EXPECT_EQ(full->cameras[0].height, 756);
  // R = 2 would need 2016 x 1512 images, which fern does not have.
  absl::StatusOr<Scene> half = load_scene(root, SceneLoadOptions{2, ""});
  ASSERT_FALSE(half.ok());
  EXPECT_TRUE(contains(half.status(), "images_4")) << half.status();
  EXPECT_TRUE(contains(half.status(), "2016x1512")) << half.status();
  // A factor that leaves no pixels is named as the factor it is, with the largest one that works.
  absl::StatusOr<Scene> nothing = load_scene(root, SceneLoadOptions{100000, ""});
  ASSERT_FALSE(nothing.ok());
  EXPECT_EQ(nothing.status().code(), absl::StatusCode::kInvalidArgument) << nothing.status();
  EXPECT_TRUE(contains(nothing.status(), "resolution 100000 would make the 4032x3024 images")) << nothing.status();
  EXPECT_TRUE(contains(nothing.status(), "the factor can be at most 3024")) << nothing.status();
}

TEST(RealSceneTest, FernResizedFromAnExplicitFolder) {
  const fs::path root = data_scene("llff/fern");
  SKIP_WITHOUT(root);
  absl::StatusOr<Scene> scene = load_scene(root, SceneLoadOptions{8, "images_4"});
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->cameras[0].width, 504);
  EXPECT_EQ(scene->cameras[0].image_path, root / "images_4" / "image000.png");
  absl::StatusOr<at::Tensor> resized = load_camera_image(scene->cameras[0]);
  absl::StatusOr<at::Tensor> shipped = read_image(root / "images_8" / "image000.png");
  ASSERT_TRUE(resized.ok() && shipped.ok());
  ASSERT_EQ(resized->sizes(), shipped->sizes());
  // Both are box-filtered versions of the same photo; only resampling details differ.
  EXPECT_LT((*resized - *shipped).abs().mean().item<float>(), 0.02f);
}

TEST(RealSceneTest, BonsaiAtResolution8) {
  const fs::path root = data_scene("mipnerf360/bonsai");
  SKIP_WITHOUT(root);
  absl::StatusOr<Scene> scene = load_scene(root, SceneLoadOptions{8, ""});
  ASSERT_TRUE(scene.ok()) << scene.status();
  // sparse/0 holds cameras.bin only, so the poses come from poses_bounds.npy.
  EXPECT_EQ(scene->format, "llff");
  ASSERT_EQ(scene->cameras.size(), 292u);
  const Camera& first = scene->cameras[0];
  EXPECT_EQ(first.name, "DSCF5565.JPG");
  EXPECT_EQ(first.image_path.parent_path(), root / "images_800x533");
  // round(3118 / 8) x round(2078 / 8); focal 3222.70 px at full size, scaled per axis.
  EXPECT_EQ(first.width, 390);
  EXPECT_EQ(first.height, 260);
  EXPECT_NEAR(first.fx, 3222.7010797592447 * 390 / 3118, 1e-9);
  EXPECT_NEAR(first.fy, 3222.7010797592447 * 260 / 2078, 1e-9);
  EXPECT_NEAR(first.cx, 195.0, 1e-9);
  EXPECT_NEAR(first.cy, 130.0, 1e-9);
  EXPECT_EQ(first.near, 0.1);
  EXPECT_EQ(first.far, 500.0);
  // A 360-degree capture around the bonsai: all cameras aim near one point.
  expect_cameras_look_at_common_point(scene->cameras, 15.0);

  absl::StatusOr<at::Tensor> image = load_camera_image(scene->cameras[291]);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_EQ(image->sizes().vec(), (std::vector<int64_t>{260, 390, 3}));
  EXPECT_GE(image->min().item<float>(), 0.0f);
  EXPECT_LE(image->max().item<float>(), 1.0f);

  absl::StatusOr<Split> split = benchmark_split(292, 12);
  ASSERT_TRUE(split.ok());
  const std::string text = describe(*scene, *split);
  for (const char* expected : {"292 images", "390x260", "12 train", "37 test", "points: none"})
    EXPECT_NE(text.find(expected), std::string::npos) << expected << " missing from:\n" << text;
}

TEST(RealSceneTest, BonsaiAtResolution4RoundsHalfToEven) {
  const fs::path root = data_scene("mipnerf360/bonsai");
  SKIP_WITHOUT(root);
  absl::StatusOr<Scene> scene = load_scene(root, SceneLoadOptions{4, ""});
  ASSERT_TRUE(scene.ok()) << scene.status();
  // 3118 / 4 = 779.5 -> 780 and 2078 / 4 = 519.5 -> 520 (Python's round, as the reference code uses).
  EXPECT_EQ(scene->cameras[0].width, 780);
  EXPECT_EQ(scene->cameras[0].height, 520);
}

// --- Synthetic LLFF scenes: every failure names the file at fault ---------------------------------------

class SyntheticSceneTest : public ::testing::Test {
 protected:
  static constexpr int kWidth = 16, kHeight = 12;
  static constexpr double kFocal = 20.0;

  void SetUp() override {
    root_ = fs::path(::testing::TempDir()) /
            ("gaps_scene_" + std::string(::testing::UnitTest::GetInstance()->current_test_info()->name()));
    test::remove_tree(root_);
    fs::create_directories(root_);
  }
  void TearDown() override { test::remove_tree(root_); }

  // Camera i sits on a circle of radius 4 in the z = 1 plane, looking at the origin.
  static Eigen::Matrix<double, 3, 4> camera_to_world(int i, int n) {
    const double a = 2 * kPi * i / n;
    const Eigen::Vector3d centre(4 * std::cos(a), 4 * std::sin(a), 1.0);
    const Eigen::Vector3d forward = -centre.normalized();
    const Eigen::Vector3d right = forward.cross(Eigen::Vector3d::UnitZ()).normalized();
    Eigen::Matrix<double, 3, 4> c2w;
    c2w << right, forward.cross(right), forward, centre;
    return c2w;
  }

  void write_images(const std::string& folder, int n, int width, int height) {
    fs::create_directories(root_ / folder);
    for (int i = 0; i < n; ++i) {
      const at::Tensor image = at::full({height, width, 3}, 0.1f * (i + 1));
      ASSERT_TRUE(write_png(root_ / folder / ("img" + std::to_string(i) + ".png"), image).ok());
    }
  }

  // LLFF rows: [down | right | backwards | centre | (H, W, f)] row-major, then near, far.
  void write_poses(int n, double bad_value_at_row = -1) {
    at::Tensor rows = at::zeros({n, 17}, at::kDouble);
    auto r = rows.accessor<double, 2>();
    for (int i = 0; i < n; ++i) {
      const Eigen::Matrix<double, 3, 4> c2w = camera_to_world(i, n);
      const Eigen::Vector3d columns[4] = {c2w.col(1), c2w.col(0), -c2w.col(2), c2w.col(3)};
      const double hwf[3] = {kHeight, kWidth, kFocal};
      for (int row = 0; row < 3; ++row) {
        for (int col = 0; col < 4; ++col) r[i][row * 5 + col] = columns[col][row];
        r[i][row * 5 + 4] = hwf[row];
      }
      r[i][15] = 1.5;
      r[i][16] = 9.0;
    }
    if (bad_value_at_row >= 0) r[static_cast<int>(bad_value_at_row)][8] = NAN;
    ASSERT_TRUE(write_npy(root_ / "poses_bounds.npy", rows).ok());
  }

  fs::path root_;
};

TEST_F(SyntheticSceneTest, LoadsPosesExactly) {
  write_images("images", 5, kWidth, kHeight);
  write_poses(5);
  absl::StatusOr<Scene> scene = load_scene(root_);
  ASSERT_TRUE(scene.ok()) << scene.status();
  ASSERT_EQ(scene->cameras.size(), 5u);
  for (int i = 0; i < 5; ++i) {
    const Camera& c = scene->cameras[i];
    const Eigen::Matrix<double, 3, 4> c2w = camera_to_world(i, 5);
    EXPECT_TRUE(c.center().isApprox(c2w.col(3), 1e-12)) << i;
    EXPECT_TRUE(c.forward().isApprox(c2w.col(2), 1e-12)) << i;
    EXPECT_TRUE(c.R.row(0).transpose().isApprox(c2w.col(0), 1e-12)) << "x must be the camera's right";
    EXPECT_EQ(c.fx, kFocal);
    EXPECT_EQ(c.near, 1.5);
    EXPECT_EQ(c.far, 9.0);
  }
  expect_cameras_look_at_common_point(scene->cameras, 1e-6);
  EXPECT_TRUE(look_at_point(scene->cameras).isZero(1e-9));
}

TEST_F(SyntheticSceneTest, ResizesWhenTheScaledFolderIsMissing) {
  write_images("images", 3, kWidth, kHeight);
  write_poses(3);
  absl::StatusOr<Scene> scene = load_scene(root_, SceneLoadOptions{4, ""});
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->cameras[0].width, 4);
  EXPECT_EQ(scene->cameras[0].height, 3);
  EXPECT_EQ(scene->cameras[0].fx, kFocal / 4);
  absl::StatusOr<at::Tensor> image = load_camera_image(scene->cameras[2]);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_EQ(image->sizes().vec(), (std::vector<int64_t>{3, 4, 3}));
  EXPECT_NEAR(image->mean().item<float>(), 0.3f, 1.0f / 255);
}

TEST_F(SyntheticSceneTest, MissingPosesFile) {
  write_images("images", 3, kWidth, kHeight);
  absl::StatusOr<Scene> scene = load_llff_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), (root_ / "poses_bounds.npy").string())) << scene.status();
  scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), root_.string())) << scene.status();
  EXPECT_TRUE(contains(scene.status(), "poses_bounds.npy")) << scene.status();
}

TEST_F(SyntheticSceneTest, RowCountMismatch) {
  write_images("images", 3, kWidth, kHeight);
  write_poses(2);
  absl::StatusOr<Scene> scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), (root_ / "poses_bounds.npy").string())) << scene.status();
  EXPECT_TRUE(contains(scene.status(), "2 poses")) << scene.status();
  EXPECT_TRUE(contains(scene.status(), "3 images")) << scene.status();
}

TEST_F(SyntheticSceneTest, NonFinitePose) {
  write_images("images", 3, kWidth, kHeight);
  write_poses(3, /*bad_value_at_row=*/1);
  absl::StatusOr<Scene> scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), (root_ / "poses_bounds.npy").string() + ": row 1")) << scene.status();
  EXPECT_TRUE(contains(scene.status(), "non-finite")) << scene.status();
}

TEST_F(SyntheticSceneTest, WrongPosesShape) {
  write_images("images", 3, kWidth, kHeight);
  ASSERT_TRUE(write_npy(root_ / "poses_bounds.npy", at::zeros({3, 15}, at::kDouble)).ok());
  absl::StatusOr<Scene> scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), (root_ / "poses_bounds.npy").string())) << scene.status();
  EXPECT_TRUE(contains(scene.status(), "(3, 15)")) << scene.status();
}

TEST_F(SyntheticSceneTest, CorruptImageFile) {
  write_images("images", 3, kWidth, kHeight);
  write_poses(3);
  const fs::path bad = root_ / "images" / "img1.png";
  std::ofstream(bad, std::ios::binary | std::ios::trunc) << "not a png";
  absl::StatusOr<Scene> scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), bad.string())) << scene.status();
}

TEST_F(SyntheticSceneTest, TruncatedImageFailsOnLoad) {
  write_images("images", 3, kWidth, kHeight);
  write_poses(3);
  const fs::path bad = root_ / "images" / "img2.png";
  std::ifstream in(bad, std::ios::binary);
  const std::string bytes{std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
  in.close();
  std::ofstream(bad, std::ios::binary | std::ios::trunc) << bytes.substr(0, 40);  // header survives
  absl::StatusOr<Scene> scene = load_scene(root_);
  ASSERT_TRUE(scene.ok()) << scene.status();
  absl::StatusOr<at::Tensor> image = load_camera_image(scene->cameras[2]);
  ASSERT_FALSE(image.ok());
  EXPECT_TRUE(contains(image.status(), bad.string())) << image.status();
}

TEST_F(SyntheticSceneTest, MissingImageFolder) {
  write_poses(3);
  absl::StatusOr<Scene> scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), root_.string())) << scene.status();
  EXPECT_TRUE(contains(scene.status(), "image folder")) << scene.status();

  write_images("images", 3, kWidth, kHeight);
  scene = load_scene(root_, SceneLoadOptions{1, "images_missing"});
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), (root_ / "images_missing").string())) << scene.status();
}

TEST_F(SyntheticSceneTest, ImagesWithTheWrongAspectRatio) {
  write_images("images", 3, kHeight, kWidth);  // portrait files for a landscape camera
  write_poses(3);
  absl::StatusOr<Scene> scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), (root_ / "images" / "img0.png").string())) << scene.status();
}

TEST_F(SyntheticSceneTest, NoSceneAndBadOptions) {
  absl::StatusOr<Scene> scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), root_.string())) << scene.status();
  scene = load_scene(root_ / "does_not_exist");
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(absl::IsNotFound(scene.status()));
  write_images("images", 3, kWidth, kHeight);
  write_poses(3);
  EXPECT_FALSE(load_scene(root_, SceneLoadOptions{0, ""}).ok());
}

// --- transforms.json -------------------------------------------------------------------------------------

TEST_F(SyntheticSceneTest, NerfstudioTransforms) {
  write_images("images", 2, kWidth, kHeight);
  write_images("images_2", 2, kWidth / 2, kHeight / 2);
  // OpenGL camera-to-world: identity rotation at (0, 0, 5) looks down -z, towards the origin.
  nlohmann::json doc = {{"fl_x", 30.0}, {"fl_y", 31.0}, {"cx", 7.5}, {"cy", 6.5},
                        {"w", kWidth},  {"h", kHeight}, {"k1", 0.0}, {"camera_model", "OPENCV"}};
  const nlohmann::json identity_at_z5 = {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 5}, {0, 0, 0, 1}};
  const nlohmann::json rotated = {{0, 0, 1, 5}, {0, 1, 0, 0}, {-1, 0, 0, 0}, {0, 0, 0, 1}};  // at +x, facing -x
  doc["frames"] = {{{"file_path", "images/img1.png"}, {"transform_matrix", rotated}, {"fl_x", 40.0}},
                   {{"file_path", "images/img0.png"}, {"transform_matrix", identity_at_z5}}};
  std::ofstream(root_ / "transforms.json") << doc.dump(2);
  write_poses(2);  // transforms.json takes precedence

  absl::StatusOr<Scene> scene = load_scene(root_);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->format, "transforms");
  ASSERT_EQ(scene->cameras.size(), 2u);
  const Camera& c0 = scene->cameras[0];
  EXPECT_EQ(c0.name, "img0.png");
  EXPECT_TRUE(c0.center().isApprox(Eigen::Vector3d(0, 0, 5)));
  EXPECT_TRUE(c0.forward().isApprox(Eigen::Vector3d(0, 0, -1)));
  // OpenCV y points down the image, i.e. along the world's -y for an upright OpenGL camera.
  EXPECT_TRUE(c0.R.row(1).transpose().isApprox(Eigen::Vector3d(0, -1, 0)));
  EXPECT_EQ(c0.fx, 30.0);
  EXPECT_EQ(c0.fy, 31.0);
  EXPECT_EQ(c0.cx, 7.5);
  EXPECT_TRUE(c0.distortion.empty());
  EXPECT_EQ(scene->cameras[1].fx, 40.0) << "per-frame intrinsics override the global ones";
  EXPECT_TRUE(scene->cameras[1].forward().isApprox(Eigen::Vector3d(-1, 0, 0)));

  absl::StatusOr<Scene> half = load_scene(root_, SceneLoadOptions{2, ""});
  ASSERT_TRUE(half.ok()) << half.status();
  EXPECT_EQ(half->cameras[0].image_path, root_ / "images_2" / "img0.png");
  EXPECT_EQ(half->cameras[0].fx, 15.0);
  EXPECT_EQ(half->cameras[0].cy, 3.25);
}

TEST_F(SyntheticSceneTest, BlenderStyleTransforms) {
  write_images("train", 2, kWidth, kHeight);
  const double angle = 2 * std::atan(kWidth / 2.0 / kFocal);
  nlohmann::json doc = {{"camera_angle_x", angle}};
  const nlohmann::json pose = {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 4}, {0, 0, 0, 1}};
  doc["frames"] = {{{"file_path", "./train/img0"}, {"transform_matrix", pose}},
                   {{"file_path", "./train/img1"}, {"transform_matrix", pose}}};
  std::ofstream(root_ / "transforms.json") << doc.dump();
  absl::StatusOr<Scene> scene = load_transforms_scene(root_ / "transforms.json");
  ASSERT_TRUE(scene.ok()) << scene.status();
  ASSERT_EQ(scene->cameras.size(), 2u);
  EXPECT_EQ(scene->cameras[1].image_path, root_ / "train" / "img1.png");
  EXPECT_EQ(scene->cameras[0].width, kWidth);
  EXPECT_NEAR(scene->cameras[0].fx, kFocal, 1e-9);
  EXPECT_NEAR(scene->cameras[0].fy, kFocal, 1e-9);
  EXPECT_EQ(scene->cameras[0].cy, kHeight / 2.0);
}

TEST_F(SyntheticSceneTest, TransformsErrorsNameTheFile) {
  const fs::path json_path = root_ / "transforms.json";
  std::ofstream(json_path) << "{ not json";
  absl::StatusOr<Scene> scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), json_path.string())) << scene.status();

  write_images("images", 1, kWidth, kHeight);
  const nlohmann::json pose = {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 4}, {0, 0, 0, 1}};
  nlohmann::json doc = {{"fl_x", 20.0}};
  doc["frames"] = {{{"file_path", "images/absent.png"}, {"transform_matrix", pose}}};
  std::ofstream(json_path, std::ios::trunc) << doc.dump();
  scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), (root_ / "images" / "absent.png").string())) << scene.status();

  doc["frames"] = {{{"file_path", "images/img0.png"}}};
  std::ofstream(json_path, std::ios::trunc) << doc.dump();
  scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), json_path.string())) << scene.status();
  EXPECT_TRUE(contains(scene.status(), "transform_matrix")) << scene.status();

  doc = {{"frames", {{{"file_path", "images/img0.png"}, {"transform_matrix", pose}}}}};
  std::ofstream(json_path, std::ios::trunc) << doc.dump();
  scene = load_scene(root_);
  ASSERT_FALSE(scene.ok());
  EXPECT_TRUE(contains(scene.status(), "focal")) << scene.status();

  // An image path leading out of the scene folder is refused (gaps submit would upload that file).
  for (const std::string outside : {std::string("../outside.png"), std::string("images/../../outside.png"),
                                    (root_.parent_path() / "outside.png").string()}) {
    doc = {{"fl_x", 20.0}, {"frames", {{{"file_path", outside}, {"transform_matrix", pose}}}}};
    std::ofstream(json_path, std::ios::trunc) << doc.dump();
    scene = load_scene(root_);
    ASSERT_FALSE(scene.ok()) << outside;
    EXPECT_EQ(scene.status().code(), absl::StatusCode::kInvalidArgument) << scene.status();
    EXPECT_TRUE(contains(scene.status(), "leads outside the scene folder")) << scene.status();
  }
}

// cameras.json: what we write reads back as the same cameras; an entry of the reference code (no cx, cy,
// no split) reads with the principal point at the image centre.
TEST(CamerasJson, RoundTripKeepsPosesIntrinsicsAndSplits) {
  Camera a;
  a.name = "IMG_0001.JPG";
  a.width = 504;
  a.height = 378;
  a.fx = 407.5;
  a.fy = 408.25;
  a.cx = 250.5;
  a.cy = 190.0;
  a.R = Eigen::AngleAxisd(0.7, Eigen::Vector3d(0.2, 1.0, -0.4).normalized()).toRotationMatrix();
  a.t = Eigen::Vector3d(0.3, -1.2, 4.0);
  Camera b = a;
  b.name = "IMG_0009.JPG";
  b.t.x() += 1.0;
  const auto path = fs::path(::testing::TempDir()) / "cameras_round_trip.json";
  ASSERT_TRUE(write_cameras_json(path, {{a, "train"}, {b, "test"}}).ok());
  const auto read = read_cameras_json(path);
  ASSERT_TRUE(read.ok()) << read.status();
  ASSERT_EQ(read->size(), 2u);
  const std::vector<Camera> written = {a, b};
  for (size_t i = 0; i < 2; ++i) {
    const Camera& c = (*read)[i].camera;
    EXPECT_EQ(c.name, written[i].name);
    EXPECT_EQ(c.width, 504);
    EXPECT_EQ(c.height, 378);
    EXPECT_DOUBLE_EQ(c.fx, a.fx);
    EXPECT_DOUBLE_EQ(c.fy, a.fy);
    EXPECT_DOUBLE_EQ(c.cx, a.cx);
    EXPECT_DOUBLE_EQ(c.cy, a.cy);
    EXPECT_LT((c.R - written[i].R).norm(), 1e-12);
    EXPECT_LT((c.t - written[i].t).norm(), 1e-12);
  }
  EXPECT_EQ((*read)[0].split, "train");
  EXPECT_EQ((*read)[1].split, "test");
  // Inria's layout: position is the camera centre, rotation the camera-to-world rotation.
  const auto entry = camera_json(a, 0);
  EXPECT_EQ(entry["img_name"], "IMG_0001");
  EXPECT_NEAR(entry["position"][0].get<double>(), a.center().x(), 1e-12);
  EXPECT_NEAR(entry["rotation"][0][2].get<double>(), a.R(2, 0), 1e-12);
  EXPECT_FALSE(entry.contains("split"));
}

TEST(CamerasJson, ReferenceEntriesUseTheImageCentre) {
  const auto entry = nlohmann::json::parse(R"({"id": 0, "img_name": "00000", "width": 800, "height": 600,
      "position": [0, 0, -4], "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "fx": 1111.0, "fy": 1111.0})");
  const auto record = parse_camera_json(entry, "cameras.json: camera 0");
  ASSERT_TRUE(record.ok()) << record.status();
  EXPECT_DOUBLE_EQ(record->camera.cx, 400.0);
  EXPECT_DOUBLE_EQ(record->camera.cy, 300.0);
  EXPECT_EQ(record->camera.name, "00000");
  EXPECT_LT((record->camera.t - Eigen::Vector3d(0, 0, 4)).norm(), 1e-12);
  EXPECT_TRUE(record->split.empty());
}

TEST(CamerasJson, BadEntriesAreNamed) {
  const auto base = nlohmann::json::parse(R"({"width": 8, "height": 6, "position": [0, 0, 0],
      "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "fx": 10, "fy": 10})");
  auto no_fx = base;
  no_fx.erase("fx");
  EXPECT_TRUE(contains(parse_camera_json(no_fx, "f: camera 3").status(), "f: camera 3: 'fx'"));
  auto scaled = base;
  scaled["rotation"][0][0] = 2.0;
  EXPECT_FALSE(parse_camera_json(scaled, "f: camera 0").ok()) << "a rotation that is not a rotation";
  auto short_position = base;
  short_position["position"] = {0, 0};
  EXPECT_TRUE(contains(parse_camera_json(short_position, "f").status(), "'position' must be a list of 3 numbers"));
  auto fractional = base;
  fractional["width"] = 8.5;
  EXPECT_TRUE(contains(parse_camera_json(fractional, "f").status(), "whole numbers"));
  EXPECT_TRUE(contains(parse_cameras_json(nlohmann::json::array(), "f").status(), "no cameras"));
  EXPECT_TRUE(contains(parse_cameras_json(base, "f").status(), "expected a list"));
  const auto garbage = fs::path(::testing::TempDir()) / "cameras_garbage.json";
  std::ofstream(garbage) << "[{";
  EXPECT_TRUE(contains(read_cameras_json(garbage).status(), "not valid JSON"));
  EXPECT_EQ(read_cameras_json(fs::path(::testing::TempDir()) / "missing.json").status().code(),
            absl::StatusCode::kNotFound);
}

}  // namespace
}  // namespace gaps

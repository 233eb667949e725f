#include "gs_trainer/scene/colmap.h"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <Eigen/Geometry>

#include "tests/test_util.h"

#include "common/image_io.h"
#include "gs_trainer/scene/scene.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

// Little-endian record builder for hand-written COLMAP .bin files (independent of the reader).
struct Bytes {
  std::string s;
  template <typename T>
  Bytes& put(T v) {
    s.append(reinterpret_cast<const char*>(&v), sizeof(T));
    return *this;
  }
  Bytes& str(const std::string& text) {
    s += text;
    s += '\0';
    return *this;
  }
};

const Eigen::Vector4d kQuat = Eigen::Vector4d(0.9, 0.1, -0.2, 0.3).normalized();

std::string cameras_bin() {
  Bytes b;
  b.put<uint64_t>(2);
  b.put<int32_t>(1).put<int32_t>(1).put<uint64_t>(64).put<uint64_t>(48);  // PINHOLE
  for (double p : {50.0, 51.0, 32.0, 24.0}) b.put(p);
  b.put<int32_t>(2).put<int32_t>(4).put<uint64_t>(64).put<uint64_t>(48);  // OPENCV
  for (double p : {60.0, 61.0, 31.5, 24.5, -0.1, 0.01, 0.001, -0.002}) b.put(p);
  return b.s;
}

std::string images_bin() {
  Bytes b;
  b.put<uint64_t>(2);
  b.put<int32_t>(5);
  for (int i = 0; i < 4; ++i) b.put(kQuat[i]);
  for (double t : {1.0, 2.0, 3.0}) b.put(t);
  b.put<int32_t>(1).str("b.png").put<uint64_t>(2);
  b.put(10.5).put(20.25).put<int64_t>(7);
  b.put(30.0).put(40.0).put<int64_t>(-1);
  b.put<int32_t>(3);
  for (double v : {1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0}) b.put(v);
  b.put<int32_t>(2).str("a.png").put<uint64_t>(0);
  return b.s;
}

std::string points_bin() {
  Bytes b;
  b.put<uint64_t>(2);
  b.put<uint64_t>(7).put(0.1).put(0.2).put(0.3).put<uint8_t>(255).put<uint8_t>(128).put<uint8_t>(0).put(0.5);
  b.put<uint64_t>(1).put<int32_t>(5).put<int32_t>(0);
  b.put<uint64_t>(9).put(1e-20).put(-3.0).put(1e10).put<uint8_t>(1).put<uint8_t>(2).put<uint8_t>(3).put(0.0);
  b.put<uint64_t>(0);
  return b.s;
}

void expect_models_equal(const ColmapModel& a, const ColmapModel& b) {
  ASSERT_EQ(a.cameras.size(), b.cameras.size());
  for (const auto& [id, cam] : a.cameras) {
    const ColmapCamera& other = b.cameras.at(id);
    EXPECT_EQ(cam.model, other.model);
    EXPECT_EQ(cam.width, other.width);
    EXPECT_EQ(cam.height, other.height);
    EXPECT_EQ(cam.params, other.params);
  }
  ASSERT_EQ(a.images.size(), b.images.size());
  for (const auto& [id, image] : a.images) {
    const ColmapImage& other = b.images.at(id);
    EXPECT_EQ(image.qvec, other.qvec);
    EXPECT_EQ(image.tvec, other.tvec);
    EXPECT_EQ(image.camera_id, other.camera_id);
    EXPECT_EQ(image.name, other.name);
    EXPECT_EQ(image.xys, other.xys);
    EXPECT_EQ(image.point3d_ids, other.point3d_ids);
  }
  ASSERT_EQ(a.points.size(), b.points.size());
  for (size_t i = 0; i < a.points.size(); ++i) {
    EXPECT_EQ(a.points[i].id, b.points[i].id);
    EXPECT_EQ(a.points[i].xyz, b.points[i].xyz);
    EXPECT_EQ(a.points[i].rgb, b.points[i].rgb);
    EXPECT_EQ(a.points[i].error, b.points[i].error);
    ASSERT_EQ(a.points[i].track.size(), b.points[i].track.size());
    for (size_t k = 0; k < a.points[i].track.size(); ++k) {
      EXPECT_EQ(a.points[i].track[k].image_id, b.points[i].track[k].image_id);
      EXPECT_EQ(a.points[i].track[k].point2d_idx, b.points[i].track[k].point2d_idx);
    }
  }
}

class ColmapTest : public test::TempDirTest {
 protected:
  fs::path write_bin_model(const fs::path& relative) {
    write(relative / "cameras.bin", cameras_bin());
    write(relative / "images.bin", images_bin());
    write(relative / "points3D.bin", points_bin());
    return dir_ / relative;
  }

  // A scene whose images are smooth gradients, so resizing and undistortion are measurable.
  void write_images(const fs::path& folder, const std::vector<std::string>& names, int width, int height) {
    fs::create_directories(dir_ / folder);
    const at::Tensor x = at::linspace(0, 1, width).view({1, width, 1});
    const at::Tensor y = at::linspace(0, 1, height).view({height, 1, 1});
    const at::Tensor image =
        at::cat({x.expand({height, width, 1}), y.expand({height, width, 1}), (x * y).expand({height, width, 1})}, 2);
    for (const std::string& name : names) ASSERT_TRUE(write_png(dir_ / folder / name, image).ok());
  }
};

TEST_F(ColmapTest, ReadsHandWrittenBinaryModel) {
  absl::StatusOr<ColmapModel> model = read_colmap_model(write_bin_model("sparse/0"));
  ASSERT_TRUE(model.ok()) << model.status();
  ASSERT_EQ(model->cameras.size(), 2u);
  EXPECT_EQ(model->cameras.at(1).model, "PINHOLE");
  EXPECT_EQ(model->cameras.at(2).model, "OPENCV");
  EXPECT_EQ(model->cameras.at(2).width, 64);
  EXPECT_EQ(model->cameras.at(2).params.back(), -0.002);
  ASSERT_EQ(model->images.size(), 2u);
  const ColmapImage& b = model->images.at(5);
  EXPECT_EQ(b.name, "b.png");
  EXPECT_EQ(b.qvec, kQuat);
  EXPECT_EQ(b.tvec, Eigen::Vector3d(1, 2, 3));
  ASSERT_EQ(b.xys.size(), 2u);
  EXPECT_EQ(b.xys[0], Eigen::Vector2d(10.5, 20.25));
  EXPECT_EQ(b.point3d_ids, (std::vector<int64_t>{7, -1}));
  EXPECT_TRUE(model->images.at(3).xys.empty());
  ASSERT_EQ(model->points.size(), 2u);
  EXPECT_EQ(model->points[0].id, 7);
  EXPECT_EQ(model->points[0].rgb, (std::array<uint8_t, 3>{255, 128, 0}));
  ASSERT_EQ(model->points[0].track.size(), 1u);
  EXPECT_EQ(model->points[0].track[0].image_id, 5);
  EXPECT_EQ(model->points[1].xyz.z(), 1e10);
}

TEST_F(ColmapTest, BinaryToTextRoundTripIsExact) {
  absl::StatusOr<ColmapModel> bin = read_colmap_model(write_bin_model("bin"));
  ASSERT_TRUE(bin.ok()) << bin.status();
  ASSERT_TRUE(write_colmap_text(dir_ / "txt" / "nested", *bin).ok());
  EXPECT_TRUE(fs::exists(dir_ / "txt" / "nested" / "points3D.txt"));
  absl::StatusOr<ColmapModel> txt = read_colmap_model(dir_ / "txt" / "nested");
  ASSERT_TRUE(txt.ok()) << txt.status();
  expect_models_equal(*bin, *txt);
  // Writing the text model again gives the same model once more (no drift through the text format).
  ASSERT_TRUE(write_colmap_text(dir_ / "txt2", *txt).ok());
  absl::StatusOr<ColmapModel> again = read_colmap_model(dir_ / "txt2");
  ASSERT_TRUE(again.ok()) << again.status();
  expect_models_equal(*bin, *again);
}

TEST_F(ColmapTest, ParsesTextWithCommentsAndEmptyPointLines) {
  write("m/cameras.txt", "# comment\n\n1 SIMPLE_RADIAL 100 80 90 50 40 0.05\r\n");
  write("m/images.txt",
        "# Image list\n"
        "1 1 0 0 0 0.5 0 0 1 first.jpg\n"
        "\n"  // the first image has no 2D points
        "2 0.7071067811865476 0 0.7071067811865476 0 1 2 3 1 second.jpg\n"
        "1.5 2.5 -1 3 4 12\n");
  write("m/points3D.txt", "12 1 2 3 10 20 30 0.25 2 1\n");
  absl::StatusOr<ColmapModel> model = read_colmap_model(dir_ / "m");
  ASSERT_TRUE(model.ok()) << model.status();
  ASSERT_EQ(model->images.size(), 2u);
  EXPECT_TRUE(model->images.at(1).xys.empty());
  EXPECT_EQ(model->images.at(2).name, "second.jpg");
  EXPECT_EQ(model->images.at(2).point3d_ids, (std::vector<int64_t>{-1, 12}));
  EXPECT_EQ(model->cameras.at(1).params, (std::vector<double>{90, 50, 40, 0.05}));
  ASSERT_EQ(model->points.size(), 1u);
  EXPECT_EQ(model->points[0].track[0].image_id, 2);
}

TEST_F(ColmapTest, ErrorsNameTheFile) {
  const fs::path truncated = write("t/cameras.bin", cameras_bin().substr(0, 50));
  absl::StatusOr<std::map<int, ColmapCamera>> cams = read_colmap_cameras_bin(truncated);
  ASSERT_FALSE(cams.ok());
  EXPECT_NE(cams.status().message().find(truncated.string()), absl::string_view::npos) << cams.status();

  std::string bad_model = cameras_bin();
  bad_model[12] = 99;  // the first camera's model id
  const fs::path unknown = write("u/cameras.bin", bad_model);
  cams = read_colmap_cameras_bin(unknown);
  ASSERT_FALSE(cams.ok());
  EXPECT_NE(cams.status().message().find("model id 99"), absl::string_view::npos) << cams.status();

  const fs::path trailing = write("x/images.bin", images_bin() + "junk");
  EXPECT_NE(read_colmap_images_bin(trailing).status().message().find(trailing.string()), absl::string_view::npos);

  const fs::path txt = write("v/cameras.txt", "# header\n1 PINHOLE 10 10 5 5 5\n");
  cams = read_colmap_cameras_txt(txt);
  ASSERT_FALSE(cams.ok());
  EXPECT_NE(cams.status().message().find(txt.string() + ":2"), absl::string_view::npos) << cams.status();

  const fs::path images = write("v/images.txt", "1 1 0 0 zero 0 0 0 1 a.png\n\n");
  EXPECT_NE(read_colmap_images_txt(images).status().message().find(images.string() + ":1"), absl::string_view::npos);

  const fs::path missing = dir_ / "none" / "points3D.bin";
  EXPECT_TRUE(absl::IsNotFound(read_colmap_points_bin(missing).status()));
}

TEST_F(ColmapTest, ConvertsEveryPinholeLikeModel) {
  ColmapImage image;
  image.name = "x.png";
  struct Case {
    std::string model;
    std::vector<double> params;
    double fx, fy, cx, cy;
    std::vector<double> distortion;
  };
  const std::vector<Case> cases = {
      {"SIMPLE_PINHOLE", {100, 50, 40}, 100, 100, 50, 40, {}},
      {"PINHOLE", {100, 110, 50, 40}, 100, 110, 50, 40, {}},
      {"SIMPLE_RADIAL", {100, 50, 40, 0.1}, 100, 100, 50, 40, {0.1, 0, 0, 0}},
      {"RADIAL", {100, 50, 40, 0.1, -0.2}, 100, 100, 50, 40, {0.1, -0.2, 0, 0}},
      {"OPENCV", {100, 110, 50, 40, 0.1, -0.2, 0.01, 0.02}, 100, 110, 50, 40, {0.1, -0.2, 0.01, 0.02}},
      {"OPENCV", {100, 110, 50, 40, 0, 0, 0, 0}, 100, 110, 50, 40, {}},
      {"FULL_OPENCV", {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12}, 1, 2, 3, 4, {5, 6, 7, 8, 9, 10, 11, 12}},
  };
  for (const Case& c : cases) {
    absl::StatusOr<Camera> camera = colmap_to_camera(ColmapCamera{1, c.model, 100, 80, c.params}, image);
    ASSERT_TRUE(camera.ok()) << c.model << ": " << camera.status();
    EXPECT_EQ(camera->width, 100);
    EXPECT_EQ(camera->height, 80);
    EXPECT_EQ(camera->fx, c.fx) << c.model;
    EXPECT_EQ(camera->fy, c.fy) << c.model;
    EXPECT_EQ(camera->cx, c.cx) << c.model;
    EXPECT_EQ(camera->cy, c.cy) << c.model;
    EXPECT_EQ(camera->distortion, c.distortion) << c.model;
  }
  absl::StatusOr<Camera> fisheye =
      colmap_to_camera(ColmapCamera{3, "OPENCV_FISHEYE", 100, 80, {1, 1, 1, 1, 0, 0, 0, 0}}, image);
  ASSERT_FALSE(fisheye.ok());
  EXPECT_NE(fisheye.status().message().find("OPENCV_FISHEYE"), absl::string_view::npos);
  EXPECT_FALSE(colmap_to_camera(ColmapCamera{4, "PINHOLE", 100, 80, {1, 2}}, image).ok());
}

TEST_F(ColmapTest, QuaternionsAreWorldToCameraWFirst) {
  // 90 degrees about z: (cos 45, 0, 0, sin 45) maps the world x axis onto the camera y axis.
  const Eigen::Matrix3d R = quaternion_to_rotation(Eigen::Vector4d(std::sqrt(0.5), 0, 0, std::sqrt(0.5)));
  EXPECT_TRUE((R * Eigen::Vector3d::UnitX()).isApprox(Eigen::Vector3d::UnitY(), 1e-12));
  const Eigen::Matrix3d random = Eigen::Quaterniond::UnitRandom().toRotationMatrix();
  const Eigen::Vector4d q = rotation_to_quaternion(random);
  EXPECT_GE(q[0], 0.0);
  EXPECT_TRUE(quaternion_to_rotation(q).isApprox(random, 1e-12));
  // COLMAP's pose is used as is: it already maps world to camera in the OpenCV convention.
  ColmapImage image;
  image.qvec = kQuat;
  image.tvec = Eigen::Vector3d(1, 2, 3);
  absl::StatusOr<Camera> camera = colmap_to_camera(ColmapCamera{1, "PINHOLE", 10, 10, {5, 5, 5, 5}}, image);
  ASSERT_TRUE(camera.ok());
  EXPECT_TRUE(camera->R.isApprox(Eigen::Quaterniond(kQuat[0], kQuat[1], kQuat[2], kQuat[3]).toRotationMatrix(), 1e-12));
  EXPECT_EQ(camera->t, image.tvec);
}

TEST_F(ColmapTest, FindsModelFolders) {
  EXPECT_FALSE(find_colmap_model(dir_).has_value());
  write("sparse/cameras.txt", "");
  EXPECT_FALSE(find_colmap_model(dir_).has_value()) << "cameras alone are not a model";
  write("sparse/images.txt", "");
  EXPECT_EQ(find_colmap_model(dir_), dir_ / "sparse");
  write_bin_model("sparse/0");
  EXPECT_EQ(find_colmap_model(dir_), dir_ / "sparse" / "0");
}

TEST_F(ColmapTest, CamerasToModelAndBack) {
  Camera a;
  a.name = "a.png";
  a.width = 40;
  a.height = 30;
  a.fx = 35, a.fy = 36, a.cx = 20, a.cy = 15;
  a.R = Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  a.t = Eigen::Vector3d(0.5, -1, 2);
  Camera b = a;
  b.name = "b.png";
  b.distortion = {0.1, 0.01, 0, 0, 0.001};
  PointCloud points{at::tensor({1.0f, 2.0f, 3.0f}).view({1, 3}), at::tensor({1.0f, 0.5f, 0.0f}).view({1, 3})};
  const ColmapModel model = colmap_from_cameras({a, b}, points);
  EXPECT_EQ(model.cameras.at(1).model, "PINHOLE");
  EXPECT_EQ(model.cameras.at(2).model, "FULL_OPENCV");
  ASSERT_TRUE(write_colmap_text(dir_ / "out", model).ok());
  absl::StatusOr<ColmapModel> back = read_colmap_model(dir_ / "out");
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->points.size(), 1u);
  EXPECT_EQ(back->points[0].rgb, (std::array<uint8_t, 3>{255, 128, 0}));
  absl::StatusOr<Camera> b2 = colmap_to_camera(back->cameras.at(2), back->images.at(2));
  ASSERT_TRUE(b2.ok()) << b2.status();
  EXPECT_EQ(b2->name, "b.png");
  EXPECT_TRUE(b2->R.isApprox(b.R, 1e-12));
  EXPECT_TRUE(b2->t.isApprox(b.t, 1e-12));
  EXPECT_EQ(b2->fy, 36);
  EXPECT_EQ(b2->distortion, (std::vector<double>{0.1, 0.01, 0, 0, 0.001, 0, 0, 0}));
}

TEST_F(ColmapTest, LoadsColmapSceneWithPointsAndDistortion) {
  write_bin_model("sparse/0");
  write_images("images", {"a.png", "b.png"}, 64, 48);
  write("poses_bounds.npy", "a full COLMAP model wins over LLFF poses");
  absl::StatusOr<Scene> scene = load_scene(dir_);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->format, "colmap");
  ASSERT_EQ(scene->cameras.size(), 2u);
  EXPECT_EQ(scene->cameras[0].name, "a.png");  // sorted by name, not by image id
  EXPECT_EQ(scene->cameras[0].fx, 60);
  EXPECT_EQ(scene->cameras[0].distortion.size(), 4u);
  EXPECT_EQ(scene->cameras[1].image_path, dir_ / "images" / "b.png");
  ASSERT_TRUE(scene->points.has_value());
  EXPECT_EQ(scene->points->xyz.size(0), 2);
  EXPECT_FLOAT_EQ(scene->points->rgb[0][1].item<float>(), 128 / 255.0f);

  absl::StatusOr<at::Tensor> raw = read_image(dir_ / "images" / "a.png");
  absl::StatusOr<at::Tensor> undistorted = load_camera_image(scene->cameras[0]);
  ASSERT_TRUE(undistorted.ok()) << undistorted.status();
  EXPECT_EQ(undistorted->sizes().vec(), (std::vector<int64_t>{48, 64, 3}));
  EXPECT_GT((*undistorted - *raw).abs().max().item<float>(), 1e-3f) << "the distorted camera must be undistorted";
  absl::StatusOr<at::Tensor> plain = load_camera_image(scene->cameras[1]);
  ASSERT_TRUE(plain.ok());
  EXPECT_TRUE(at::equal(*plain, *read_image(dir_ / "images" / "b.png")));
}

TEST_F(ColmapTest, ResolutionUsesScaledFolderOrResizes) {
  write_bin_model("sparse/0");
  write_images("images", {"a.png", "b.png"}, 64, 48);
  absl::StatusOr<Scene> resized = load_scene(dir_, SceneLoadOptions{2, ""});
  ASSERT_TRUE(resized.ok()) << resized.status();
  EXPECT_EQ(resized->cameras[1].width, 32);
  EXPECT_EQ(resized->cameras[1].fx, 25);  // 50 at 64 px wide
  absl::StatusOr<at::Tensor> image = load_camera_image(resized->cameras[1]);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_EQ(image->sizes().vec(), (std::vector<int64_t>{24, 32, 3}));
  // LLFF-style downscaled folders rename the photos but keep their order.
  write_images("images_2", {"image000.png", "image001.png"}, 32, 24);
  absl::StatusOr<Scene> scaled = load_scene(dir_, SceneLoadOptions{2, ""});
  ASSERT_TRUE(scaled.ok()) << scaled.status();
  EXPECT_EQ(scaled->cameras[1].image_path, dir_ / "images_2" / "image001.png");
  EXPECT_EQ(scaled->cameras[1].cx, 16);
}

TEST_F(ColmapTest, MissingImageNamesTheFile) {
  write_bin_model("sparse/0");
  write_images("images", {"a.png"}, 64, 48);
  absl::StatusOr<Scene> scene = load_scene(dir_);
  ASSERT_FALSE(scene.ok());
  EXPECT_NE(scene.status().message().find((dir_ / "images" / "b.png").string()), absl::string_view::npos)
      << scene.status();
}

TEST_F(ColmapTest, ReadsBonsaiCamerasBin) {
  const fs::path root = fs::path(GAPS_DATA_DIR) / "mipnerf360" / "bonsai";
  if (!fs::exists(root)) GTEST_SKIP() << "no benchmark data at " << GAPS_DATA_DIR;
  // Bonsai ships cameras.bin only: no COLMAP scene, so its poses come from poses_bounds.npy.
  EXPECT_FALSE(find_colmap_model(root).has_value());
  absl::StatusOr<std::map<int, ColmapCamera>> cameras = read_colmap_cameras(root / "sparse" / "0");
  ASSERT_TRUE(cameras.ok()) << cameras.status();
  ASSERT_EQ(cameras->size(), 1u);
  const ColmapCamera& camera = cameras->begin()->second;
  EXPECT_EQ(camera.model, "PINHOLE");
  EXPECT_EQ(camera.width, 3118);
  EXPECT_EQ(camera.height, 2078);
  EXPECT_NEAR(camera.params[0], 3222.701, 1e-3);
  EXPECT_EQ(camera.params[2], 1559.0);
  EXPECT_EQ(camera.params[3], 1039.0);
}

}  // namespace
}  // namespace gaps

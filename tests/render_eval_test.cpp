// `gaps render`, `gaps eval` and `--init-ply` with a full model, through the built binary on one short fern run
// (3 views, -r 8, CPU) that every test shares: eval reproduces the run's metrics.json, the frames of a path lie
// on it (and make a video where ffmpeg is installed), the test path renders what the run rendered, and a run
// started from the saved PLY continues that model.
#include <cmath>
#include <fstream>
#include <regex>
#include <tuple>

#include <unistd.h>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "common/image_io.h"
#include "common/ply.h"
#include "gs_trainer/scene/bounds.h"
#include "gs_trainer/scene/camera_path.h"
#include "gs_trainer/scene/cameras_json.h"
#include "gs_trainer/scene/scene.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using test::contains;
using test::read_json;
using test::read_text;

namespace fs = std::filesystem;

const std::string kGaps = GAPS_CLI_BIN;
const fs::path kFern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
const std::string kFernRun = " --views 3 -r 8 --device cpu";

bool on_path(const std::string& program) { return test::run_command("command -v " + program).first == 0; }

// The frames' cameras as the command wrote them (cameras.json beside the frames).
std::vector<Camera> frame_cameras(const fs::path& out) {
  auto records = read_cameras_json(out / "cameras.json");
  EXPECT_TRUE(records.ok()) << records.status();
  std::vector<Camera> cameras;
  if (records.ok())
    for (const auto& r : *records) cameras.push_back(r.camera);
  return cameras;
}

// Fern's training cameras as the run split them.
std::vector<Camera> fern_training_cameras() {
  SceneLoadOptions load;
  load.resolution = 8;
  auto scene = load_scene(kFern, load);
  EXPECT_TRUE(scene.ok()) << scene.status();
  auto split = benchmark_split(static_cast<int>(scene->cameras.size()), 3);
  std::vector<Camera> train;
  for (int i : split->train) train.push_back(scene->cameras[i]);
  return train;
}

// One short run, trained once for the whole suite.
class RenderEval : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    if (!fs::exists(kFern)) return;
    // One folder per process: ctest runs each test of the suite as its own process, several at once.
    run_ = fs::path(::testing::TempDir()) / ("gaps_render_eval_run_" + std::to_string(::getpid()));
    test::remove_tree(run_);
    const auto [code, log] =
        test::run_command(kGaps + " train --scene " + kFern.string() + kFernRun +
                          " --quiet --iterations 15 --init random --random-points 2000 --eval-every 0 --report=false "
                          "--save-every 0 --out " +
                          run_.string());
    trained_ = code == 0;
    log_ = log;
  }
  static void TearDownTestSuite() {
    if (!run_.empty()) test::remove_tree(run_);
  }
  void SetUp() override {
    if (!fs::exists(kFern)) GTEST_SKIP() << "benchmark data not found at " << kFern;
    ASSERT_TRUE(trained_) << log_;
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    dir_ = fs::path(::testing::TempDir()) /
           ("gaps_RenderEval_" + std::string(info->name()) + "_" + std::to_string(::getpid()));
    test::remove_tree(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { test::remove_tree(dir_); }

  static fs::path run_;
  static bool trained_;
  static std::string log_;
  fs::path dir_;
};

fs::path RenderEval::run_;
bool RenderEval::trained_ = false;
std::string RenderEval::log_;

// LPIPS follows --lpips-weights: off on request, null and said so where the set-up's file is missing, an error
// naming a file that is there but is not LPIPS weights.
TEST_F(RenderEval, LpipsWeightsAreTheSetUpsUnlessTheFlagSaysOtherwise) {
  auto [code, out] =
      test::run_command(kGaps + " eval " + run_.string() + " --device cpu --lpips-weights=none --out " + dir_.string());
  ASSERT_EQ(code, 0) << out;
  EXPECT_TRUE(contains(out, "LPIPS off (--lpips-weights=none)")) << out;
  EXPECT_TRUE(read_json(dir_ / "eval.json")["lpips"].is_null());

  const fs::path empty_cache = dir_ / "empty_cache";
  std::tie(code, out) = test::run_command("GAPS_CACHE=" + empty_cache.string() + " " + kGaps + " eval " +
                                          run_.string() + " --device cpu --out " + dir_.string());
  ASSERT_EQ(code, 0) << out;
  EXPECT_TRUE(contains(out, "n/a (no LPIPS weights at " + (empty_cache / "lpips").string())) << out;
  EXPECT_TRUE(contains(out, "bash scripts/setup.sh makes them")) << out;

  const fs::path not_weights = dir_ / "not_weights.safetensors";
  std::ofstream(not_weights) << "not a safetensors file";
  std::tie(code, out) = test::run_command(kGaps + " eval " + run_.string() + " --device cpu --lpips-weights " +
                                          not_weights.string() + " --out " + dir_.string());
  EXPECT_NE(code, 0) << out;
  EXPECT_TRUE(contains(out, not_weights.string())) << out;
}

TEST_F(RenderEval, EvalReproducesTheRunsOwnMetricsAndLeavesThemAlone) {
  const std::string before = read_text(run_ / "metrics.json");
  const auto [code, out] = test::run_command(kGaps + " eval " + run_.string() + " --device cpu");
  ASSERT_EQ(code, 0) << out;
  EXPECT_TRUE(contains(out, "test PSNR")) << out;
  EXPECT_EQ(read_text(run_ / "metrics.json"), before);
  const nlohmann::json metrics = read_json(run_ / "metrics.json"), eval = read_json(run_ / "eval.json");
  ASSERT_EQ(eval["per_view"].size(), metrics["per_view"].size());
  ASSERT_EQ(eval["per_view"].size(), 3u);  // fern's 20 images: every 8th is a test view
  for (size_t i = 0; i < eval["per_view"].size(); ++i) {
    const auto &e = eval["per_view"][i], m = metrics["per_view"][i];
    EXPECT_EQ(e["image"], m["image"]);
    EXPECT_NEAR(e["psnr"].get<double>(), m["psnr"].get<double>(), 1e-4) << e["image"];
    EXPECT_NEAR(e["ssim"].get<double>(), m["ssim"].get<double>(), 1e-4) << e["image"];
    // Both with the set-up's LPIPS weights, which gaps train and gaps eval use by default.
    ASSERT_TRUE(m["lpips"].is_number() && e["lpips"].is_number()) << m << "\n" << e;
    EXPECT_NEAR(e["lpips"].get<double>(), m["lpips"].get<double>(), 1e-4) << e["image"];
  }
  ASSERT_TRUE(eval["lpips"].is_number()) << eval;
  EXPECT_NEAR(eval["lpips"].get<double>(), metrics["lpips"].get<double>(), 1e-4);
  EXPECT_TRUE(contains(out, "LPIPS 0.")) << out;
  EXPECT_NEAR(eval["psnr"].get<double>(), metrics["psnr"].get<double>(), 1e-4);
  EXPECT_NEAR(eval["ssim"].get<double>(), metrics["ssim"].get<double>(), 1e-4);
  EXPECT_EQ(eval["num_gaussians"], metrics["num_gaussians"]);

  // The same model given as a file, with its scene and split as flags; the metrics go to --out.
  const auto [code2, out2] = test::run_command(kGaps + " eval --model " + (run_ / "point_cloud.ply").string() +
                                               " --scene " + kFern.string() + kFernRun + " --out " + dir_.string());
  ASSERT_EQ(code2, 0) << out2;
  EXPECT_NEAR(read_json(dir_ / "eval.json")["psnr"].get<double>(), metrics["psnr"].get<double>(), 1e-4);
  EXPECT_NE(test::run_command(kGaps + " eval " + dir_.string()).first, 0);  // not a run folder
}

TEST_F(RenderEval, OrbitFramesCircleThePointTheyLookAtAndMakeAVideo) {
  const fs::path out = dir_ / "orbit";
  const auto [code, log] = test::run_command(kGaps + " render " + run_.string() +
                                             " --path orbit --frames 6 --device cpu --quiet --out " + out.string());
  ASSERT_EQ(code, 0) << log;
  for (int k = 0; k < 6; ++k) {
    char name[16];
    std::snprintf(name, sizeof name, "%05d.png", k);
    auto image = read_image(out / name);
    ASSERT_TRUE(image.ok()) << image.status();
    EXPECT_EQ(image->size(1), 504);  // fern at -r 8: the first training camera's size
    EXPECT_GT(image->std().item<float>(), 0.01f) << name;
  }
  EXPECT_FALSE(fs::exists(out / "00006.png"));
  const std::vector<Camera> frames = frame_cameras(out), train = fern_training_cameras();
  ASSERT_EQ(frames.size(), 6u);
  // The point the frames look at; their distance to it and height above it are the training cameras' means.
  const auto centre = optical_axes_target(frames);
  ASSERT_TRUE(centre.has_value());
  const Eigen::Vector3d up = mean_up(train);
  double distance = 0, height = 0;
  for (const Camera& c : train) {
    distance += (c.center() - *centre).norm() / train.size();
    height += (c.center() - *centre).dot(up) / train.size();
  }
  for (const Camera& c : frames) {
    EXPECT_NEAR((c.center() - *centre).norm(), distance, 1e-6 * distance);
    EXPECT_NEAR((c.center() - *centre).dot(up), height, 1e-6 * distance);
    EXPECT_GT(c.forward().dot((*centre - c.center()).normalized()), 1 - 1e-9);
    EXPECT_NEAR(c.fx, train[0].fx, 1e-9);
  }
  // A second render into the same folder needs --overwrite.
  EXPECT_EQ(
      test::run_command(kGaps + " render " + run_.string() + " --frames 2 --device cpu --out " + out.string()).first,
      2);
  if (!on_path("ffmpeg")) {
    EXPECT_TRUE(contains(log, "ffmpeg is not on PATH")) << log;
    GTEST_SKIP() << "ffmpeg is not installed: the video is not checked (frames only)";
  }
  ASSERT_TRUE(fs::exists(out / "orbit.mp4")) << log;
  if (!on_path("ffprobe")) GTEST_SKIP() << "ffprobe is not installed: the video's frames are not counted";
  const auto [probe_code, frames_text] = test::run_command(
      "ffprobe -v error -count_frames -select_streams v:0 -show_entries stream=nb_read_frames,codec_name,pix_fmt "
      "-of default=noprint_wrappers=1 " +
      (out / "orbit.mp4").string());
  ASSERT_EQ(probe_code, 0) << frames_text;
  EXPECT_TRUE(contains(frames_text, "nb_read_frames=6")) << frames_text;
  EXPECT_TRUE(contains(frames_text, "codec_name=h264")) << frames_text;
  EXPECT_TRUE(contains(frames_text, "pix_fmt=yuv420p")) << frames_text;
}

TEST_F(RenderEval, TheTestPathRendersWhatTheRunRenderedAndInterpPassesTheTrainingCameras) {
  const fs::path test_out = dir_ / "test";
  auto [code, log] = test::run_command(kGaps + " render " + run_.string() + " --path test --device cpu --quiet --out " +
                                       test_out.string());
  ASSERT_EQ(code, 0) << log;
  const nlohmann::json metrics = read_json(run_ / "metrics.json");
  ASSERT_EQ(frame_cameras(test_out).size(), metrics["per_view"].size());
  for (size_t k = 0; k < metrics["per_view"].size(); ++k) {
    char name[16];
    std::snprintf(name, sizeof name, "%05d.png", static_cast<int>(k));
    const std::string image = metrics["per_view"][k]["image"];
    auto frame = read_image(test_out / name);
    auto saved = read_image(run_ / "renders" / (fs::path(image).stem().string() + ".png"));
    ASSERT_TRUE(frame.ok() && saved.ok()) << image;
    EXPECT_LE((*frame - *saved).abs().max().item<float>(), 1.0f / 255 + 1e-6) << image;
  }

  // From the PLY alone (scene and split as flags): frame 2i of 5 is training camera i of 3.
  const fs::path interp_out = dir_ / "interp";
  std::tie(code, log) =
      test::run_command(kGaps + " render --model " + (run_ / "point_cloud.ply").string() + " --scene " +
                        kFern.string() + kFernRun + " --path interp --frames 5 --out " + interp_out.string());
  ASSERT_EQ(code, 0) << log;
  const std::vector<Camera> frames = frame_cameras(interp_out), train = fern_training_cameras();
  ASSERT_EQ(frames.size(), 5u);
  for (int i = 0; i < 3; ++i) {
    EXPECT_LT((frames[2 * i].center() - train[i].center()).norm(), 1e-6) << "training camera " << i;
    EXPECT_LT((frames[2 * i].R - train[i].R).norm(), 1e-6) << "training camera " << i;
  }
  std::tie(code, log) =
      test::run_command(kGaps + " render " + run_.string() + " --path circle --out " + (dir_ / "circle").string());
  EXPECT_EQ(code, 2) << log;
  EXPECT_TRUE(contains(log, "orbit, spiral, interp, test")) << log;
}

// --init-ply with a full 3DGS PLY continues that model: a run of one step with every learning rate near zero
// ends where the saved model was; the same points as a plain point cloud start over from new Gaussians.
TEST_F(RenderEval, InitPlyWithAFullModelContinuesIt) {
  const std::string tiny_steps =
      " --iterations 1 --position-lr-init 1e-12 --position-lr-final 1e-12 --feature-lr 1e-12 --opacity-lr "
      "1e-12 "
      "--scaling-lr 1e-12 --rotation-lr 1e-12 --eval-every 0 --report=false --save-every 0";
  auto [code, log] =
      test::run_command(kGaps + " train --scene " + kFern.string() + kFernRun + tiny_steps + " --init-ply " +
                        (run_ / "point_cloud.ply").string() + " --out " + (dir_ / "continued").string());
  ASSERT_EQ(code, 0) << log;
  EXPECT_TRUE(contains(log, "is a full 3DGS model: ")) << log;
  const nlohmann::json saved = read_json(run_ / "metrics.json"),
                       continued = read_json(dir_ / "continued" / "metrics.json");
  EXPECT_EQ(continued["init_method"], "ply-model");
  EXPECT_EQ(continued["num_gaussians"], saved["num_gaussians"]);
  EXPECT_NEAR(continued["psnr"].get<double>(), saved["psnr"].get<double>(), 1e-4);

  auto ply = read_ply_vertices(run_ / "point_cloud.ply");
  ASSERT_TRUE(ply.ok());
  const at::Tensor xyz = at::stack({ply->properties["x"], ply->properties["y"], ply->properties["z"]}, 1);
  ASSERT_TRUE(write_point_cloud_ply({xyz, at::full_like(xyz, 0.5)}, dir_ / "points.ply").ok());
  std::tie(code, log) =
      test::run_command(kGaps + " train --scene " + kFern.string() + kFernRun + tiny_steps + " --init-ply " +
                        (dir_ / "points.ply").string() + " --out " + (dir_ / "from_points").string());
  ASSERT_EQ(code, 0) << log;
  EXPECT_TRUE(contains(log, "is a point cloud")) << log;
  const nlohmann::json from_points = read_json(dir_ / "from_points" / "metrics.json");
  EXPECT_EQ(from_points["init_method"], "ply");
  EXPECT_GT(std::abs(from_points["psnr"].get<double>() - saved["psnr"].get<double>()), 0.1);
}

}  // namespace
}  // namespace gaps

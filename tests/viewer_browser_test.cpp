// The web viewer in a real browser: a small model trained on fern, served by the real `gaps view`, opened by
// headless Chromium (WebGL2 through SwiftShader, on the CPU) at a test camera with the UI hidden
// (#camera=test:0&ui=0). Its screenshot, at exactly the camera's size, must match the C++ rasterizer's
// render of the same camera, and the page must have drawn without a JavaScript error. The same for the
// model exported as a .splat file. Skipped, with a message, without the fern data or a Chromium binary
// ($GAPS_CHROMIUM, else chromium, chromium-browser or google-chrome on the PATH; scripts/setup.sh installs
// Debian's chromium).
//
// GAPS_VIEWER_SCREENSHOT=FILE.png also saves a screenshot of the viewer with its UI (the README's picture).
#include <unistd.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <regex>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "gs_trainer/eval/metrics.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/scene/cameras_json.h"
#include "gs_trainer/viewer/pack.h"
#include "tests/process_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// The threshold's basis. Both images are 8-bit, so each pixel already differs by up to half a step
// (1/510) from the float image; beyond that the two renderers differ only by float rounding (GPU exp and
// FMA against the CPU's, blending in float32 back to front against the rasterizer's front to back sums)
// and by the rasterizer's stop once a pixel's transmittance would fall below 1e-4 (at most 1e-4 of the
// colour), and the viewer reads the SH rest coefficients as float16 (~5e-4 relative). That is a few 1/255
// on few pixels, 40 dB and more; 30 dB (an RMS error of 8/255) leaves room for rounding yet fails a
// renderer that gets any part of the projection, the colours or the compositing wrong.
constexpr double kMinPsnr = 30.0;
// The .splat file stores colours, opacities and rotations in 8 bits (a rotation to within 1/256 per
// component) and SH degree 0 only. Against the rasterizer's render of the values the file decodes to, the
// bar above holds. Against the trained model (view-dependent colour to degree 3, full precision), the
// lost SH bands dominate; 20 dB still fails a file that decodes wrongly (channels, quaternion order, scale).
constexpr double kMinSplatVsModelPsnr = 20.0;

const fs::path kFern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";

std::string chromium_binary() {
  if (const char* given = std::getenv("GAPS_CHROMIUM")) return given;
  for (const char* name : {"chromium", "chromium-browser", "google-chrome"}) {
    const auto [code, path] = test::run_command(absl::StrCat("command -v ", name));
    if (code == 0 && !path.empty()) return path.substr(0, path.find('\n'));
  }
  return "";
}

// A model trained for a few hundred iterations on fern (3 views, 252x189 at -r 16) with every SH degree
// active and a grey background, shared by the suite.
class ViewerInBrowser : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    run_ = fs::path(::testing::TempDir()) / "gaps_viewer_browser_run";
    remove_tree(run_);
    if (!fs::exists(kFern)) return;
    RunOptions o;
    o.scene_dir = kFern;
    o.out_dir = run_;
    o.views = 3;
    o.resolution = 16;
    o.init = "random";
    o.random_points = 3000;
    o.config.iterations = 200;
    o.config.sh_increase_interval = 50;  // degree 3 from iteration 150: the viewer's SH is exercised
    o.config.background = 0.25;
    const auto result = run_pipeline(o, nullptr, [](const std::string&) {});
    trained_ = result.ok();
    EXPECT_TRUE(result.ok()) << result.status();
  }
  static void TearDownTestSuite() { remove_tree(run_); }

  void SetUp() override {
    if (!fs::exists(kFern)) GTEST_SKIP() << "benchmark data not found at " << kFern;
    chromium_ = chromium_binary();
    if (chromium_.empty())
      GTEST_SKIP() << "no Chromium to drive (set GAPS_CHROMIUM, or install Debian's chromium: scripts/setup.sh)";
    ASSERT_TRUE(trained_) << "the model could not be trained";
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    dir_ = fs::path(::testing::TempDir()) / ("gaps_viewer_browser_" + std::string(info->name()));
    remove_tree(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override {
    if (!dir_.empty()) remove_tree(dir_);
  }

  // `gaps view INPUT --port 0`, running until the test ends; the URL it prints.
  std::string serve(const fs::path& input) {
    server_ = std::make_unique<test::Process>(
        std::vector<std::string>{GAPS_CLI_BIN, "view", input.string(), "--port", "0"}, dir_ / "view.log");
    const int port = server_->wait_for_port();
    EXPECT_GT(port, 0) << server_->log_text();
    return absl::StrCat("http://127.0.0.1:", port, "/");
  }

  // Headless Chromium on `url` at a window of width x height: `action` is --dump-dom (the DOM on stdout) or
  // --screenshot=FILE. Its own profile under the test's folder; no sandbox only where it cannot run as root.
  std::string chromium(const std::string& action, int width, int height, const std::string& url) {
    const std::string command = absl::StrCat(
        "timeout 300 '", chromium_, "' --headless=new", geteuid() == 0 ? " --no-sandbox" : "", " --user-data-dir='",
        (dir_ / "profile").string(),
        "' --use-angle=swiftshader --enable-unsafe-swiftshader --force-device-scale-factor=1 --hide-scrollbars",
        " --no-first-run --disable-extensions --window-size=", width, ",", height, " --virtual-time-budget=60000 ",
        action, " '", url, "' 2>>'", (dir_ / "chromium.log").string(), "'");
    const auto [code, output] = test::run_command(command);
    EXPECT_EQ(code, 0) << command << "\n" << output << read_file_bytes(dir_ / "chromium.log").value_or("");
    return output;
  }

  // Opens the page at `hash` and checks it drew a frame without a JavaScript error.
  void expect_page_ready(const std::string& url) {
    const std::string dom = chromium("--dump-dom", 320, 240, url);
    std::smatch errors;
    const bool has_errors = std::regex_search(dom, errors, std::regex("<pre id=\"gaps-errors\"[^>]*>([^<]*)</pre>"));
    EXPECT_TRUE(has_errors && errors[1].str().empty()) << "the page reported errors: " << errors[1];
    EXPECT_EQ(dom.find("data-errors="), std::string::npos) << dom.substr(0, 400);
    EXPECT_NE(dom.find("data-state=\"ready\""), std::string::npos) << dom.substr(0, 400);
  }

  at::Tensor screenshot(const std::string& url, const Camera& camera) {
    const fs::path file = dir_ / "screenshot.png";
    chromium(absl::StrCat("--screenshot='", file.string(), "'"), camera.width, camera.height, url);
    const auto image = read_image(file);
    EXPECT_TRUE(image.ok()) << image.status();
    return image.ok() ? *image : at::Tensor();
  }

  static CameraRecord first_test_camera() {
    const auto cameras = read_cameras_json(run_ / "cameras.json");
    EXPECT_TRUE(cameras.ok()) << cameras.status();
    for (const CameraRecord& c : *cameras)
      if (c.split == "test") return c;
    ADD_FAILURE() << "cameras.json has no test camera";
    return {};
  }

  static at::Tensor background() {
    const json metrics = json::parse(*read_file_bytes(run_ / "metrics.json"));
    const float b = metrics["config"]["background"].get<float>();
    return at::full({3}, b);
  }

  // The rasterizer's render of `model` from `camera`, as a saved PNG has it (8 bits).
  static at::Tensor reference(const GaussianModel& model, const Camera& camera) {
    RenderOptions options;
    options.background = background();
    const at::Tensor rgb = render(model, camera, options).rgb.clamp(0, 1);
    return (rgb * 255).round() / 255;
  }

  // The fraction of pixels further than 16/255 from the background in some channel: the page must draw the
  // model, not the empty background.
  static double drawn_fraction(const at::Tensor& image) {
    return (image - background().view({1, 1, 3})).abs().amax(2).gt(16.0 / 255).to(at::kDouble).mean().item<double>();
  }

  void expect_matches(const at::Tensor& shot, const at::Tensor& expected, double min_psnr) {
    ASSERT_TRUE(shot.defined());
    ASSERT_EQ(shot.sizes(), expected.sizes()) << "the screenshot must have the camera's size";
    const double reference_drawn = drawn_fraction(expected);
    ASSERT_GT(reference_drawn, 0.3) << "the trained model covers too little of the view to test anything";
    EXPECT_GT(drawn_fraction(shot), 0.5 * reference_drawn) << "the page shows (almost) only the background";
    const double p = psnr(shot, expected);
    EXPECT_GE(p, min_psnr) << "viewer against the rasterizer";
    std::cout << "viewer vs rasterizer: PSNR " << p << " dB (bar " << min_psnr << ")\n";
  }

  static fs::path run_;
  static bool trained_;
  std::string chromium_;
  fs::path dir_;
  std::unique_ptr<test::Process> server_;
};

fs::path ViewerInBrowser::run_;
bool ViewerInBrowser::trained_ = false;

TEST_F(ViewerInBrowser, ATestCameraLooksAsTheRasterizerRendersIt) {
  const std::string url = serve(run_);
  expect_page_ready(url + "#camera=test:0&ui=0");
  const CameraRecord camera = first_test_camera();
  const auto model = load_gaussians_ply(run_ / "point_cloud.ply");
  ASSERT_TRUE(model.ok()) << model.status();
  ASSERT_GT(viewer::effective_sh_degree(*model), 0) << "the SH rest must be exercised";
  expect_matches(screenshot(url + "#camera=test:0&ui=0", camera.camera), reference(*model, camera.camera), kMinPsnr);
  // The report of the run embeds the same viewer (the model is far below its size limit).
  EXPECT_NE(read_file_bytes(run_ / "report.html")->find("<iframe class=\"viewer\""), std::string::npos);

  if (const char* docs = std::getenv("GAPS_VIEWER_SCREENSHOT")) {
    chromium(absl::StrCat("--screenshot='", docs, "'"), 960, 600, url + "#camera=train:1");
    std::cout << "saved the viewer with its UI to " << docs << "\n";
  }
}

// What the viewer decodes a .splat record to (splats.js decodeSplat), as a model the rasterizer renders.
GaussianModel decode_splat(const std::string& bytes) {
  const int64_t n = static_cast<int64_t>(bytes.size()) / viewer::kSplatRecordBytes;
  const at::Tensor records = at::from_blob(const_cast<char*>(bytes.data()), {n, 32}, at::kByte).clone();
  const at::Tensor floats = records.slice(1, 0, 24).contiguous().view(at::kFloat).view({n, 6});
  const at::Tensor u8 = records.slice(1, 24, 32).to(at::kFloat);
  GaussianModel m;
  m.means = floats.slice(1, 0, 3).contiguous();
  m.log_scales = floats.slice(1, 3, 6).log().contiguous();
  m.sh_dc = ((u8.slice(1, 0, 3) / 255 - 0.5) / 0.28209479177387814).view({n, 1, 3});
  m.opacity_logits = at::logit(u8.select(1, 3) / 255);
  m.quats = ((u8.slice(1, 4, 8) - 128) / 128).contiguous();
  m.sh_rest = at::zeros({n, 0, 3});
  m.max_sh_degree = m.sh_degree = 0;
  return m;
}

TEST_F(ViewerInBrowser, AnExportedSplatFileLoadsAndLooksAsItsValuesRender) {
  const fs::path splat = dir_ / "model.splat";
  const auto [code, output] =
      test::run_command(absl::StrCat(GAPS_CLI_BIN, " export ", run_.string(), " --format splat -o ", splat.string()));
  ASSERT_EQ(code, 0) << output;
  const std::string url = serve(splat);
  expect_page_ready(url + "#ui=0");
  const auto model = load_gaussians_ply(run_ / "point_cloud.ply");
  ASSERT_TRUE(model.ok()) << model.status();
  const auto bytes = read_file_bytes(splat);
  ASSERT_TRUE(bytes.ok());
  ASSERT_EQ(static_cast<int64_t>(bytes->size()), model->size() * viewer::kSplatRecordBytes);

  // A .splat has no cameras: the page shows its default view, so the test camera's pose goes in the URL of a
  // page served from the run's cameras. Served alone it must still draw (above); to look through the test
  // camera, the same bytes are viewed next to the run's cameras.json.
  fs::create_directories(dir_ / "with_cameras");
  ASSERT_TRUE(write_file_bytes(dir_ / "with_cameras" / "point_cloud.splat", *bytes).ok());
  fs::copy_file(run_ / "cameras.json", dir_ / "with_cameras" / "cameras.json");
  server_.reset();
  const std::string with_cameras = serve(dir_ / "with_cameras" / "point_cloud.splat");
  const CameraRecord camera = first_test_camera();
  const at::Tensor shot = screenshot(with_cameras + "#camera=test:0&ui=0", camera.camera);
  // The .splat's own values, rendered by the rasterizer: the viewer must match them as closely as the model.
  expect_matches(shot, reference(decode_splat(*bytes), camera.camera), kMinPsnr);
  // Against the trained model itself: 8-bit values and degree 0 (see kMinSplatVsModelPsnr).
  expect_matches(shot, reference(*model, camera.camera), kMinSplatVsModelPsnr);
}

TEST_F(ViewerInBrowser, ThePageReportsItsErrors) {
  // An unknown camera is an error the page reports where the test above looks for errors.
  const std::string url = serve(run_);
  const std::string dom = chromium("--dump-dom", 320, 240, url + "#camera=test:99&ui=0");
  EXPECT_NE(dom.find("data-errors=\"1\""), std::string::npos) << dom.substr(0, 400);
  EXPECT_NE(dom.find("#camera=test:99: no such camera"), std::string::npos);
}

}  // namespace
}  // namespace gaps

// The web viewer in a real browser: a small model trained on fern, served by the real `gaps view`, opened by
// headless Chromium (WebGL2 through SwiftShader, on the CPU) at a test camera with the UI hidden
// (#camera=test:0&ui=0). Its screenshot, at exactly the camera's size, must match the C++ rasterizer's
// render of the same camera, and the page must have drawn without a JavaScript error. The same for the
// model exported as a .splat file. The page's error reporting is checked on its own. Skipped, with a
// message, without the fern data or a Chromium binary ($GAPS_CHROMIUM, else chromium, chromium-browser or
// google-chrome on the PATH; scripts/setup.sh installs Debian's chromium).
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

// A browser, a folder per test and `gaps view`. Skips without a Chromium binary.
class BrowserTest : public ::testing::Test {
 protected:
  void SetUp() override {
    chromium_ = chromium_binary();
    if (chromium_.empty())
      GTEST_SKIP() << "no Chromium to drive (set GAPS_CHROMIUM, or install Debian's chromium: scripts/setup.sh)";
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    dir_ = fs::path(::testing::TempDir()) / ("gaps_viewer_browser_" + std::string(info->name()));
    remove_tree(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override {
    server_.reset();
    if (!dir_.empty()) remove_tree(dir_);
  }

  // `gaps view INPUT --port 0`, running until the next serve() or the end of the test; the URL it prints.
  std::string serve(const fs::path& input) {
    server_.reset();
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

  // The page at `url` after it settled: its DOM.
  std::string dom(const std::string& url) { return chromium("--dump-dom", 320, 240, url); }

  // Opens the page at `url` and checks it drew a frame without a JavaScript error.
  void expect_page_ready(const std::string& url) {
    const std::string page = dom(url);
    std::smatch errors;
    const bool has_box = std::regex_search(page, errors, std::regex("<pre id=\"gaps-errors\"[^>]*>([^<]*)</pre>"));
    EXPECT_TRUE(has_box && errors[1].str().empty()) << "the page reported errors: " << errors[1];
    EXPECT_EQ(page.find("data-errors="), std::string::npos) << page.substr(0, 400);
    EXPECT_NE(page.find("data-state=\"ready\""), std::string::npos) << page.substr(0, 400);
  }

  at::Tensor screenshot(const std::string& url, const Camera& camera) {
    const fs::path file = dir_ / "screenshot.png";
    chromium(absl::StrCat("--screenshot='", file.string(), "'"), camera.width, camera.height, url);
    const auto image = read_image(file);
    EXPECT_TRUE(image.ok()) << image.status();
    return image.ok() ? *image : at::Tensor();
  }

  std::string chromium_;
  fs::path dir_;
  std::unique_ptr<test::Process> server_;
};

// A model trained for 150 iterations on fern (3 views, 252x189 at -r 16) with every SH degree active and a
// grey background (one training per test process: ctest runs each test in a process of its own).
class ViewerInBrowser : public BrowserTest {
 protected:
  static void SetUpTestSuite() {
    run_ = fs::path(::testing::TempDir()) / ("gaps_viewer_browser_run_" + std::to_string(::getpid()));
    remove_tree(run_);
    if (!fs::exists(kFern) || chromium_binary().empty()) return;
    RunOptions o;
    o.scene_dir = kFern;
    o.out_dir = run_;
    o.views = 3;
    o.resolution = 16;
    o.init = "random";
    o.random_points = 3000;
    o.config.iterations = 150;
    o.config.sh_increase_interval = 40;  // degree 3 from iteration 120: the viewer's SH is exercised
    o.config.background = 0.25;
    const auto result = run_pipeline(o, nullptr, [](const std::string&) {});
    trained_ = result.ok();
    EXPECT_TRUE(result.ok()) << result.status();
  }
  static void TearDownTestSuite() { remove_tree(run_); }

  void SetUp() override {
    if (!fs::exists(kFern)) GTEST_SKIP() << "benchmark data not found at " << kFern;
    BrowserTest::SetUp();
    if (IsSkipped()) return;
    ASSERT_TRUE(trained_) << "the model could not be trained";
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
    return at::full({3}, metrics["config"]["background"].get<float>());
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

  void expect_matches(const at::Tensor& shot, const at::Tensor& expected, double min_psnr, const std::string& what) {
    ASSERT_TRUE(shot.defined());
    ASSERT_EQ(shot.sizes(), expected.sizes()) << "the screenshot must have the camera's size";
    const double reference_drawn = drawn_fraction(expected);
    ASSERT_GT(reference_drawn, 0.3) << "the trained model covers too little of the view to test anything";
    EXPECT_GT(drawn_fraction(shot), 0.5 * reference_drawn) << what << ": the page shows (almost) only the background";
    const double p = psnr(shot, expected);
    EXPECT_GE(p, min_psnr) << what;
    std::cout << what << ": PSNR " << p << " dB (at least " << min_psnr << " required)\n";
  }

  static fs::path run_;
  static bool trained_;
};

fs::path ViewerInBrowser::run_;
bool ViewerInBrowser::trained_ = false;

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

TEST_F(ViewerInBrowser, ATestCameraLooksAsTheRasterizerRendersTheModelAndItsSplatExport) {
  const CameraRecord camera = first_test_camera();
  const auto model = load_gaussians_ply(run_ / "point_cloud.ply");
  ASSERT_TRUE(model.ok()) << model.status();
  ASSERT_GT(viewer::effective_sh_degree(*model), 0) << "the SH rest must be exercised";
  const std::string url = serve(run_);
  expect_page_ready(url + "#camera=test:0&ui=0");
  expect_matches(screenshot(url + "#camera=test:0&ui=0", camera.camera), reference(*model, camera.camera), kMinPsnr,
                 "the model in the viewer against the rasterizer");
  // The report of the run embeds the same viewer (the model is far below its size limit).
  EXPECT_NE(read_file_bytes(run_ / "report.html")->find("<iframe class=\"viewer\""), std::string::npos);

  // The model exported as a .splat file, served alone (no cameras: the page's default view) and then next to
  // the run's cameras.json, to look through the test camera.
  fs::create_directories(dir_ / "export");
  const fs::path splat = dir_ / "export" / "model.splat";
  const auto [code, output] =
      test::run_command(absl::StrCat(GAPS_CLI_BIN, " export ", run_.string(), " --format splat -o ", splat.string()));
  ASSERT_EQ(code, 0) << output;
  const auto bytes = read_file_bytes(splat);
  ASSERT_TRUE(bytes.ok());
  ASSERT_EQ(static_cast<int64_t>(bytes->size()), model->size() * viewer::kSplatRecordBytes);
  expect_page_ready(serve(splat) + "#ui=0");
  fs::copy_file(run_ / "cameras.json", dir_ / "export" / "cameras.json");
  const at::Tensor shot = screenshot(serve(splat) + "#camera=test:0&ui=0", camera.camera);
  // The .splat's own values, rendered by the rasterizer: the viewer must match them as closely as the model.
  expect_matches(shot, reference(decode_splat(*bytes), camera.camera), kMinPsnr,
                 "the .splat in the viewer against the rasterizer's render of its values");
  // Against the trained model itself: 8-bit values and degree 0 (see kMinSplatVsModelPsnr).
  expect_matches(shot, reference(*model, camera.camera), kMinSplatVsModelPsnr,
                 "the .splat in the viewer against the trained model");
}

// A run folder with an untrained model (no training, no data set): enough to see errors reported.
class PageInBrowser : public BrowserTest {};

TEST_F(PageInBrowser, ReportsItsErrorsWhereTheTestsLookForThem) {
  at::manual_seed(3);
  GaussianModel m;
  m.means = at::randn({200, 3}) + at::tensor({0.0f, 0.0f, 4.0f});
  m.log_scales = at::full({200, 3}, -3.0);
  m.quats = at::randn({200, 4});
  m.opacity_logits = at::zeros({200});
  m.sh_dc = at::randn({200, 1, 3});
  m.sh_rest = at::zeros({200, 0, 3});
  m.max_sh_degree = m.sh_degree = 0;
  fs::create_directories(dir_ / "run");
  ASSERT_TRUE(save_gaussians_ply(m, dir_ / "run" / "point_cloud.ply").ok());
  Camera camera;
  camera.name = "a.png";
  camera.width = 64;
  camera.height = 48;
  camera.fx = camera.fy = 60;
  camera.cx = 32;
  camera.cy = 24;
  ASSERT_TRUE(write_cameras_json(dir_ / "run" / "cameras.json", {{camera, "test"}}).ok());
  const std::string url = serve(dir_ / "run");
  expect_page_ready(url + "#camera=test:0&ui=0");
  // An unknown camera is an error the page reports where the tests look for errors.
  const std::string page = dom(url + "#camera=test:9&ui=0");
  EXPECT_NE(page.find("data-errors=\"1\""), std::string::npos) << page.substr(0, 400);
  EXPECT_NE(page.find("#camera=test:9: no such camera"), std::string::npos);
}

}  // namespace
}  // namespace gaps

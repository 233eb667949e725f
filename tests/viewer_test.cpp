// The web viewer's pieces without a browser: the packed model and .splat layouts (bytes and round trips),
// what the viewer shows of a run folder, the self-contained page, and the HTTP server of `gaps view`
// (every resource, 404, bad requests, a real socket, a busy port).
#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <cmath>
#include <cstring>
#include <thread>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "client/view_server.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/scene/cameras_json.h"
#include "gs_trainer/viewer/assets.h"
#include "gs_trainer/viewer/pack.h"
#include "gs_trainer/viewer/site.h"
#include "gs_trainer/viewer/viewer_scene.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

constexpr double kShC0 = 0.28209479177387814;

// n Gaussians of SH degree 3 with distinct values; `rest_bands`: how many SH bands above 0 are non-zero.
GaussianModel model_with(int64_t n, int rest_bands) {
  at::manual_seed(7);
  GaussianModel m;
  m.means = at::randn({n, 3});
  m.log_scales = at::rand({n, 3}) * 3 - 4;
  m.quats = at::randn({n, 4});
  m.opacity_logits = at::randn({n});
  m.sh_dc = at::randn({n, 1, 3});
  m.sh_rest = at::zeros({n, 15, 3});
  const int64_t nonzero_rows = (rest_bands + 1) * (rest_bands + 1) - 1;
  if (nonzero_rows > 0) m.sh_rest.slice(1, 0, nonzero_rows).copy_(at::randn({n, nonzero_rows, 3}) * 0.3);
  m.max_sh_degree = 3;
  m.sh_degree = 3;
  return m;
}

template <typename T>
T read_at(const std::string& bytes, size_t offset) {
  T v;
  std::memcpy(&v, bytes.data() + offset, sizeof v);
  return v;
}

float half_to_float(uint16_t h) { return at::Half(h, at::Half::from_bits()).operator float(); }

TEST(PackModel, HeaderAndArraysFollowTheDocumentedLayout) {
  const GaussianModel m = model_with(5, 3);
  const std::string bytes = viewer::pack_model(m);
  ASSERT_EQ(static_cast<int64_t>(bytes.size()), viewer::packed_model_bytes(5, 3));
  EXPECT_EQ(bytes.size(), 32u + 5 * (4 * 14 + 2 * 45));
  EXPECT_EQ(bytes.substr(0, 8), "GAPSVW01");
  EXPECT_EQ(read_at<uint32_t>(bytes, 8), 5u);
  EXPECT_EQ(read_at<uint32_t>(bytes, 12), 3u);
  size_t offset = 32;
  // Each array in turn, as the rasterizer uses the values: activations applied, quaternions as stored.
  const std::vector<at::Tensor> floats = {m.means, m.scales(), m.quats, m.opacities(), m.sh_dc.reshape({5, 3})};
  for (const at::Tensor& expected : floats) {
    const at::Tensor e = expected.contiguous().view(-1);
    for (int64_t i = 0; i < e.numel(); ++i, offset += 4)
      EXPECT_EQ(read_at<float>(bytes, offset), e[i].item<float>()) << "float " << i << " at byte " << offset;
  }
  const at::Tensor rest = m.sh_rest.contiguous().view(-1);
  for (int64_t i = 0; i < rest.numel(); ++i, offset += 2) {
    const float expected = rest[i].item<float>();
    EXPECT_NEAR(half_to_float(read_at<uint16_t>(bytes, offset)), expected, 1e-3 * std::fabs(expected) + 1e-7);
  }
  EXPECT_EQ(offset, bytes.size());
}

TEST(PackModel, KeepsOnlyTheShBandsThatAreNotAllZero) {
  EXPECT_EQ(viewer::effective_sh_degree(model_with(4, 0)), 0);
  EXPECT_EQ(viewer::effective_sh_degree(model_with(4, 2)), 2);
  EXPECT_EQ(viewer::effective_sh_degree(model_with(4, 3)), 3);
  GaussianModel early = model_with(4, 3);
  early.sh_degree = 1;  // the active degree bounds what the rasterizer uses
  EXPECT_EQ(viewer::effective_sh_degree(early), 1);
  const std::string bytes = viewer::pack_model(model_with(4, 0));
  EXPECT_EQ(static_cast<int64_t>(bytes.size()), viewer::packed_model_bytes(4, 0));
  EXPECT_EQ(read_at<uint32_t>(bytes, 12), 0u);
}

TEST(SplatFile, RecordsHoldTheValuesInAntimatter15sLayoutAndOrder) {
  const int64_t n = 40;
  const GaussianModel m = model_with(n, 0);
  const std::string bytes = viewer::splat_file_bytes(m);
  ASSERT_EQ(bytes.size(), static_cast<size_t>(32 * n));
  EXPECT_TRUE(viewer::check_splat_bytes(bytes, "x").ok());
  const at::Tensor scales = m.scales(), opacities = m.opacities(), dc = m.sh_dc.reshape({n, 3});
  std::vector<bool> seen(n, false);
  double previous_importance = INFINITY;
  for (int64_t r = 0; r < n; ++r) {
    const size_t o = 32 * r;
    // Which Gaussian this record is: its position is stored exactly.
    int64_t g = -1;
    for (int64_t i = 0; i < n; ++i)
      if (read_at<float>(bytes, o) == m.means[i][0].item<float>() &&
          read_at<float>(bytes, o + 4) == m.means[i][1].item<float>())
        g = i;
    ASSERT_GE(g, 0) << "record " << r;
    ASSERT_FALSE(seen[g]);
    seen[g] = true;
    EXPECT_EQ(read_at<float>(bytes, o + 8), m.means[g][2].item<float>());
    double importance = opacities[g].item<double>();
    for (int k = 0; k < 3; ++k) {
      EXPECT_EQ(read_at<float>(bytes, o + 12 + 4 * k), scales[g][k].item<float>());
      importance *= scales[g][k].item<double>();
      const double colour = std::clamp(0.5 + kShC0 * dc[g][k].item<double>(), 0.0, 1.0);
      EXPECT_EQ(static_cast<uint8_t>(bytes[o + 24 + k]), std::lround(255 * colour)) << "record " << r;
    }
    EXPECT_EQ(static_cast<uint8_t>(bytes[o + 27]), std::lround(255 * opacities[g].item<double>()));
    EXPECT_LE(importance, previous_importance) << "records are sorted by size x opacity, largest first";
    previous_importance = importance;
    const at::Tensor q = m.quats[g] / m.quats[g].norm();
    for (int k = 0; k < 4; ++k)  // (q / |q|) * 128 + 128, w first: back within one step of 1/128
      EXPECT_NEAR((static_cast<uint8_t>(bytes[o + 28 + k]) - 128) / 128.0, q[k].item<double>(), 0.5 / 128 + 1e-6);
  }
}

TEST(SplatFile, OnlyWholeRecordsAreASplatFile) {
  EXPECT_FALSE(viewer::check_splat_bytes("", "f.splat").ok());
  const absl::Status odd = viewer::check_splat_bytes(std::string(33, 'x'), "f.splat");
  EXPECT_FALSE(odd.ok());
  EXPECT_NE(odd.message().find("f.splat: 33 bytes"), std::string::npos) << odd;
}

Camera test_camera(const std::string& name, double x) {
  Camera c;
  c.name = name;
  c.width = 40;
  c.height = 30;
  c.fx = c.fy = 35;
  c.cx = 20;
  c.cy = 15;
  c.t = Eigen::Vector3d(x, 0, 4);
  return c;
}

class ViewerRun : public test::TempDirTest {
 protected:
  // A finished run's folder: model, cameras (2 train, 1 test), one phase with an admitted and a rejected
  // pseudo-view (the first with a thumbnail), metrics with a grey background.
  void SetUp() override {
    TempDirTest::SetUp();
    run_ = dir_ / "run";
    fs::create_directories(run_ / "pseudo_views" / "phase_01");
    ASSERT_TRUE(save_gaussians_ply(model_with(20, 1), run_ / "point_cloud.ply").ok());
    ASSERT_TRUE(write_cameras_json(run_ / "cameras.json", {{test_camera("a.png", 0), "train"},
                                                           {test_camera("b.png", 0.5), "train"},
                                                           {test_camera("c.png", 0.25), "test"}})
                    .ok());
    const json phases = json::array({{{"phase", 1},
                                      {"iteration", 500},
                                      {"tier", 0},
                                      {"selection",
                                       {{{"id", 3},
                                         {"admitted", true},
                                         {"reason", "admitted: coverage"},
                                         {"coverage", 0.9},
                                         {"camera", camera_json(test_camera("p3", 0.1), 3, "pseudo")}},
                                        {{"id", 7},
                                         {"admitted", false},
                                         {"reason", "rejected: residual"},
                                         {"coverage", 0.4},
                                         {"camera", camera_json(test_camera("p7", 0.2), 7, "pseudo")}}}}}});
    ASSERT_TRUE(write_file_bytes(run_ / "phases.json", phases.dump()).ok());
    ASSERT_TRUE(write_png(run_ / "pseudo_views" / "phase_01" / "cand_003_admitted.png", at::rand({30, 40, 3})).ok());
    const json metrics = {
        {"scene", "/data/llff/fern"}, {"views", 3}, {"variant", "full"}, {"config", {{"background", 0.25}}}};
    ASSERT_TRUE(write_file_bytes(run_ / "metrics.json", metrics.dump()).ok());
  }

  fs::path run_;
};

TEST_F(ViewerRun, SceneHasTheRunsCamerasPhasesBackgroundAndThumbnails) {
  const auto scene = viewer::load_viewer_scene(run_);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->model_format, "packed");
  EXPECT_EQ(scene->gaussians, 20);
  EXPECT_EQ(scene->model_bytes, viewer::pack_model(*load_gaussians_ply(run_ / "point_cloud.ply")));
  const json& s = scene->scene;
  EXPECT_EQ(s["title"], "fern, 3 views, full");
  EXPECT_EQ(s["background"], json({0.25, 0.25, 0.25}));
  EXPECT_EQ(s["model"]["sh_degree"], 1);
  ASSERT_EQ(s["cameras"].size(), 3u);
  EXPECT_EQ(s["cameras"][2]["split"], "test");
  EXPECT_EQ(s["cameras"][2]["name"], "c.png");
  // World-to-camera pose and intrinsics as the rasterizer's camera: t survives the Inria layout's round trip.
  EXPECT_NEAR(s["cameras"][2]["t"][0].get<double>(), 0.25, 1e-12);
  EXPECT_NEAR(s["cameras"][2]["t"][2].get<double>(), 4, 1e-12);
  EXPECT_EQ(s["cameras"][2]["R"], json({1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0}));
  EXPECT_EQ(s["cameras"][2]["cx"], 20.0);
  ASSERT_EQ(s["phases"].size(), 1u);
  const json& views = s["phases"][0]["views"];
  ASSERT_EQ(views.size(), 2u);
  EXPECT_EQ(views[0]["admitted"], true);
  EXPECT_EQ(views[1]["reason"], "rejected: residual");
  EXPECT_EQ(views[1]["camera"]["split"], "pseudo");
  EXPECT_EQ(views[0]["image"], "pseudo_views/phase_01/cand_003_admitted.png");
  EXPECT_TRUE(views[1]["image"].is_null());  // not saved
  ASSERT_EQ(scene->images.size(), 1u);
}

TEST_F(ViewerRun, MissingInputsAndCorruptFilesAreErrorsNamingThem) {
  const auto missing = viewer::load_viewer_scene(dir_ / "nothing");
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kNotFound);
  EXPECT_NE(missing.status().message().find("nothing does not exist"), std::string::npos);
  fs::create_directories(dir_ / "empty");
  const auto empty = viewer::load_viewer_scene(dir_ / "empty");
  EXPECT_NE(empty.status().message().find("has no point_cloud.ply"), std::string::npos) << empty.status();
  const auto corrupt = viewer::load_viewer_scene(write("bad.ply", "ply\nformat ascii 1.0\nelement vertex 3\n"));
  EXPECT_FALSE(corrupt.ok());
  EXPECT_NE(corrupt.status().message().find("bad.ply"), std::string::npos) << corrupt.status();
  const auto splat = viewer::load_viewer_scene(write("odd.splat", std::string(40, 'x')));
  EXPECT_NE(splat.status().message().find("not a .splat file"), std::string::npos) << splat.status();
  const auto other = viewer::load_viewer_scene(write("model.txt", "x"));
  EXPECT_NE(other.status().message().find("neither a run folder"), std::string::npos) << other.status();
}

TEST_F(ViewerRun, ASplatFileIsServedAsItIs) {
  const std::string bytes = viewer::splat_file_bytes(model_with(6, 0));
  const auto scene = viewer::load_viewer_scene(write("m.splat", bytes));
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->model_format, "splat");
  EXPECT_EQ(scene->model_bytes, bytes);
  EXPECT_EQ(scene->gaussians, 6);
  EXPECT_EQ(viewer::viewer_site(*scene).count("/model.splat"), 1u);
}

// Status code, headers and body of a response.
struct Response {
  int code = 0;
  std::string head, body;
};
Response parse_response(const std::string& text) {
  Response r;
  const size_t end = text.find("\r\n\r\n");
  r.head = text.substr(0, end);
  r.body = end == std::string::npos ? "" : text.substr(end + 4);
  if (text.rfind("HTTP/1.1 ", 0) == 0) r.code = std::stoi(text.substr(9, 3));
  return r;
}
Response get(const viewer::WebSite& site, const std::string& path, const std::string& method = "GET") {
  return parse_response(client::http_response(site, method + " " + path + " HTTP/1.1\r\nHost: x\r\n\r\n"));
}

TEST_F(ViewerRun, TheServerAnswersEveryResourceAndNothingElse) {
  const auto scene = viewer::load_viewer_scene(run_);
  ASSERT_TRUE(scene.ok()) << scene.status();
  const viewer::WebSite site = viewer::viewer_site(*scene);
  const Response index = get(site, "/");
  EXPECT_EQ(index.code, 200);
  EXPECT_NE(index.head.find("Content-Type: text/html"), std::string::npos);
  EXPECT_NE(index.body.find("<canvas id=\"view\">"), std::string::npos);
  for (const viewer::Asset& a : viewer::viewer_assets()) {
    const Response r = get(site, "/" + a.name);
    EXPECT_EQ(r.code, 200) << a.name;
    EXPECT_EQ(r.body, a.text) << a.name;
    EXPECT_NE(r.head.find("Content-Length: " + std::to_string(a.text.size())), std::string::npos) << a.name;
  }
  EXPECT_NE(get(site, "/splats.js").head.find("Content-Type: text/javascript"), std::string::npos);
  const json description = json::parse(get(site, "/scene.json?x=1").body);
  EXPECT_EQ(description["model"]["url"], "model.bin");
  EXPECT_EQ(description["cameras"].size(), 3u);
  EXPECT_EQ(get(site, "/model.bin").body, scene->model_bytes);
  const Response image = get(site, "/pseudo_views/phase_01/cand_003_admitted.png");
  EXPECT_EQ(image.code, 200);
  EXPECT_EQ(image.body, *read_file_bytes(run_ / "pseudo_views" / "phase_01" / "cand_003_admitted.png"));
  // HEAD: the headers alone.
  const Response head = get(site, "/model.bin", "HEAD");
  EXPECT_EQ(head.code, 200);
  EXPECT_TRUE(head.body.empty());
  EXPECT_NE(head.head.find("Content-Length: " + std::to_string(scene->model_bytes.size())), std::string::npos);
  // Only the listed paths exist: the run's other files and anything climbing out are 404.
  for (const char* path : {"/metrics.json", "/point_cloud.ply", "/../run/metrics.json", "/pseudo_views/",
                           "/pseudo_views/phase_01/cand_007_rejected.png", "/%2e%2e/etc/passwd"})
    EXPECT_EQ(get(site, path).code, 404) << path;
  EXPECT_EQ(get(site, "/", "POST").code, 405);
  EXPECT_NE(get(site, "/", "DELETE").head.find("Allow: GET, HEAD"), std::string::npos);
  for (const char* bad :
       {"", "GET\r\n\r\n", "GET / FTP/1.0\r\n\r\n", "GET nopath HTTP/1.1\r\n\r\n", "GET / HTTP/1.1 extra\r\n\r\n"})
    EXPECT_EQ(parse_response(client::http_response(site, bad)).code, 400) << bad;
}

// One request over a socket to 127.0.0.1:port; the whole response.
std::string request_over_socket(int port, const std::string& request) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  inet_pton(AF_INET, "127.0.0.1", &address.sin_addr);
  if (connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof address) != 0) {
    close(fd);
    return "";
  }
  send(fd, request.data(), request.size(), 0);
  std::string response;
  char buffer[4096];
  for (ssize_t n; (n = recv(fd, buffer, sizeof buffer, 0)) > 0;) response.append(buffer, static_cast<size_t>(n));
  close(fd);
  return response;
}

TEST_F(ViewerRun, TheServerAnswersOverASocketAndABusyPortIsAClearError) {
  const auto scene = viewer::load_viewer_scene(run_);
  ASSERT_TRUE(scene.ok()) << scene.status();
  auto server = client::ViewServer::start("127.0.0.1", 0, viewer::viewer_site(*scene));
  ASSERT_TRUE(server.ok()) << server.status();
  const int port = (*server)->port();
  EXPECT_GT(port, 0);
  EXPECT_EQ((*server)->url(), "http://127.0.0.1:" + std::to_string(port) + "/");
  std::atomic<bool> stop{false};
  std::thread serving([&] { (*server)->serve([&] { return stop.load(); }); });
  const Response model = parse_response(request_over_socket(port, "GET /model.bin HTTP/1.1\r\nHost: x\r\n\r\n"));
  EXPECT_EQ(model.code, 200);
  EXPECT_EQ(model.body, scene->model_bytes);
  EXPECT_EQ(parse_response(request_over_socket(port, "GET /missing HTTP/1.1\r\n\r\n")).code, 404);
  EXPECT_EQ(parse_response(request_over_socket(port, "HELLO\r\n\r\n")).code, 400);

  const auto busy = client::ViewServer::start("127.0.0.1", port, {});
  ASSERT_FALSE(busy.ok());
  EXPECT_NE(busy.status().message().find("port " + std::to_string(port) + " on 127.0.0.1 is in use"), std::string::npos)
      << busy.status();
  EXPECT_NE(busy.status().message().find("--port"), std::string::npos);
  const auto no_host = client::ViewServer::start("no-such-host.invalid", 0, {});
  EXPECT_FALSE(no_host.ok());
  EXPECT_NE(no_host.status().message().find("--host no-such-host.invalid"), std::string::npos) << no_host.status();
  stop = true;
  serving.join();
}

TEST_F(ViewerRun, TheStandalonePageInlinesEveryAssetAndTheData) {
  const auto scene = viewer::load_viewer_scene(run_);
  ASSERT_TRUE(scene.ok()) << scene.status();
  const std::string page = viewer::standalone_viewer_page(*scene);
  EXPECT_EQ(page.find("<script src="), std::string::npos);
  EXPECT_EQ(page.find("href=\"viewer.css\""), std::string::npos);
  for (const viewer::Asset& a : viewer::viewer_assets())
    if (a.name != "index.html") EXPECT_NE(page.find(a.text), std::string::npos) << a.name;
  EXPECT_NE(page.find(viewer::base64_encode(scene->model_bytes)), std::string::npos);
  // The scene's JSON, with no '<' that could close its <script> element, and without the thumbnails (no
  // server to ask for them).
  const size_t begin = page.find("<script type=\"application/json\" id=\"gaps-scene\">");
  ASSERT_NE(begin, std::string::npos);
  const size_t start = page.find('>', begin) + 1, end = page.find("</script>", start);
  const json embedded = json::parse(page.substr(start, end - start));
  EXPECT_EQ(embedded["cameras"], scene->scene["cameras"]);
  EXPECT_TRUE(embedded["phases"][0]["views"][0]["image"].is_null());
}

TEST(Base64, EncodesEveryPaddingCase) {
  EXPECT_EQ(viewer::base64_encode(""), "");
  EXPECT_EQ(viewer::base64_encode("f"), "Zg==");
  EXPECT_EQ(viewer::base64_encode("fo"), "Zm8=");
  EXPECT_EQ(viewer::base64_encode("foo"), "Zm9v");
  EXPECT_EQ(viewer::base64_encode(std::string("\xff\x00\x10", 3)), "/wAQ");
}

}  // namespace
}  // namespace gaps

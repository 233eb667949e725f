#include "client/view_commands.h"

#include <atomic>
#include <csignal>
#include <filesystem>
#include <iostream>

#include "absl/flags/flag.h"
#include "absl/strings/str_cat.h"
#include "client/run_flags.h"
#include "client/view_server.h"
#include "common/error_kind.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/viewer/pack.h"
#include "gs_trainer/viewer/site.h"
#include "gs_trainer/viewer/viewer_scene.h"

ABSL_FLAG(std::string, host, "127.0.0.1",
          "address gaps view listens on (0.0.0.0: every interface; the viewer has no access control)");
ABSL_FLAG(int, port, 8080, "port gaps view listens on (0: a free one; the URL is printed)");
ABSL_FLAG(std::string, format, "",
          "splat (antimatter15 .splat: 32 bytes per Gaussian, SH degree 0) or html (one self-contained viewer "
          "page); default: from the extension of -o, else splat");

namespace gaps::client {
namespace {

namespace fs = std::filesystem;

std::atomic<bool> g_stop_serving{false};

extern "C" void on_view_stop(int) { g_stop_serving = true; }

int fail(const std::string& command, const absl::Status& status) {
  std::cerr << "gaps " << command << ": " << status.message() << "\n";
  return exit_code(status);
}

absl::StatusOr<fs::path> the_input(const cli::CommandLine& line, const std::string& command) {
  if (line.positional.size() != 1)
    return usage_error(
        absl::StrCat("gaps ", command, " takes one run folder, .ply or .splat file (gaps ", command, " --help)"));
  return fs::path(line.positional[0]);
}

absl::StatusOr<viewer::ViewerScene> load(const fs::path& input) {
  absl::StatusOr<viewer::ViewerScene> scene = viewer::load_viewer_scene(input);
  if (!scene.ok()) return input_data_error(scene.status());
  return scene;
}

absl::Status export_model(const fs::path& input, const std::string& format, const fs::path& output) {
  std::string bytes;
  if (format == "splat") {
    const fs::path ply = fs::is_directory(input) ? input / "point_cloud.ply" : input;
    absl::StatusOr<GaussianModel> model = load_gaussians_ply(ply);
    if (!model.ok()) return input_data_error(model.status());
    bytes = viewer::splat_file_bytes(*model);
  } else {
    GAPS_ASSIGN_OR_RETURN(const viewer::ViewerScene scene, load(input));
    bytes = viewer::standalone_viewer_page(scene);
  }
  return write_file_bytes(output, bytes);
}

}  // namespace

cli::FlagGroup view_flags() { return {"server", {"host", "port"}}; }
cli::FlagGroup export_flags() { return {"export", {"format", "out"}}; }

int run_view(const cli::CommandLine& line) {
  const absl::StatusOr<fs::path> input = the_input(line, "view");
  if (!input.ok()) return fail("view", input.status());
  const absl::StatusOr<viewer::ViewerScene> scene = load(*input);
  if (!scene.ok()) return fail("view", scene.status());
  absl::StatusOr<std::unique_ptr<ViewServer>> server =
      ViewServer::start(absl::GetFlag(FLAGS_host), absl::GetFlag(FLAGS_port), viewer::viewer_site(*scene));
  if (!server.ok()) return fail("view", server.status());
  std::signal(SIGINT, on_view_stop);
  std::signal(SIGTERM, on_view_stop);
  std::cout << "gaps view: " << input->string() << " (" << scene->gaussians << " Gaussians, "
            << scene->scene["cameras"].size() << " cameras) at " << (*server)->url() << " (port " << (*server)->port()
            << "); Ctrl-C stops" << std::endl;
  (*server)->serve([] { return g_stop_serving.load(); });
  std::cout << "gaps view: stopped" << std::endl;
  return 0;
}

int run_export(const cli::CommandLine& line) {
  const absl::StatusOr<fs::path> input = the_input(line, "export");
  if (!input.ok()) return fail("export", input.status());
  if (!fs::exists(*input))
    return fail("export", input_data_error(absl::NotFoundError(input->string() + " does not exist")));
  fs::path output = absl::GetFlag(FLAGS_out);
  std::string format = absl::GetFlag(FLAGS_format);
  if (format.empty()) format = output.extension() == ".html" ? "html" : "splat";
  if (format != "splat" && format != "html")
    return fail("export", usage_error(absl::StrCat("--format ", format, ": splat or html")));
  if (output.empty()) {
    const fs::path folder = fs::is_directory(*input) ? *input : input->parent_path();
    output = folder / (format == "splat" ? "point_cloud.splat" : "viewer.html");
  }
  if (absl::Status st = export_model(*input, format, output); !st.ok()) return fail("export", st);
  std::cout << "gaps export: wrote " << output.string() << " (" << fs::file_size(output) << " bytes)\n";
  return 0;
}

}  // namespace gaps::client

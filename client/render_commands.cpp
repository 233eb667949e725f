#include "client/render_commands.h"

#include <spawn.h>
#include <sys/wait.h>

#include <fstream>
#include <functional>
#include <iostream>
#include <optional>
#include <sstream>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/remote_client.h"
#include "client/remote_commands.h"
#include "client/run_flags.h"
#include "client/run_folder.h"
#include "common/device.h"
#include "common/error_kind.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/eval/lpips.h"
#include "gs_trainer/init/initializer.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/scene/camera_path.h"
#include "gs_trainer/scene/cameras_json.h"
#include "rpc/codec.h"

ABSL_FLAG(std::string, path, "auto",
          "camera path: auto (spiral for a capture facing one way, orbit for views around the scene), orbit, spiral, "
          "interp, test (the test cameras) or a cameras.json file (FILE.json)");
ABSL_FLAG(int, frames, 120, "frames of a generated path (orbit, spiral, interp)");
ABSL_FLAG(int, fps, 30, "frame rate of the video");
ABSL_FLAG(std::string, model, "",
          "a 3DGS PLY to use instead of a run folder (with --scene, --views and -r to know its cameras)");
ABSL_FLAG(std::string, job, "", "render a finished job on its gaps-trainer (--trainer) instead of a local model");

extern char** environ;

namespace gaps::client {
namespace {

namespace fs = std::filesystem;

// A saved model and the run that made it: what gaps render and gaps eval work on.
struct SavedRun {
  fs::path folder;      // the run folder; empty with --model
  fs::path model_file;  // its point_cloud.ply, or --model
  RunOptions options;   // scene_dir, views, resolution, config.background and config.device; LPIPS files
};

int fail(const std::string& command, const absl::Status& status) {
  std::cerr << "gaps " << command << ": " << status.message() << "\n";
  return exit_code(status);
}

absl::StatusOr<nlohmann::json> read_json_file(const fs::path& path, const std::string& what) {
  absl::StatusOr<std::string> text = read_file_bytes(path, what);
  if (!text.ok()) return input_data_error(text.status());
  nlohmann::json j = nlohmann::json::parse(*text, nullptr, /*allow_exceptions=*/false);
  if (!j.is_object()) return input_data_error(absl::DataLossError(absl::StrCat(path.string(), ": not a JSON object")));
  return j;
}

// The run a folder records: run.json (gaps train) or else metrics.json (also a fetched job's).
absl::StatusOr<RunOptions> recorded_run(const fs::path& folder) {
  std::error_code ec;
  if (fs::is_regular_file(folder / "run.json", ec)) {
    GAPS_ASSIGN_OR_RETURN(RunRecord record, read_run_record(folder));
    return record.options;
  }
  if (!fs::is_regular_file(folder / "metrics.json", ec))
    return usage_error(absl::StrCat(folder.string(),
                                    ": no run.json or metrics.json, so not a run folder (for a PLY alone: --model "
                                    "FILE --scene DIR --views N -r R)"));
  GAPS_ASSIGN_OR_RETURN(const nlohmann::json j, read_json_file(folder / "metrics.json", "run metrics"));
  RunOptions o;
  try {
    o.scene_dir = j.at("scene").get<std::string>();
    o.views = j.at("views");
    o.resolution = j.at("resolution");
    o.config = j.at("config").get<TrainConfig>();
  } catch (const std::exception& e) {
    return input_data_error(
        absl::DataLossError(absl::StrCat((folder / "metrics.json").string(), ": ", json_error_message(e))));
  }
  return o;
}

// The run folder (the command's argument) or --model, with what the flags given change of the recorded run.
absl::StatusOr<SavedRun> saved_run(const cli::CommandLine& line) {
  GAPS_ASSIGN_OR_RETURN(const FlagRun flags, run_from_flags());
  SavedRun run;
  if (!line.positional.empty()) {
    if (line.has("model")) return usage_error("a run folder and --model: give one");
    run.folder = line.positional[0];
    run.model_file = run.folder / "point_cloud.ply";
    GAPS_ASSIGN_OR_RETURN(run.options, recorded_run(run.folder));
    if (line.has("scene")) run.options.scene_dir = flags.options.scene_dir;
    if (line.has("views")) run.options.views = flags.options.views;
    if (line.has("resolution")) run.options.resolution = flags.options.resolution;
    if (flags.given.training.contains("background")) run.options.config.background = flags.options.config.background;
  } else if (line.has("model")) {
    run.model_file = absl::GetFlag(FLAGS_model);
    run.options = flags.options;
  } else {
    return usage_error("which model? give a run folder (gaps train's --out) or --model FILE.ply");
  }
  run.options.config.device = flags.options.config.device;
  run.options.lpips_backbone = flags.options.lpips_backbone;
  run.options.lpips_weights = flags.options.lpips_weights;
  GAPS_RETURN_IF_ERROR(check_device(run.options.config.device));
  std::error_code ec;
  if (!fs::is_regular_file(run.model_file, ec))
    return input_data_error(absl::NotFoundError(absl::StrCat(run.model_file.string(), ": no model there")));
  return run;
}

absl::StatusOr<GaussianModel> load_model(const SavedRun& run) {
  absl::StatusOr<GaussianModel> model = load_gaussians_ply(run.model_file);
  if (!model.ok()) return input_data_error(model.status());
  return model->to(at::Device(run.options.config.device));
}

absl::StatusOr<Scene> load_run_scene(const RunOptions& o) {
  if (o.scene_dir.empty()) return usage_error("the scene is unknown: give --scene DIR");
  SceneLoadOptions load;
  load.resolution = o.resolution;
  absl::StatusOr<Scene> scene = load_scene(o.scene_dir, load);
  if (!scene.ok()) return input_data_error(scene.status());
  return scene;
}

absl::StatusOr<Split> run_split(const Scene& scene, const RunOptions& o) {
  absl::StatusOr<Split> split = benchmark_split(static_cast<int>(scene.cameras.size()), o.views);
  if (!split.ok()) return usage_error(absl::StrCat("--views ", o.views, ": ", split.status().message()));
  return split;
}

// The run's training and test cameras: its cameras.json when there is one (so that a run renders without its
// scene), otherwise the scene split as the run split it.
absl::StatusOr<PathScene> run_cameras(const SavedRun& run) {
  PathScene out;
  const fs::path listed = run.folder / "cameras.json";
  std::error_code ec;
  if (!run.folder.empty() && fs::is_regular_file(listed, ec)) {
    absl::StatusOr<std::vector<CameraRecord>> records = read_cameras_json(listed);
    if (!records.ok()) return input_data_error(records.status());
    for (const CameraRecord& r : *records) {
      if (r.split == "train") out.train.push_back(r.camera);
      if (r.split == "test") out.test.push_back(r.camera);
    }
    if (!out.train.empty()) return out;
  }
  GAPS_ASSIGN_OR_RETURN(const Scene scene, load_run_scene(run.options));
  GAPS_ASSIGN_OR_RETURN(const Split split, run_split(scene, run.options));
  for (int i : split.train) out.train.push_back(scene.cameras[i]);
  for (int i : split.test) out.test.push_back(scene.cameras[i]);
  return out;
}

// --path, with "auto" following the capture: an orbit around a forward-facing capture looks at the back of
// what was never photographed, so such scenes get the spiral; views around the scene get the orbit.
std::string chosen_path(const PathScene& scene) {
  const std::string path = absl::GetFlag(FLAGS_path);
  if (path != "auto") return path;
  std::vector<Camera> capture = scene.train;
  capture.insert(capture.end(), scene.test.begin(), scene.test.end());
  const bool around = views_surround_scene(capture);
  if (!absl::GetFlag(FLAGS_quiet))
    std::cerr << "path: " << (around ? "orbit (the views surround the scene)" : "spiral (the views face one way)")
              << "; --path orbit|spiral|interp|test chooses another\n";
  return around ? "orbit" : "spiral";
}

// The cameras of `path` over `scene`, whose depth bounds are set first (from `points` when the cameras give
// none).
absl::StatusOr<std::vector<Camera>> path_cameras(const std::string& path, PathScene& scene, const at::Tensor& points) {
  if (scene.near <= 0 || scene.far <= scene.near) {
    absl::StatusOr<std::pair<double, double>> bounds = path_depth_bounds(scene.train, points);
    if (!bounds.ok()) return input_data_error(bounds.status());
    std::tie(scene.near, scene.far) = *bounds;
  }
  if (absl::GetFlag(FLAGS_frames) < 1) return usage_error("--frames must be at least 1");
  absl::StatusOr<std::vector<Camera>> cameras = camera_path(path, scene, absl::GetFlag(FLAGS_frames));
  if (absl::IsInvalidArgument(cameras.status()))
    return usage_error(absl::StrCat("--path ", cameras.status().message()));
  if (!cameras.ok()) return input_data_error(cameras.status());
  return cameras;
}

// A new or empty output folder; --overwrite first removes an earlier render's frames, cameras and video.
absl::Status prepare_render_folder(const fs::path& out) {
  std::error_code ec;
  if (fs::exists(out, ec) && !fs::is_empty(out, ec)) {
    if (!absl::GetFlag(FLAGS_overwrite))
      return usage_error(absl::StrCat(out.string(),
                                      " is not empty: pass --overwrite to replace an earlier render, "
                                      "or choose another --out"));
    for (const auto& entry : fs::directory_iterator(out, ec)) {
      const std::string name = entry.path().filename().string();
      const bool frame = entry.path().extension() == ".png" && name.size() == 9;
      if (frame || name == "cameras.json" || entry.path().extension() == ".mp4") fs::remove(entry.path(), ec);
    }
  }
  fs::create_directories(out, ec);
  if (ec || !fs::is_directory(out, ec)) return usage_error(absl::StrCat(out.string(), ": cannot create the folder"));
  return absl::OkStatus();
}

// Runs a program found on PATH, its output passed through; its exit status, or -1 when it could not start.
int run_program(const std::vector<std::string>& argv) {
  std::vector<char*> args;
  for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  pid_t pid = 0;
  if (posix_spawnp(&pid, args[0], nullptr, nullptr, args.data(), environ) != 0) return -1;
  int status = 0;
  if (waitpid(pid, &status, 0) != pid) return -1;
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

bool on_path(const std::string& program) {
  const char* path = std::getenv("PATH");
  if (path == nullptr) return false;
  std::stringstream dirs(path);
  std::string dir;
  std::error_code ec;
  while (std::getline(dirs, dir, ':'))
    if (!dir.empty() && fs::is_regular_file(fs::path(dir) / program, ec)) return true;
  return false;
}

// out/<name>.mp4 from out/%05d.png (H.264, yuv420p, padded to even sizes as yuv420p needs), where ffmpeg exists.
absl::Status write_video(const fs::path& out, const std::string& name) {
  if (!on_path("ffmpeg")) {
    std::cerr << "ffmpeg is not on PATH: frames only, no video\n";
    return absl::OkStatus();
  }
  const fs::path video = out / (name + ".mp4");
  const int code =
      run_program({"ffmpeg", "-y", "-loglevel", "error", "-framerate", std::to_string(absl::GetFlag(FLAGS_fps)), "-i",
                   (out / "%05d.png").string(), "-c:v", "libx264", "-pix_fmt", "yuv420p", "-vf",
                   "pad=ceil(iw/2)*2:ceil(ih/2)*2", video.string()});
  if (code != 0)
    return absl::InternalError(absl::StrCat("ffmpeg failed (exit status ", code, ") writing ", video.string()));
  std::cout << "video: " << video.string() << "\n";
  return absl::OkStatus();
}

using FrameRenderer = std::function<absl::StatusOr<at::Tensor>(const Camera&)>;

// Every frame through `render_frame` into out/00000.png..., their cameras into out/cameras.json, then the video.
absl::Status render_frames(const std::vector<Camera>& cameras, const FrameRenderer& render_frame, const fs::path& out,
                           const std::string& name) {
  GAPS_RETURN_IF_ERROR(prepare_render_folder(out));
  std::vector<CameraRecord> records;
  for (size_t k = 0; k < cameras.size(); ++k) {
    GAPS_ASSIGN_OR_RETURN(const at::Tensor rgb, render_frame(cameras[k]));
    GAPS_RETURN_IF_ERROR(write_png(out / cameras[k].name, rgb));
    records.push_back({cameras[k], name});
    if (!absl::GetFlag(FLAGS_quiet) && ((k + 1) % 10 == 0 || k + 1 == cameras.size()))
      std::cerr << "\rframe " << k + 1 << "/" << cameras.size() << std::flush;
  }
  if (!absl::GetFlag(FLAGS_quiet)) std::cerr << "\n";
  GAPS_RETURN_IF_ERROR(write_cameras_json(out / "cameras.json", records));
  std::cout << cameras.size() << " frames in " << out.string() << "\n";
  return write_video(out, name);
}

fs::path default_out(const fs::path& beside, const std::string& name) {
  const std::string out = absl::GetFlag(FLAGS_out);
  return out.empty() ? beside / ("render_" + name) : fs::path(out);
}

absl::Status render_local(const cli::CommandLine& line) {
  GAPS_ASSIGN_OR_RETURN(const SavedRun run, saved_run(line));
  GAPS_ASSIGN_OR_RETURN(const GaussianModel model, load_model(run));
  GAPS_ASSIGN_OR_RETURN(PathScene scene, run_cameras(run));
  const std::string path = chosen_path(scene);
  GAPS_ASSIGN_OR_RETURN(const std::vector<Camera> cameras, path_cameras(path, scene, model.means));
  const std::string name = camera_path_name(path);
  RenderOptions options;
  options.background = at::full({3}, run.options.config.background, model.means.options());
  const auto render_frame = [&](const Camera& camera) -> absl::StatusOr<at::Tensor> {
    at::AutoGradMode no_grad(false);
    return render(model, camera, options).rgb.clamp(0.0, 1.0).cpu();
  };
  return render_frames(cameras, render_frame,
                       default_out(run.folder.empty() ? run.model_file.parent_path() : run.folder, name), name);
}

absl::StatusOr<std::vector<Camera>> decoded(const google::protobuf::RepeatedPtrField<v1::Camera>& wire,
                                            const std::string& what) {
  std::vector<Camera> cameras;
  for (const v1::Camera& c : wire) {
    GAPS_ASSIGN_OR_RETURN(Camera camera, rpc::decode_camera(c, what));
    cameras.push_back(std::move(camera));
  }
  return cameras;
}

absl::Status render_remote() {
  const std::string job = absl::GetFlag(FLAGS_job);
  GAPS_ASSIGN_OR_RETURN(TrainerClient client, connect_trainer());
  GAPS_ASSIGN_OR_RETURN(const v1::JobCameras listed, client.job_cameras(job));
  PathScene scene;
  GAPS_ASSIGN_OR_RETURN(scene.train, decoded(listed.train(), "training camera"));
  GAPS_ASSIGN_OR_RETURN(scene.test, decoded(listed.test(), "test camera"));
  scene.near = listed.near();
  scene.far = listed.far();
  const std::string path = chosen_path(scene);
  GAPS_ASSIGN_OR_RETURN(const std::vector<Camera> cameras, path_cameras(path, scene, at::Tensor()));
  const std::string name = camera_path_name(path);
  const auto render_frame = [&](const Camera& camera) {
    v1::Camera wire;
    rpc::encode_camera(camera, &wire);
    return client.render(job, wire);
  };
  return render_frames(cameras, render_frame, default_out(fs::path("."), job + "_" + name), name);
}

// The test views of the run's split, with their images, on `device`.
absl::StatusOr<std::vector<TrainingView>> test_views(const RunOptions& o, const at::Device& device) {
  GAPS_ASSIGN_OR_RETURN(const Scene scene, load_run_scene(o));
  GAPS_ASSIGN_OR_RETURN(const Split split, run_split(scene, o));
  std::vector<TrainingView> views;
  for (int i : split.test) {
    absl::StatusOr<at::Tensor> image = load_camera_image(scene.cameras[i]);
    if (!image.ok()) return input_data_error(image.status());
    views.push_back({scene.cameras[i], image->to(device)});
  }
  return views;
}

absl::StatusOr<std::optional<Lpips>> lpips_for(const RunOptions& o) {
  absl::StatusOr<std::optional<Lpips>> lpips =
      load_lpips(o.lpips_weights, o.lpips_backbone, at::Device(o.config.device));
  if (!lpips.ok()) return input_data_error(lpips.status());
  return lpips;
}

nlohmann::json lpips_json(const std::optional<double>& value) {
  return value ? nlohmann::json(*value) : nlohmann::json(nullptr);
}

std::string lpips_text(const std::optional<double>& value) { return value ? absl::StrFormat("%.4f", *value) : "n/a"; }

absl::Status evaluate(const cli::CommandLine& line) {
  GAPS_ASSIGN_OR_RETURN(const SavedRun run, saved_run(line));
  const RunOptions& o = run.options;
  GAPS_ASSIGN_OR_RETURN(const GaussianModel model, load_model(run));
  GAPS_ASSIGN_OR_RETURN(const std::optional<Lpips> lpips, lpips_for(o));
  GAPS_ASSIGN_OR_RETURN(const std::vector<TrainingView> test, test_views(o, at::Device(o.config.device)));
  GAPS_ASSIGN_OR_RETURN(const std::vector<ImageMetrics> per_view,
                        evaluate_views(model, test, o.config.background, lpips ? &*lpips : nullptr, {}));
  GAPS_ASSIGN_OR_RETURN(const ImageMetrics mean, average_metrics(per_view));
  nlohmann::json j = {{"psnr", mean.psnr},
                      {"ssim", mean.ssim},
                      {"lpips", lpips_json(mean.lpips)},
                      {"model", run.model_file.string()},
                      {"num_gaussians", model.size()},
                      {"scene", o.scene_dir.string()},
                      {"views", o.views},
                      {"resolution", o.resolution},
                      {"background", o.config.background},
                      {"device", o.config.device},
                      {"per_view", nlohmann::json::array()}};
  for (size_t i = 0; i < per_view.size(); ++i) {
    const ImageMetrics& v = per_view[i];
    std::cout << absl::StrFormat("%-24s PSNR %.2f  SSIM %.4f  LPIPS %s\n", test[i].camera.name, v.psnr, v.ssim,
                                 lpips_text(v.lpips));
    j["per_view"].push_back(
        {{"image", test[i].camera.name}, {"psnr", v.psnr}, {"ssim", v.ssim}, {"lpips", lpips_json(v.lpips)}});
  }
  std::cout << absl::StrFormat("test PSNR %.2f dB  SSIM %.4f  LPIPS %s  |  %d views, %d Gaussians\n", mean.psnr,
                               mean.ssim, mean.lpips ? lpips_text(mean.lpips) : lpips_missing_note(), per_view.size(),
                               model.size());
  const std::string out_flag = absl::GetFlag(FLAGS_out);
  const fs::path out = !out_flag.empty()    ? fs::path(out_flag)
                       : run.folder.empty() ? run.model_file.parent_path()
                                            : run.folder;
  std::error_code ec;
  fs::create_directories(out, ec);
  GAPS_RETURN_IF_ERROR(write_file_bytes(out / "eval.json", j.dump(2) + "\n"));
  std::cout << "metrics in " << (out / "eval.json").string() << "\n";
  return absl::OkStatus();
}

}  // namespace

cli::FlagGroup render_flags() { return {"camera path", {"path", "frames", "fps", "job"}}; }
cli::FlagGroup model_flags() {
  return {"model (instead of a run folder)", {"model", "scene", "views", "resolution", "device", "background"}};
}

int run_render(const cli::CommandLine& line) {
  const bool remote = line.has("job");
  if (remote && (!line.positional.empty() || line.has("model")))
    return fail("render", usage_error("--job renders a job on its trainer: give no run folder or --model"));
  const absl::Status done = remote ? render_remote() : render_local(line);
  return done.ok() ? 0 : fail("render", done);
}

int run_eval(const cli::CommandLine& line) {
  const absl::Status done = evaluate(line);
  return done.ok() ? 0 : fail("eval", done);
}

}  // namespace gaps::client

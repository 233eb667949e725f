#include "gs_trainer/init/stage_control.h"

#include <chrono>
#include <memory>

#include "absl/strings/str_format.h"

namespace gaps {
namespace {

std::string stage_title(const std::string& stage) {
  if (stage == "sparse") return "sparse points (SIFT, matching, triangulation)";
  if (stage == "patchmatch") return "PatchMatch";
  if (stage == "fusion") return "fusion of the depth maps";
  if (stage == "sweep") return "plane sweep";
  return stage;
}

}  // namespace

std::function<void(const std::string&, int, int)> stage_progress_lines(std::function<void(const std::string&)> log) {
  if (!log) return {};
  struct State {
    std::chrono::steady_clock::time_point started;
    int tenths = 0;
  };
  auto state = std::make_shared<State>();
  return [log = std::move(log), state](const std::string& stage, int done, int total) {
    const std::string title = stage_title(stage);
    const bool counted = total > 1;  // a stage of many units (PatchMatch's sweeps), not one step
    if (done == 0) {
      state->started = std::chrono::steady_clock::now();
      state->tenths = 0;
      log(counted ? absl::StrFormat("init: %s: 0/%d sweeps", title, total) : absl::StrFormat("init: %s...", title));
      return;
    }
    const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - state->started).count();
    if (done >= total) {
      log(counted ? absl::StrFormat("init: %s: %d/%d sweeps, done in %.1f s", title, done, total, seconds)
                  : absl::StrFormat("init: %s: done in %.1f s", title, seconds));
      return;
    }
    const int tenths = 10 * done / total;
    if (tenths == state->tenths) return;
    state->tenths = tenths;
    log(absl::StrFormat("init: %s: %d/%d sweeps (%d%%, %.0f s)", title, done, total, 100 * done / total, seconds));
  };
}

}  // namespace gaps

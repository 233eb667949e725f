#pragma once
// What a long initialisation stage gets from its caller: a question whose "yes" stops it early, and a place
// to say how far it has come (on a CPU PatchMatch alone takes minutes, and a silent wait looks like a hang).
#include <functional>
#include <string>

namespace gaps {

struct StageControl {
  // Asked between units of work (a PatchMatch sweep, a stage): true ends the stage with CANCELLED.
  std::function<bool()> should_stop;
  // Told after each unit: the stage ("sparse", "patchmatch", "fusion", "sweep"), units done and in all.
  std::function<void(const std::string& stage, int done, int total)> on_progress;

  bool stop_requested() const { return should_stop && should_stop(); }
  void progress(const std::string& stage, int done, int total) const {
    if (on_progress) on_progress(stage, done, total);
  }
};

// A StageControl::on_progress that says where the initialisation is in `log` lines: each stage as it starts and
// ends (with its seconds), and PatchMatch at every tenth of its sweeps. Enough to see a CPU initialisation move
// (minutes) without flooding a log.
std::function<void(const std::string& stage, int done, int total)> stage_progress_lines(
    std::function<void(const std::string&)> log);

}  // namespace gaps

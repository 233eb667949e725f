#pragma once
// Training progress on stderr, for `gaps train`, `demo` and `watch`: on a terminal a bar redrawn in place;
// otherwise (a log file, a pipe) one plain line at every tenth of the run, so logs stay readable.
#include <cstdint>
#include <string>

namespace gaps::client {

// What --quiet keeps of a run's log lines: the warnings (the pipeline's and the client's start "warning:").
bool is_warning(const std::string& log_line);

struct ProgressLine {
  int iteration = 0;
  int iterations = 0;
  double loss = 0.0;
  int64_t num_gaussians = 0;
  double iterations_per_second = 0.0;
};

class ProgressPrinter {
 public:
  // `terminal`: whether stderr is one (isatty), unless a test says otherwise.
  explicit ProgressPrinter(bool quiet);
  ProgressPrinter(bool quiet, bool terminal) : quiet_(quiet), terminal_(terminal) {}

  void print(const ProgressLine& p);
  // Ends a bar drawn in place, so that the next message starts on a line of its own.
  void end_line();

 private:
  bool quiet_;
  bool terminal_;
  bool mid_line_ = false;
  int last_tenth_ = -1;
};

}  // namespace gaps::client

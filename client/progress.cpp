#include "client/progress.h"

#include <unistd.h>

#include <cstdio>
#include <string>

namespace gaps::client {

bool is_warning(const std::string& log_line) { return log_line.rfind("warning:", 0) == 0; }

ProgressPrinter::ProgressPrinter(bool quiet) : ProgressPrinter(quiet, isatty(fileno(stderr)) != 0) {}

void ProgressPrinter::print(const ProgressLine& p) {
  if (quiet_ || p.iterations <= 0) return;
  const double eta = p.iterations_per_second > 0 ? (p.iterations - p.iteration) / p.iterations_per_second : 0;
  const int eta_seconds = static_cast<int>(eta);
  if (terminal_) {
    const int width = 30;
    const int filled = static_cast<int>(width * static_cast<double>(p.iteration) / p.iterations);
    std::fprintf(stderr, "\r[%s%s] %6d/%d  loss %.4f  %8lld Gaussians  %6.1f it/s  ETA %02d:%02d ",
                 std::string(filled, '#').c_str(), std::string(width - filled, '.').c_str(), p.iteration, p.iterations,
                 p.loss, static_cast<long long>(p.num_gaussians), p.iterations_per_second, eta_seconds / 60,
                 eta_seconds % 60);
    mid_line_ = p.iteration != p.iterations;
    if (!mid_line_) std::fprintf(stderr, "\n");
    return;
  }
  const int tenth = static_cast<int>(10LL * p.iteration / p.iterations);
  if (tenth == last_tenth_) return;
  last_tenth_ = tenth;
  std::fprintf(stderr, "iteration %d/%d (%d%%)  loss %.4f  %lld Gaussians  %.1f it/s  ETA %02d:%02d\n", p.iteration,
               p.iterations, static_cast<int>(100LL * p.iteration / p.iterations), p.loss,
               static_cast<long long>(p.num_gaussians), p.iterations_per_second, eta_seconds / 60, eta_seconds % 60);
}

void ProgressPrinter::end_line() {
  if (mid_line_) std::fprintf(stderr, "\n");
  mid_line_ = false;
}

}  // namespace gaps::client

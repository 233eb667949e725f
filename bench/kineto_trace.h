#pragma once
// The PyTorch (Kineto) profiler around part of a benchmark: its Chrome trace is what bench/trace_summary.py
// ranks. The caller synchronises the device before start() and stop(), so the trace holds that part only.
#include <set>
#include <string>

#include <torch/csrc/autograd/profiler_kineto.h>

namespace gaps::bench {

class KinetoTrace {
 public:
  // Prepares the profiler for CPU operations, and CUDA kernels when `cuda`.
  explicit KinetoTrace(bool cuda) {
    if (cuda) activities_.insert(torch::profiler::impl::ActivityType::CUDA);
    torch::autograd::profiler::prepareProfiler(config_, activities_);
  }
  void start() { torch::autograd::profiler::enableProfiler(config_, activities_); }
  void stop_and_save(const std::string& path) { torch::autograd::profiler::disableProfiler()->save(path); }

 private:
  const torch::profiler::impl::ProfilerConfig config_{torch::profiler::impl::ProfilerState::KINETO};
  std::set<torch::profiler::impl::ActivityType> activities_ = {torch::profiler::impl::ActivityType::CPU};
};

}  // namespace gaps::bench

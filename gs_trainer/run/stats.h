#pragma once
// What a run measures about itself besides the final image quality: its evaluation curve (test metrics
// during training, for speed-vs-accuracy charts), its peak memory, and the time spent in the generator.
#include <optional>
#include <string>
#include <vector>

#include <ATen/Device.h>
#include <nlohmann/json_fwd.hpp>
#include "gs_trainer/eval/metrics.h"
#include "gs_trainer/gaps/generator.h"

namespace gaps {

// Test metrics after `iteration` iterations; `train_seconds` is the wall-clock training time up to then,
// without the time spent evaluating.
struct CurvePoint {
  int iteration = 0;
  double train_seconds = 0.0;
  ImageMetrics metrics;
  int64_t num_gaussians = 0;
};
void to_json(nlohmann::json& j, const CurvePoint& p);
void from_json(const nlohmann::json& j, CurvePoint& p);

// Peak memory of a run. On CUDA: the caching allocator's peak of allocated bytes (and of reserved bytes,
// closer to what nvidia-smi shows) since start(); on the CPU: the process's peak resident set size, which
// includes everything the process held before the run started.
struct PeakMemory {
  std::string kind;  // "cuda_allocator" or "cpu_rss"
  int64_t bytes = 0;
  std::optional<int64_t> reserved_bytes;  // CUDA only
};
void to_json(nlohmann::json& j, const PeakMemory& m);

class PeakMemoryMeter {
 public:
  // Resets the allocator's peak statistics of a CUDA device.
  explicit PeakMemoryMeter(const at::Device& device);
  PeakMemory read() const;

 private:
  at::Device device_;
};

// A Generator that forwards to another and adds up the wall-clock seconds spent in adapt() and generate().
class TimedGenerator : public Generator {
 public:
  explicit TimedGenerator(Generator* inner) : inner_(inner) {}
  std::string name() const override { return inner_->name(); }
  absl::Status adapt(const std::vector<ReferenceView>& views,
                     const std::optional<SceneAdaptation>& adaptation) override;
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override;
  std::vector<std::string> notes() const override { return inner_->notes(); }
  std::map<std::string, double> stage_seconds() const override { return inner_->stage_seconds(); }
  std::map<std::string, double> counters() const override { return inner_->counters(); }
  double seconds() const { return seconds_; }

 private:
  Generator* inner_;
  double seconds_ = 0.0;
};

}  // namespace gaps

#pragma once
// transformers' DepthAnythingForDepthEstimation (Depth-Anything V1 and V2): a DINOv2 backbone, a DPT-style
// neck (reassemble each chosen stage's patch tokens into a feature map at its own scale, then fuse them
// coarse to fine through residual conv units) and a head producing relative depth (disparity, ReLU) or
// metric depth (sigmoid times max_depth). Loaded from a transformers-layout folder; forward only.
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "diffusion_worker/depth/depth_processor.h"
#include "diffusion_worker/depth/dinov2.h"
#include "diffusion_worker/sdxl/layers.h"

namespace gaps::depth {

// DepthAnythingConfig (config.json). Unsupported options are refused by name.
struct DepthAnythingConfig {
  Dinov2Config backbone;
  int64_t patch_size = 14, reassemble_hidden_size = 384, fusion_hidden_size = 64, head_in_index = -1,
          head_hidden_size = 32;
  std::vector<double> reassemble_factors = {4, 2, 1, 0.5};
  std::vector<int64_t> neck_hidden_sizes = {48, 96, 192, 384};
  bool metric = false;  // depth_estimation_type "metric" (else "relative")
  double max_depth = 1.0;
  static absl::StatusOr<DepthAnythingConfig> from_json(const nlohmann::json& config);
};

class DepthAnything {
 public:
  // folder: config.json, preprocessor_config.json and the weights (*.safetensors, fp32/fp16/bf16, shards
  // allowed). options: the dtype and device the model runs in (weights are converted on load).
  static absl::StatusOr<DepthAnything> load(const std::string& folder, at::TensorOptions options = {});
  // The same from parts already in memory; source names the weights in errors.
  static absl::StatusOr<DepthAnything> from_weights(const DepthAnythingConfig& config,
                                                    const DepthProcessorConfig& processor, sdxl::TensorMap weights,
                                                    at::TensorOptions options, const std::string& source);
  // Every tensor the config asks for, by name and shape (current transformers names).
  static std::vector<sdxl::TensorSpec> weight_specs(const DepthAnythingConfig& config);

  // The model's forward: B x 3 x H x W normalised pixel values (any dtype and device) -> B x h x w predicted
  // depth with h, w = H, W rounded down to the patch size, in the model's dtype on its device.
  at::Tensor forward(const at::Tensor& pixel_values) const;
  // The backbone's stage hidden states for pixel values (B x (1 + patches) x hidden each).
  std::vector<at::Tensor> backbone_features(const at::Tensor& pixel_values) const;

  // image: H x W x 3 (uint8, or float in [0, 1]) -> H x W float32 CPU depth: preprocess, forward,
  // resample back to the image size. Relative models give disparity (larger is nearer, arbitrary scale and
  // shift); the bicubic resampling may leave small negative values at edges, as transformers' does.
  absl::StatusOr<at::Tensor> estimate_depth(const at::Tensor& image) const;

  const DepthAnythingConfig& config() const { return config_; }
  const DepthProcessor& processor() const { return processor_; }

 private:
  // Reassemble layer: 1x1 projection to the stage's width, then a transposed conv (factor > 1), nothing
  // (factor 1) or a strided 3x3 conv (factor < 1) to the stage's scale.
  struct Reassemble {
    sdxl::Conv2d projection, downsample;
    at::Tensor upsample_weight, upsample_bias;
    int64_t factor_up = 1, factor_down = 1;
  };
  struct ResidualUnit {  // pre-activation: x + conv2(relu(conv1(relu(x))))
    sdxl::Conv2d conv1, conv2;
    at::Tensor operator()(const at::Tensor& x) const;
  };
  struct Fusion {
    ResidualUnit residual1, residual2;
    sdxl::Conv2d projection;
  };
  static DepthAnything build(const DepthAnythingConfig& config, const DepthProcessorConfig& processor,
                             sdxl::WeightLoader& w);
  at::Tensor reassemble(const Reassemble& layer, const at::Tensor& tokens, int64_t grid_height,
                        int64_t grid_width) const;
  at::Tensor fuse(const Fusion& layer, const at::Tensor& fused, const at::Tensor& feature, at::IntArrayRef size) const;
  at::Tensor head(const at::Tensor& features, int64_t grid_height, int64_t grid_width) const;

  explicit DepthAnything(const DepthProcessorConfig& processor) : processor_(processor) {}

  DepthAnythingConfig config_;
  DepthProcessor processor_;
  Dinov2Backbone backbone_;
  std::vector<Reassemble> reassemble_;
  std::vector<sdxl::Conv2d> neck_convs_;
  std::vector<Fusion> fusion_;
  sdxl::Conv2d head_conv1_, head_conv2_, head_conv3_;
};

}  // namespace gaps::depth

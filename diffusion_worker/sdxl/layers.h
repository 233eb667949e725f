#pragma once
// The building blocks shared by the SDXL components, as plain ATen ops over weights taken by name from
// a WeightLoader (diffusers parameter names). Plain ATen ops, so autograd differentiates them (LoRA training).
#include <memory>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "diffusion_worker/sdxl/weights.h"

namespace gaps::sdxl {

struct Linear {
  at::Tensor weight, bias;  // bias undefined when the layer has none
  // Optional low-rank adapter (LoRA, see lora.h): the output gains lora_scale * lora_up(lora_down(x)),
  // lora_down r x in, lora_up out x r (float32, on the weight's device); undefined when the layer has none.
  at::Tensor lora_down, lora_up;
  double lora_scale = 1.0;
  static Linear load(WeightLoader& w, const std::string& prefix, int64_t in, int64_t out, bool with_bias = true);
  at::Tensor operator()(const at::Tensor& x) const;
};

// The layer that computes outputs [begin, end) of `layer` (weights copied; no adapter).
Linear output_rows(const Linear& layer, int64_t begin, int64_t end);

struct Conv2d {
  at::Tensor weight, bias;  // bias undefined when the layer has none
  int64_t stride = 1, padding = 0;
  // The model's activation layout (WeightLoader::kernel_format), kept apart from the kernel's strides: a 1x1
  // kernel's strides are both NCHW and channels-last, and ATen reads them as NCHW.
  at::MemoryFormat memory_format = at::MemoryFormat::Contiguous;
  static Conv2d load(WeightLoader& w, const std::string& prefix, int64_t in, int64_t out, int64_t kernel,
                     int64_t stride = 1, int64_t padding = -1 /* kernel / 2 */, bool with_bias = true);
  at::Tensor operator()(const at::Tensor& x) const;
};

struct GroupNorm {
  at::Tensor weight, bias;
  int64_t groups = 32;
  double eps = 1e-5;
  // Of a model whose convolutions run channels-last (WeightLoader::kernel_format): on CUDA outside autograd every
  // input goes through the channels-last kernel, made channels-last first where an elementwise result was not.
  bool channels_last = false;
  // weight and bias in float32, as the fused kernel reads them, kept once at load for a channels-last model
  // (undefined otherwise: the kernel converts per call where an NCHW model is given channels-last input).
  at::Tensor kernel_weight, kernel_bias;
  static GroupNorm load(WeightLoader& w, const std::string& prefix, int64_t groups, int64_t channels, double eps);
  at::Tensor operator()(const at::Tensor& x) const;
  // silu(operator()(x)), in one pass where the fused kernel applies.
  at::Tensor with_silu(const at::Tensor& x) const;
  // The model's activation layout, for blocks that rebuild a feature map from tokens after this norm.
  at::MemoryFormat memory_format() const {
    return channels_last ? at::MemoryFormat::ChannelsLast : at::MemoryFormat::Contiguous;
  }
};

struct LayerNorm {
  at::Tensor weight, bias;
  double eps = 1e-5;
  static LayerNorm load(WeightLoader& w, const std::string& prefix, int64_t dim, double eps);
  at::Tensor operator()(const at::Tensor& x) const;
};

// diffusers ResnetBlock2D (time_scale_shift "default", output scale 1): temb_channels 0 = no time input.
struct ResnetBlock {
  GroupNorm norm1, norm2;
  Conv2d conv1, conv2;
  Linear time_emb_proj;
  bool has_time = false, has_shortcut = false;
  Conv2d conv_shortcut;
  static ResnetBlock load(WeightLoader& w, const std::string& prefix, int64_t in, int64_t out, int64_t temb_channels,
                          int64_t groups, double eps);
  at::Tensor operator()(const at::Tensor& x, const at::Tensor& temb) const;
};

struct Downsample {  // stride-2 3x3 conv; the VAE pads (0, 1, 0, 1) itself and convolves without padding
  Conv2d conv;
  bool asymmetric_pad = false;
  static Downsample load(WeightLoader& w, const std::string& prefix, int64_t channels, bool asymmetric_pad);
  at::Tensor operator()(const at::Tensor& x) const;
};

struct Upsample {  // nearest 2x (or to a given size), then a 3x3 conv
  Conv2d conv;
  static Upsample load(WeightLoader& w, const std::string& prefix, int64_t channels);
  at::Tensor operator()(const at::Tensor& x, at::IntArrayRef size = {}) const;
};

// Multi-head attention over B x N x (H*D) projections: splits the heads, attends with
// at::scaled_dot_product_attention (scale 1/sqrt(D)), merges them back.
at::Tensor multi_head_attention(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v, int64_t heads,
                                bool causal = false);

class Attention;

// Computes an attention layer's output from its input and context. The default is plain multi-head
// attention; decoupled cross-attention (IP-Adapter) or other variants replace it per layer.
class AttentionProcessor {
 public:
  virtual ~AttentionProcessor() = default;
  // x: B x N x C (already normalised); context: B x M x Cc, or x itself for self-attention.
  virtual at::Tensor operator()(const Attention& attn, const at::Tensor& x, const at::Tensor& context) const = 0;
};

// diffusers Attention over token sequences: to_q, to_k, to_v, to_out.0.
class Attention {
 public:
  static Attention load(WeightLoader& w, const std::string& prefix, int64_t query_dim, int64_t context_dim,
                        int64_t heads, int64_t dim_head, bool qkv_bias);
  at::Tensor operator()(const at::Tensor& x, const at::Tensor& context) const;

  at::Tensor attend(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v) const {
    return multi_head_attention(q, k, v, heads);
  }
  void set_processor(std::shared_ptr<const AttentionProcessor> processor) { processor_ = std::move(processor); }

  // Projections stay public so processors (and low-rank adapters) can use and wrap them.
  Linear to_q, to_k, to_v, to_out;
  int64_t heads = 1;

 private:
  std::shared_ptr<const AttentionProcessor> processor_;
};

// Sinusoidal timestep features, B -> B x dim (diffusers get_timestep_embedding; cos first when flipped).
at::Tensor timestep_features(const at::Tensor& timesteps, int64_t dim, bool flip_sin_to_cos, double freq_shift);

// diffusers TimestepEmbedding: linear_1, SiLU, linear_2.
struct TimestepEmbedding {
  Linear linear_1, linear_2;
  static TimestepEmbedding load(WeightLoader& w, const std::string& prefix, int64_t in, int64_t dim);
  at::Tensor operator()(const at::Tensor& x) const;
};

}  // namespace gaps::sdxl

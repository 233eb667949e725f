#include "diffusion_worker/sdxl/layers.h"

#include <cmath>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#if defined(GAPS_CUDA_KERNELS)
#include "diffusion_worker/sdxl/cuda/group_norm_nhwc_cuda.h"
#endif

namespace gaps::sdxl {

Linear Linear::load(WeightLoader& w, const std::string& prefix, int64_t in, int64_t out, bool with_bias) {
  Linear l;
  l.weight = w.take(join_name(prefix, "weight"), {out, in});
  if (with_bias) l.bias = w.take(join_name(prefix, "bias"), {out});
  return l;
}

at::Tensor Linear::operator()(const at::Tensor& x) const {
  at::Tensor y = at::linear(x, weight, bias);
  if (!lora_down.defined()) return y;
  // Adapters stay float32 under half-precision weights (trainable, and their small updates survive).
  const at::Tensor low_rank = at::linear(at::linear(x.to(lora_down.scalar_type()), lora_down), lora_up);
  return y + (low_rank * lora_scale).to(y.scalar_type());
}

Linear output_rows(const Linear& layer, int64_t begin, int64_t end) {
  Linear l;
  l.weight = layer.weight.slice(0, begin, end).contiguous();
  if (layer.bias.defined()) l.bias = layer.bias.slice(0, begin, end).contiguous();
  return l;
}

Conv2d Conv2d::load(WeightLoader& w, const std::string& prefix, int64_t in, int64_t out, int64_t kernel, int64_t stride,
                    int64_t padding, bool with_bias) {
  Conv2d c;
  c.weight = w.take(join_name(prefix, "weight"), {out, in, kernel, kernel});
  if (with_bias) c.bias = w.take(join_name(prefix, "bias"), {out});
  c.stride = stride;
  c.padding = padding < 0 ? kernel / 2 : padding;
  c.memory_format = w.kernel_format();
  return c;
}

at::Tensor Conv2d::operator()(const at::Tensor& x) const {
  // The input takes the kernel's layout, and cuDNN gives the output that layout too: so the activations' layout is
  // the model's (channels_last or not), not whatever strides an elementwise result happened to get, and the
  // GroupNorms, cuDNN's algorithms and a CUDA graph's replay see the same layout at every step.
  return at::conv2d(x.contiguous(memory_format), weight, bias, {stride, stride}, {padding, padding});
}

GroupNorm GroupNorm::load(WeightLoader& w, const std::string& prefix, int64_t groups, int64_t channels, double eps) {
  GroupNorm g{w.take(join_name(prefix, "weight"), {channels}), w.take(join_name(prefix, "bias"), {channels}), groups,
              eps, w.kernel_format() == at::MemoryFormat::ChannelsLast};
  if (g.channels_last) {
    // The fused kernel's hot path (600 GroupNorms a batch) should not convert them at every call.
    g.kernel_weight = g.weight.to(at::kFloat).contiguous();
    g.kernel_bias = g.bias.to(at::kFloat).contiguous();
  }
  return g;
}

namespace {

// On a CUDA device a channels-last model's GroupNorm (or one given channels-last activations) runs the fused
// kernel, which keeps the layout (ATen's CUDA GroupNorm returns NCHW, and the next convolution would transpose
// back); the kernel has no backward, so a graph autograd records (LoRA training) takes ATen's.
bool fused_group_norm(const at::Tensor& x, const GroupNorm& norm) {
#if defined(GAPS_CUDA_KERNELS)
  const bool recording = at::GradMode::is_enabled() && (x.requires_grad() || norm.weight.requires_grad());
  const bool channels_last =
      norm.channels_last || (x.is_contiguous(at::MemoryFormat::ChannelsLast) && !x.is_contiguous());
  // The kernel keeps per-channel sums in shared memory: up to 4096 channels (SDXL's widest layer has 1280).
  return x.is_cuda() && x.dim() == 4 && x.size(1) <= 4096 && channels_last && !recording;
#else
  (void)x, (void)norm;
  return false;
#endif
}

at::Tensor group_norm(const GroupNorm& norm, const at::Tensor& x, bool silu) {
#if defined(GAPS_CUDA_KERNELS)
  if (fused_group_norm(x, norm))
    return group_norm_nhwc_cuda(x.contiguous(at::MemoryFormat::ChannelsLast), norm.groups,
                                norm.kernel_weight.defined() ? norm.kernel_weight : norm.weight,
                                norm.kernel_bias.defined() ? norm.kernel_bias : norm.bias, norm.eps, silu);
#endif
  const at::Tensor y = at::group_norm(x, norm.groups, norm.weight, norm.bias, norm.eps);
  return silu ? at::silu(y) : y;
}

}  // namespace

at::Tensor GroupNorm::operator()(const at::Tensor& x) const { return group_norm(*this, x, false); }

at::Tensor GroupNorm::with_silu(const at::Tensor& x) const { return group_norm(*this, x, true); }

LayerNorm LayerNorm::load(WeightLoader& w, const std::string& prefix, int64_t dim, double eps) {
  return {w.take(join_name(prefix, "weight"), {dim}), w.take(join_name(prefix, "bias"), {dim}), eps};
}

at::Tensor LayerNorm::operator()(const at::Tensor& x) const {
  return at::layer_norm(x, {weight.size(0)}, weight, bias, eps);
}

ResnetBlock ResnetBlock::load(WeightLoader& w, const std::string& prefix, int64_t in, int64_t out,
                              int64_t temb_channels, int64_t groups, double eps) {
  ResnetBlock r;
  r.norm1 = GroupNorm::load(w, join_name(prefix, "norm1"), groups, in, eps);
  r.conv1 = Conv2d::load(w, join_name(prefix, "conv1"), in, out, 3);
  r.has_time = temb_channels > 0;
  if (r.has_time) r.time_emb_proj = Linear::load(w, join_name(prefix, "time_emb_proj"), temb_channels, out);
  r.norm2 = GroupNorm::load(w, join_name(prefix, "norm2"), groups, out, eps);
  r.conv2 = Conv2d::load(w, join_name(prefix, "conv2"), out, out, 3);
  r.has_shortcut = in != out;
  if (r.has_shortcut) r.conv_shortcut = Conv2d::load(w, join_name(prefix, "conv_shortcut"), in, out, 1);
  return r;
}

at::Tensor ResnetBlock::operator()(const at::Tensor& x, const at::Tensor& temb) const {
  at::Tensor h = conv1(norm1.with_silu(x));
  if (has_time) h = h + time_emb_proj(at::silu(temb)).unsqueeze(-1).unsqueeze(-1);
  h = conv2(norm2.with_silu(h));
  return (has_shortcut ? conv_shortcut(x) : x) + h;
}

Downsample Downsample::load(WeightLoader& w, const std::string& prefix, int64_t channels, bool asymmetric_pad) {
  return {Conv2d::load(w, join_name(prefix, "conv"), channels, channels, 3, 2, asymmetric_pad ? 0 : 1), asymmetric_pad};
}

at::Tensor Downsample::operator()(const at::Tensor& x) const {
  return conv(asymmetric_pad ? at::constant_pad_nd(x, {0, 1, 0, 1}, 0) : x);
}

Upsample Upsample::load(WeightLoader& w, const std::string& prefix, int64_t channels) {
  return {Conv2d::load(w, join_name(prefix, "conv"), channels, channels, 3)};
}

at::Tensor Upsample::operator()(const at::Tensor& x, at::IntArrayRef size) const {
  at::Tensor up;
  if (size.empty()) {
    up = at::upsample_nearest2d(x, {2 * x.size(2), 2 * x.size(3)});
  } else {
    up = at::upsample_nearest2d(x, size);
  }
  return conv(up);
}

Attention Attention::load(WeightLoader& w, const std::string& prefix, int64_t query_dim, int64_t context_dim,
                          int64_t heads, int64_t dim_head, bool qkv_bias) {
  Attention a;
  const int64_t inner = heads * dim_head;
  a.to_q = Linear::load(w, join_name(prefix, "to_q"), query_dim, inner, qkv_bias);
  a.to_k = Linear::load(w, join_name(prefix, "to_k"), context_dim, inner, qkv_bias);
  a.to_v = Linear::load(w, join_name(prefix, "to_v"), context_dim, inner, qkv_bias);
  a.to_out = Linear::load(w, join_name(prefix, "to_out.0"), inner, query_dim, true);
  a.heads = heads;
  return a;
}

at::Tensor multi_head_attention(const at::Tensor& q, const at::Tensor& k, const at::Tensor& v, int64_t heads,
                                bool causal) {
  const auto split = [heads](const at::Tensor& t) {
    return t.view({t.size(0), t.size(1), heads, t.size(2) / heads}).transpose(1, 2);
  };
  at::Tensor out = at::scaled_dot_product_attention(split(q), split(k), split(v), {}, 0.0, causal);
  return out.transpose(1, 2).reshape({q.size(0), q.size(1), v.size(2)});
}

at::Tensor Attention::operator()(const at::Tensor& x, const at::Tensor& context) const {
  if (processor_) return (*processor_)(*this, x, context);
  return to_out(attend(to_q(x), to_k(context), to_v(context)));
}

at::Tensor timestep_features(const at::Tensor& timesteps, int64_t dim, bool flip_sin_to_cos, double freq_shift) {
  const int64_t half = dim / 2;
  const at::Tensor exponent =
      at::arange(0, half, timesteps.options().dtype(at::kFloat)) * (-std::log(10000.0)) / (half - freq_shift);
  const at::Tensor args = timesteps.to(at::kFloat).unsqueeze(1) * at::exp(exponent).unsqueeze(0);
  at::Tensor emb =
      flip_sin_to_cos ? at::cat({at::cos(args), at::sin(args)}, -1) : at::cat({at::sin(args), at::cos(args)}, -1);
  if (dim % 2 == 1) emb = at::constant_pad_nd(emb, {0, 1}, 0);
  return emb;
}

TimestepEmbedding TimestepEmbedding::load(WeightLoader& w, const std::string& prefix, int64_t in, int64_t dim) {
  return {Linear::load(w, join_name(prefix, "linear_1"), in, dim),
          Linear::load(w, join_name(prefix, "linear_2"), dim, dim)};
}

at::Tensor TimestepEmbedding::operator()(const at::Tensor& x) const { return linear_2(at::silu(linear_1(x))); }

}  // namespace gaps::sdxl

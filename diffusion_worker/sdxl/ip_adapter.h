#pragma once
// IP-Adapter (Ye et al. 2023) as diffusers runs it: the CLIP image embedding of a reference image is
// projected to a few context tokens (ImageProjection), and every cross-attention layer (attn2) of the UNet
// attends to them through its own key/value projections, added to the text attention with a scale:
//   out = to_out(attention(q, k_text, v_text) + scale * attention(q, to_k_ip(tokens), to_v_ip(tokens)))
// (diffusers' IPAdapterAttnProcessor2_0). Weights come in diffusers' single-file layout
// (ip-adapter_sdxl*.safetensors): image_proj.proj.{weight,bias}, image_proj.norm.{weight,bias} and
// ip_adapter.<n>.to_{k,v}_ip.weight, n = 1, 3, 5, ... over the cross-attention layers in the order of
// diffusers' unet.attn_processors (down blocks, up blocks, then the mid block).
#include <map>
#include <memory>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "diffusion_worker/sdxl/layers.h"
#include "diffusion_worker/sdxl/unet.h"

namespace gaps::sdxl {

// diffusers ImageProjection: B x E image embeddings -> B x num_tokens x cross_attention_dim.
struct ImageProjection {
  Linear image_embeds;
  LayerNorm norm;
  int64_t num_tokens = 4;
  at::Tensor operator()(const at::Tensor& embeds) const;
};

// The image prompt the decoupled cross-attention layers read during a UNet forward: B x T x C tokens and
// a per-image scale. Values are copied into buffers kept per shape, so a UNet forward captured as a CUDA
// graph (which reads fixed addresses) sees every later prompt of its batch size.
class ImagePrompt {
 public:
  // tokens: B x T x C in the UNet's dtype and device; scales: B.
  void set(const at::Tensor& tokens, const at::Tensor& scales);
  // No image prompt until the next set(): the layers attend to the text alone, as the UNet without the
  // adapter does (LoRA training, which adapts the text-conditioned UNet; see SdxlPipeline::train_lora).
  void set_text_only() {
    current_ = nullptr;
    text_only_ = true;
  }
  bool text_only() const { return text_only_; }
  const at::Tensor& tokens() const;  // undefined before the first set()
  const at::Tensor& scales() const;  // B x 1 x 1

 private:
  struct Buffers {
    at::Tensor tokens, scales;
  };
  std::map<std::vector<int64_t>, Buffers> buffers_;
  const Buffers* current_ = nullptr;
  bool text_only_ = false;
};

// The decoupled cross-attention of one attn2 layer.
class DecoupledCrossAttention final : public AttentionProcessor {
 public:
  DecoupledCrossAttention(Linear to_k_ip, Linear to_v_ip, std::shared_ptr<const ImagePrompt> prompt)
      : to_k_ip_(std::move(to_k_ip)), to_v_ip_(std::move(to_v_ip)), prompt_(std::move(prompt)) {}
  at::Tensor operator()(const Attention& attn, const at::Tensor& x, const at::Tensor& context) const override;

 private:
  Linear to_k_ip_, to_v_ip_;
  std::shared_ptr<const ImagePrompt> prompt_;
};

class IpAdapter {
 public:
  // Reads an IP-Adapter safetensors file, checks it against the UNet (number and sizes of its
  // cross-attention layers, cross_attention_dim) and installs the decoupled cross-attention on every attn2
  // layer. The UNet is left untouched on error; errors name the file and the mismatch. Other IP-Adapter
  // kinds (Plus, Full Face, FaceID) are refused by name.
  static absl::StatusOr<std::unique_ptr<IpAdapter>> load(const std::string& path, UNet2DCondition& unet,
                                                         at::TensorOptions options);
  static absl::StatusOr<std::unique_ptr<IpAdapter>> load(TensorMap weights, UNet2DCondition& unet,
                                                         at::TensorOptions options, const std::string& source);

  // CLIP image_embeds B x E -> B x 4 x cross_attention_dim.
  at::Tensor project(const at::Tensor& image_embeds) const { return projection_(image_embeds); }
  // The tokens (B x T x C) and per-image scales (B) the UNet's attn2 layers attend to from now on.
  void set_image_prompt(const at::Tensor& tokens, const at::Tensor& scales) { prompt_->set(tokens, scales); }
  // The attn2 layers attend to the text alone until the next set_image_prompt.
  void set_text_only() { prompt_->set_text_only(); }

  int64_t image_embed_dim() const { return projection_.image_embeds.weight.size(1); }
  int64_t num_layers() const { return num_layers_; }

 private:
  ImageProjection projection_;
  std::shared_ptr<ImagePrompt> prompt_ = std::make_shared<ImagePrompt>();
  int64_t num_layers_ = 0;
};

}  // namespace gaps::sdxl

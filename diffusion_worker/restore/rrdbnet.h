#pragma once
// RRDBNet, the generator of Real-ESRGAN (BasicSR's architecture): a trunk of residual-in-residual dense
// blocks at the input's resolution, then nearest-neighbour x2 upsamplings each followed by a convolution.
//   feat = conv_first(x); trunk = body(feat); feat = feat + conv_body(trunk)
//   feat = lrelu(conv_up1(nearest x2(feat))); feat = lrelu(conv_up2(nearest x2(feat)))
//   out  = conv_last(lrelu(conv_hr(feat)))
// RRDB: three dense blocks, out = 0.2 * rdb3(rdb2(rdb1(x))) + x. Dense block: five 3x3 convolutions, the
// k-th over the concatenation of its input and the k-1 earlier outputs (LeakyReLU 0.2 after the first
// four), out = 0.2 * conv5 + x. Weight names are BasicSR's (conv_first, body.N.rdbM.convK, conv_body,
// conv_up1, conv_up2, conv_hr, conv_last; .weight OIHW, .bias), as scripts/realesrgan_weights.py writes them.
#include <vector>

#include <ATen/Tensor.h>
#include "diffusion_worker/sdxl/layers.h"
#include "diffusion_worker/sdxl/weights.h"

namespace gaps::restore {

// Real-ESRGAN x4plus by default; tests build small random ones.
struct RrdbNetConfig {
  int64_t in_channels = 3, out_channels = 3;
  int64_t num_feat = 64;   // trunk channels
  int64_t num_block = 23;  // RRDB blocks
  int64_t num_grow = 32;   // channels each dense-block convolution adds
};

class RrdbNet {
 public:
  // Takes every weight the config implies from w (check w.finish() afterwards for missing or mis-shaped ones).
  static RrdbNet load(sdxl::WeightLoader& w, const RrdbNetConfig& config);

  // x: N x in_channels x h x w of the weights' dtype and device, images in [0, 1] for the real weights.
  // Returns N x out_channels x 4h x 4w, not clamped.
  at::Tensor operator()(const at::Tensor& x) const;

  const RrdbNetConfig& config() const { return config_; }
  static constexpr int64_t kScale = 4;

 private:
  struct DenseBlock {
    sdxl::Conv2d convs[5];
  };
  struct Rrdb {
    DenseBlock rdbs[3];
  };
  at::Tensor dense_block(const DenseBlock& block, const at::Tensor& x) const;

  RrdbNetConfig config_;
  sdxl::Conv2d conv_first_, conv_body_, conv_up1_, conv_up2_, conv_hr_, conv_last_;
  std::vector<Rrdb> body_;
};

}  // namespace gaps::restore

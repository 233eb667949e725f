#include "diffusion_worker/restore/rrdbnet.h"

#include <string>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"

namespace gaps::restore {
namespace {

constexpr double kSlope = 0.2;          // LeakyReLU's negative slope throughout
constexpr double kResidualScale = 0.2;  // dense blocks and RRDBs add 0.2 x their output to their input

at::Tensor lrelu(const at::Tensor& x) { return at::leaky_relu(x, kSlope); }

at::Tensor nearest2x(const at::Tensor& x) {
  return at::upsample_nearest2d(x, {x.size(2) * 2, x.size(3) * 2}, 2.0, 2.0);
}

}  // namespace

RrdbNet RrdbNet::load(sdxl::WeightLoader& w, const RrdbNetConfig& c) {
  RrdbNet net;
  net.config_ = c;
  net.conv_first_ = sdxl::Conv2d::load(w, "conv_first", c.in_channels, c.num_feat, 3);
  net.body_.resize(c.num_block);
  for (int64_t b = 0; b < c.num_block; ++b) {
    for (int r = 0; r < 3; ++r) {
      for (int k = 0; k < 5; ++k) {
        const int64_t in = c.num_feat + k * c.num_grow, out = k < 4 ? c.num_grow : c.num_feat;
        net.body_[b].rdbs[r].convs[k] =
            sdxl::Conv2d::load(w, absl::StrCat("body.", b, ".rdb", r + 1, ".conv", k + 1), in, out, 3);
      }
    }
  }
  net.conv_body_ = sdxl::Conv2d::load(w, "conv_body", c.num_feat, c.num_feat, 3);
  net.conv_up1_ = sdxl::Conv2d::load(w, "conv_up1", c.num_feat, c.num_feat, 3);
  net.conv_up2_ = sdxl::Conv2d::load(w, "conv_up2", c.num_feat, c.num_feat, 3);
  net.conv_hr_ = sdxl::Conv2d::load(w, "conv_hr", c.num_feat, c.num_feat, 3);
  net.conv_last_ = sdxl::Conv2d::load(w, "conv_last", c.num_feat, c.out_channels, 3);
  return net;
}

at::Tensor RrdbNet::dense_block(const DenseBlock& block, const at::Tensor& x) const {
  std::vector<at::Tensor> features = {x};
  for (int k = 0; k < 4; ++k) features.push_back(lrelu(block.convs[k](at::cat(features, 1))));
  return block.convs[4](at::cat(features, 1)) * kResidualScale + x;
}

at::Tensor RrdbNet::operator()(const at::Tensor& x) const {
  const at::Tensor feat = conv_first_(x);
  at::Tensor trunk = feat;
  for (const Rrdb& rrdb : body_) {
    at::Tensor y = trunk;
    for (const DenseBlock& block : rrdb.rdbs) y = dense_block(block, y);
    trunk = y * kResidualScale + trunk;
  }
  at::Tensor out = feat + conv_body_(trunk);
  out = lrelu(conv_up1_(nearest2x(out)));
  out = lrelu(conv_up2_(nearest2x(out)));
  return conv_last_(lrelu(conv_hr_(out)));
}

}  // namespace gaps::restore

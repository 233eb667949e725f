#include "gs_trainer/eval/lpips.h"

#include <ATen/ATen.h>

#include <cstdlib>
#include <map>
#include <set>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/cache_dir.h"
#include "common/safetensors.h"
#include "common/status_macros.h"
#include "common/torch_pickle.h"

namespace gaps {
namespace {

using StateDict = std::map<std::string, at::Tensor>;

// VGG16 `features`: five blocks of 3x3 convolutions (each followed by a ReLU), a 2x2 max-pool
// before blocks 2..5. LPIPS taps the last ReLU of every block.
constexpr int kBlockConvs[5] = {2, 2, 3, 3, 3};
constexpr int64_t kBlockChannels[5] = {64, 128, 256, 512, 512};
constexpr double kShift[3] = {-0.030, -0.088, -0.188};
constexpr double kScale[3] = {0.458, 0.448, 0.450};
constexpr double kNormEps = 1e-10;  // lpips.normalize_tensor
constexpr char kSafetensorsFormat[] = "gaps-lpips-vgg16-v0.1";
constexpr char kMakeWeights[] = "bash scripts/setup.sh (or python3 scripts/lpips_weights.py) makes it";

struct ExpectedTensor {
  std::string key;
  std::vector<int64_t> shape;
};

// torchvision key names: indices count the ReLU and pooling layers too (0, 2, 5, 7, 10, ...).
std::vector<ExpectedTensor> backbone_layout() {
  std::vector<ExpectedTensor> layout;
  int index = 0;
  int64_t in_channels = 3;
  for (int block = 0; block < 5; ++block) {
    if (block > 0) ++index;                                     // max-pool
    for (int i = 0; i < kBlockConvs[block]; ++i, index += 2) {  // conv + ReLU
      const int64_t out_channels = kBlockChannels[block];
      const std::string prefix = absl::StrCat("features.", index);
      layout.push_back({prefix + ".weight", {out_channels, in_channels, 3, 3}});
      layout.push_back({prefix + ".bias", {out_channels}});
      in_channels = out_channels;
    }
  }
  return layout;
}

std::vector<ExpectedTensor> lin_layout() {
  std::vector<ExpectedTensor> layout;
  for (int tap = 0; tap < 5; ++tap) {
    layout.push_back({absl::StrCat("lin", tap, ".model.1.weight"), {1, kBlockChannels[tap], 1, 1}});
  }
  return layout;
}

// Checks `dict` against `layout` (keys with an `ignored_prefix` are skipped) and returns the
// tensors in layout order as float32.
absl::StatusOr<std::vector<at::Tensor>> take_tensors(const StateDict& dict, const std::vector<ExpectedTensor>& layout,
                                                     const std::string& ignored_prefix, const std::string& path) {
  std::set<std::string> expected;
  std::vector<at::Tensor> out;
  for (const ExpectedTensor& e : layout) {
    expected.insert(e.key);
    auto it = dict.find(e.key);
    if (it == dict.end()) {
      return absl::InvalidArgumentError(absl::StrCat("'", path, "': missing key ", e.key));
    }
    const at::Tensor& t = it->second;
    if (t.sizes() != at::IntArrayRef(e.shape)) {
      return absl::InvalidArgumentError(absl::StrCat("'", path, "': key ", e.key, " has shape [",
                                                     absl::StrJoin(t.sizes(), ","), "], expected [",
                                                     absl::StrJoin(e.shape, ","), "]"));
    }
    if (!at::isFloatingType(t.scalar_type())) {
      return absl::InvalidArgumentError(absl::StrCat("'", path, "': key ", e.key, " is not a floating-point tensor"));
    }
    out.push_back(t.to(at::kFloat));
  }
  for (const auto& [key, tensor] : dict) {
    const bool ignored = !ignored_prefix.empty() && key.rfind(ignored_prefix, 0) == 0;
    if (!expected.count(key) && !ignored) {
      return absl::InvalidArgumentError(absl::StrCat("'", path, "': unexpected key ", key));
    }
  }
  return out;
}

// HxWx3 in [0, 1] -> 1x3xHxW scaled as lpips does: [0,1] -> [-1,1], then (x - shift) / scale.
at::Tensor scale_input(const at::Tensor& image) {
  TORCH_CHECK(image.dim() == 3 && image.size(2) == 3, "LPIPS expects HxWx3 images, got ", image.sizes());
  TORCH_CHECK(image.size(0) >= 16 && image.size(1) >= 16, "LPIPS-VGG needs images of at least 16x16 pixels, got ",
              image.sizes());
  at::Tensor x = image.to(at::kFloat).permute({2, 0, 1}).unsqueeze(0) * 2.0 - 1.0;
  const auto options = x.options();
  at::Tensor shift = at::tensor(at::ArrayRef<double>(kShift, 3), options).view({1, 3, 1, 1});
  at::Tensor scale = at::tensor(at::ArrayRef<double>(kScale, 3), options).view({1, 3, 1, 1});
  return (x - shift) / scale;
}

at::Tensor unit_normalise(const at::Tensor& features) {
  at::Tensor norm = features.pow(2).sum(1, /*keepdim=*/true).sqrt();
  return features / (norm + kNormEps);
}

}  // namespace

std::filesystem::path default_lpips_weights_path() {
  const std::filesystem::path cache = gaps_cache_dir();
  return cache.empty() ? cache : cache / "lpips" / "vgg16_lpips_v0.1.safetensors";
}

Lpips Lpips::from_tensors(std::vector<at::Tensor> lins, const std::vector<at::Tensor>& backbone) {
  Lpips lpips;
  lpips.lins_ = std::move(lins);
  for (size_t i = 0; i < backbone.size(); i += 2) {
    lpips.convs_.push_back({backbone[i], backbone[i + 1]});
  }
  return lpips;
}

absl::StatusOr<Lpips> Lpips::load(const std::string& lin_weights_path, const std::string& backbone_path) {
  GAPS_ASSIGN_OR_RETURN(StateDict lin_dict, load_torch_state_dict(lin_weights_path));
  GAPS_ASSIGN_OR_RETURN(std::vector<at::Tensor> lins, take_tensors(lin_dict, lin_layout(), "", lin_weights_path));
  GAPS_ASSIGN_OR_RETURN(StateDict backbone_dict, load_torch_state_dict(backbone_path));
  // The classification head of the full torchvision model plays no part in LPIPS.
  GAPS_ASSIGN_OR_RETURN(std::vector<at::Tensor> backbone,
                        take_tensors(backbone_dict, backbone_layout(), "classifier.", backbone_path));
  return from_tensors(std::move(lins), backbone);
}

absl::StatusOr<Lpips> Lpips::load_safetensors(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat("LPIPS weights '", path, "' not found: ", kMakeWeights));
  }
  GAPS_ASSIGN_OR_RETURN(const sdxl::SafetensorsMetadata metadata, sdxl::read_safetensors_metadata(path));
  const auto format = metadata.find("format");
  if (format == metadata.end() || format->second != kSafetensorsFormat) {
    return absl::InvalidArgumentError(absl::StrCat("'", path, "' is not an LPIPS-VGG weights file (metadata format ",
                                                   format == metadata.end() ? "absent" : format->second, ", expected ",
                                                   kSafetensorsFormat, "): ", kMakeWeights));
  }
  GAPS_ASSIGN_OR_RETURN(const sdxl::TensorMap tensors, sdxl::read_safetensors(path));
  // Each part is checked against its layout; the other part's keys are the only ones allowed beside it.
  GAPS_ASSIGN_OR_RETURN(std::vector<at::Tensor> lins, take_tensors(tensors, lin_layout(), "features.", path));
  GAPS_ASSIGN_OR_RETURN(std::vector<at::Tensor> backbone, take_tensors(tensors, backbone_layout(), "lin", path));
  return from_tensors(std::move(lins), backbone);
}

absl::StatusOr<std::optional<Lpips>> load_lpips(const std::filesystem::path& weights,
                                                const std::filesystem::path& backbone, const c10::Device& device) {
  if (weights.empty()) return std::nullopt;
  absl::StatusOr<Lpips> lpips =
      backbone.empty() ? Lpips::load_safetensors(weights.string()) : Lpips::load(weights.string(), backbone.string());
  if (!lpips.ok()) return lpips.status();
  lpips->to(device);
  return std::optional<Lpips>(std::move(*lpips));
}

void Lpips::to(const c10::Device& device) {
  for (Conv& conv : convs_) {
    conv.weight = conv.weight.to(device);
    conv.bias = conv.bias.to(device);
  }
  for (at::Tensor& lin : lins_) lin = lin.to(device);
}

std::vector<at::Tensor> Lpips::features(const at::Tensor& x, const c10::Device& device) const {
  const std::vector<int64_t> ones = {1, 1};
  const std::vector<int64_t> twos = {2, 2};
  std::vector<at::Tensor> taps;
  at::Tensor h = x;
  size_t conv_index = 0;
  for (int block = 0; block < 5; ++block) {
    if (block > 0) h = at::max_pool2d(h, twos, twos);
    for (int i = 0; i < kBlockConvs[block]; ++i, ++conv_index) {
      const Conv& conv = convs_[conv_index];
      h = at::relu(at::conv2d(h, conv.weight.to(device), conv.bias.to(device), ones, ones));
    }
    taps.push_back(h);
  }
  return taps;
}

at::Tensor Lpips::distance(const at::Tensor& pred, const at::Tensor& gt) const {
  TORCH_CHECK(pred.sizes() == gt.sizes(), "LPIPS inputs differ in shape: ", pred.sizes(), " vs ", gt.sizes());
  TORCH_CHECK(pred.device() == gt.device(), "LPIPS inputs are on different devices");
  const c10::Device device = pred.device();
  // Both images go through VGG as one batch of two.
  at::Tensor batch = at::cat({scale_input(pred), scale_input(gt)}, 0);
  std::vector<at::Tensor> taps = features(batch, device);
  at::Tensor total = at::zeros({}, batch.options());
  for (size_t l = 0; l < taps.size(); ++l) {
    at::Tensor normalised = unit_normalise(taps[l]);
    at::Tensor diff = (normalised[0] - normalised[1]).pow(2).unsqueeze(0);  // 1xCxhxw
    at::Tensor weighted = at::conv2d(diff, lins_[l].to(device));            // 1x1xhxw
    total = total + weighted.mean();
  }
  return total;
}

}  // namespace gaps

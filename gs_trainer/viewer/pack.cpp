#include "gs_trainer/viewer/pack.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <numeric>
#include <vector>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "common/spherical_harmonics.h"

namespace gaps::viewer {
namespace {

static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__, "the viewer's formats are little endian, as this host");

constexpr double kShC0 = 0.28209479177387814;

at::Tensor cpu_float(const at::Tensor& t) { return t.detach().to(at::kCPU, at::kFloat).contiguous(); }

template <typename T>
void append(std::string& out, const T* data, int64_t count) {
  out.append(reinterpret_cast<const char*>(data), static_cast<size_t>(count) * sizeof(T));
}

void append_tensor(std::string& out, const at::Tensor& t) {
  const at::Tensor c = t.contiguous();
  out.append(static_cast<const char*>(c.data_ptr()), c.numel() * c.element_size());
}

uint8_t to_byte(double v) { return static_cast<uint8_t>(std::lround(std::clamp(v, 0.0, 255.0))); }

}  // namespace

int effective_sh_degree(const GaussianModel& model) {
  const at::Tensor rest = cpu_float(model.sh_rest);
  int degree = std::min<int>(model.sh_degree, static_cast<int>(std::lround(std::sqrt(rest.size(1) + 1.0))) - 1);
  for (; degree > 0; --degree) {
    const int64_t first = sh_coefficients(degree - 1) - 1, last = sh_coefficients(degree) - 1;
    if (rest.slice(1, first, last).ne(0).any().item<bool>()) break;
  }
  return std::max(degree, 0);
}

int64_t packed_model_bytes(int64_t count, int sh_degree) {
  return kPackHeaderBytes + count * (4 * (3 + 3 + 4 + 1 + 3) + 2 * 3 * (sh_coefficients(sh_degree) - 1));
}

std::string pack_model(const GaussianModel& model) {
  const int64_t n = model.size();
  const int degree = effective_sh_degree(model);
  std::string out(kPackMagic, 8);
  const uint32_t header[6] = {static_cast<uint32_t>(n), static_cast<uint32_t>(degree), 0, 0, 0, 0};
  append(out, header, 6);
  append_tensor(out, cpu_float(model.means));
  append_tensor(out, cpu_float(model.scales()));
  append_tensor(out, cpu_float(model.quats));
  append_tensor(out, cpu_float(model.opacities()));
  append_tensor(out, cpu_float(model.sh_dc).reshape({n, 3}));
  append_tensor(out, cpu_float(model.sh_rest).slice(1, 0, sh_coefficients(degree) - 1).to(at::kHalf));
  return out;
}

std::string splat_file_bytes(const GaussianModel& model) {
  const int64_t n = model.size();
  const at::Tensor means = cpu_float(model.means), scales = cpu_float(model.scales());
  const at::Tensor quats = cpu_float(model.quats), opacities = cpu_float(model.opacities());
  const at::Tensor dc = cpu_float(model.sh_dc).reshape({n, 3});
  const float* m = means.data_ptr<float>();
  const float* s = scales.data_ptr<float>();
  const float* q = quats.data_ptr<float>();
  const float* o = opacities.data_ptr<float>();
  const float* c = dc.data_ptr<float>();
  std::vector<double> importance(static_cast<size_t>(n));
  for (int64_t i = 0; i < n; ++i)
    importance[i] = static_cast<double>(s[3 * i]) * s[3 * i + 1] * s[3 * i + 2] * static_cast<double>(o[i]);
  std::vector<int64_t> order(static_cast<size_t>(n));
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return importance[a] > importance[b]; });

  std::string out;
  out.reserve(static_cast<size_t>(n * kSplatRecordBytes));
  for (const int64_t i : order) {
    append(out, m + 3 * i, 3);
    append(out, s + 3 * i, 3);
    uint8_t bytes[8];
    for (int k = 0; k < 3; ++k) bytes[k] = to_byte(255.0 * std::clamp(0.5 + kShC0 * c[3 * i + k], 0.0, 1.0));
    bytes[3] = to_byte(255.0 * o[i]);
    const double norm = std::sqrt(double(q[4 * i]) * q[4 * i] + double(q[4 * i + 1]) * q[4 * i + 1] +
                                  double(q[4 * i + 2]) * q[4 * i + 2] + double(q[4 * i + 3]) * q[4 * i + 3]);
    for (int k = 0; k < 4; ++k) bytes[4 + k] = to_byte(norm > 0 ? q[4 * i + k] / norm * 128.0 + 128.0 : 128.0);
    append(out, bytes, 8);
  }
  return out;
}

absl::Status check_splat_bytes(const std::string& bytes, const std::string& where) {
  if (bytes.empty() || bytes.size() % kSplatRecordBytes != 0)
    return absl::InvalidArgumentError(
        absl::StrCat(where, ": ", bytes.size(), " bytes is not a .splat file (32 bytes per Gaussian)"));
  return absl::OkStatus();
}

}  // namespace gaps::viewer

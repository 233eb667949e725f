#include "common/spherical_harmonics.h"

#include <ATen/ATen.h>

namespace gaps {
namespace {

constexpr double kC1 = 0.4886025119029199;
constexpr double kC2[] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                          0.5462742152960396};
constexpr double kC3[] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                          -0.4570457994644658, 1.445305721320277, -0.5900435899266435};

}  // namespace

at::Tensor sh_to_color(int degree, const at::Tensor& sh, const at::Tensor& dirs) {
  TORCH_CHECK(degree >= 0 && degree <= 3, "SH degree must be 0..3, got ", degree);
  TORCH_CHECK(sh.dim() == 3 && sh.size(1) >= sh_coefficients(degree) && sh.size(2) == 3,
              "SH coefficients must be N x K x 3 with K >= ", sh_coefficients(degree), ", got ", sh.sizes());
  auto coef = [&](int k) { return sh.select(1, k); };
  at::Tensor result = kShC0 * coef(0);
  if (degree >= 1) {
    const auto x = dirs.select(1, 0).unsqueeze(1), y = dirs.select(1, 1).unsqueeze(1),
               z = dirs.select(1, 2).unsqueeze(1);
    result = result - kC1 * y * coef(1) + kC1 * z * coef(2) - kC1 * x * coef(3);
    if (degree >= 2) {
      const auto xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
      result = result + kC2[0] * xy * coef(4) + kC2[1] * yz * coef(5) + kC2[2] * (2 * zz - xx - yy) * coef(6) +
               kC2[3] * xz * coef(7) + kC2[4] * (xx - yy) * coef(8);
      if (degree >= 3) {
        result = result + kC3[0] * y * (3 * xx - yy) * coef(9) + kC3[1] * xy * z * coef(10) +
                 kC3[2] * y * (4 * zz - xx - yy) * coef(11) + kC3[3] * z * (2 * zz - 3 * xx - 3 * yy) * coef(12) +
                 kC3[4] * x * (4 * zz - xx - yy) * coef(13) + kC3[5] * z * (xx - yy) * coef(14) +
                 kC3[6] * x * (xx - 3 * yy) * coef(15);
      }
    }
  }
  return at::clamp_min(result + 0.5, 0.0);
}

at::Tensor rgb_to_sh_dc(const at::Tensor& rgb) { return (rgb - 0.5) / kShC0; }
at::Tensor sh_dc_to_rgb(const at::Tensor& dc) { return dc * kShC0 + 0.5; }

}  // namespace gaps

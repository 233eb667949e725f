#pragma once
// Real spherical harmonics up to degree 3, as in 3DGS: colour = SH(dir) + 0.5, clamped at 0.
// Written with ATen operations so autograd differentiates it on every device.
#include <ATen/Tensor.h>

namespace gaps {

constexpr double kShC0 = 0.28209479177387814;

inline int sh_coefficients(int degree) { return (degree + 1) * (degree + 1); }

// sh: N x K x 3 coefficients (K >= (degree+1)^2); dirs: N x 3 unit vectors from the camera to the Gaussians.
at::Tensor sh_to_color(int degree, const at::Tensor& sh, const at::Tensor& dirs);

// Conversions of the constant (DC) term, used for initialisation and PLY files.
at::Tensor rgb_to_sh_dc(const at::Tensor& rgb);
at::Tensor sh_dc_to_rgb(const at::Tensor& dc);

}  // namespace gaps

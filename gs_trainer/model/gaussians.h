#pragma once
// The Gaussian scene model: raw (pre-activation) parameters as in 3DGS, their activations, creation from
// points and the standard 3DGS PLY layout.
#include <filesystem>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "common/ply.h"
#include "gs_trainer/scene/bounds.h"
#include "gs_trainer/scene/camera.h"
#include "gs_trainer/scene/scene.h"

namespace gaps {

struct GaussianModel {
  at::Tensor means;           // N x 3
  at::Tensor log_scales;      // N x 3, scale = exp(log_scale)
  at::Tensor quats;           // N x 4 (w, x, y, z), normalised when used
  at::Tensor opacity_logits;  // N, opacity = sigmoid(logit)
  at::Tensor sh_dc;           // N x 1 x 3
  at::Tensor sh_rest;         // N x (K-1) x 3, K = (max_sh_degree + 1)^2
  int max_sh_degree = 3;
  int sh_degree = 0;  // active degree, raised during training

  int64_t size() const { return means.defined() ? means.size(0) : 0; }
  at::Tensor scales() const;
  at::Tensor opacities() const;
  at::Tensor sh() const;  // N x K x 3

  // The six parameter tensors in a fixed order (means, log_scales, quats, opacity_logits, sh_dc, sh_rest).
  std::vector<at::Tensor*> parameters();
  GaussianModel to(const at::Device& device) const;
};

// 3DGS initialisation: colours to the SH DC term, isotropic scales from the mean squared distance to the
// three nearest neighbours, identity rotations, opacity 0.1.
GaussianModel gaussians_from_points(const PointCloud& points, int max_sh_degree);

// The model with SH degree `degree`: higher bands dropped, missing ones added as zeros (which leaves every
// render unchanged). The active degree is capped at the new one.
GaussianModel with_sh_degree(GaussianModel model, int degree);

// Standard 3DGS PLY: x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3 (binary little endian):
// 62 properties at SH degree 3, 3 (K - 1) f_rest_* at lower degrees, as the reference code (Inria) writes
// them. A PLY holds no active SH degree: a loaded model renders at its full degree, which renders as the
// saved model did whenever the bands above its active degree were never trained (they stay zero).
absl::Status save_gaussians_ply(const GaussianModel& model, const std::filesystem::path& path);
absl::StatusOr<GaussianModel> load_gaussians_ply(const std::filesystem::path& path);

// Whether PLY vertices carry a Gaussian model (opacity, scale_*, rot_* besides positions and colours) rather
// than a plain coloured point cloud (common/ply.h read_point_cloud_ply).
bool holds_gaussians(const PlyVertices& vertices);
// The model of vertices in the layout above; `where` names them in errors (InvalidArgument).
absl::StatusOr<GaussianModel> gaussians_from_ply_vertices(const PlyVertices& vertices, const std::string& where);

}  // namespace gaps

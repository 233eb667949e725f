#include "gs_trainer/model/gaussians.h"

#include <algorithm>
#include <cmath>

#include <ATen/ATen.h>
#include <opencv2/flann.hpp>
#include "absl/strings/str_cat.h"
#include "common/ply.h"
#include "common/spherical_harmonics.h"
#include "common/status_macros.h"

namespace gaps {

at::Tensor GaussianModel::scales() const { return at::exp(log_scales); }
at::Tensor GaussianModel::opacities() const { return at::sigmoid(opacity_logits); }
at::Tensor GaussianModel::sh() const { return at::cat({sh_dc, sh_rest}, 1); }

std::vector<at::Tensor*> GaussianModel::parameters() {
  return {&means, &log_scales, &quats, &opacity_logits, &sh_dc, &sh_rest};
}

GaussianModel GaussianModel::to(const at::Device& device) const {
  GaussianModel m = *this;
  for (at::Tensor* p : m.parameters()) *p = p->to(device).detach().contiguous();
  return m;
}

namespace {

// Mean squared distance to the 3 nearest other points (a k-d tree, as N can be in the millions).
at::Tensor mean_sq_knn_distance(const at::Tensor& xyz) {
  const int64_t n = xyz.size(0);
  if (n < 2) return at::full({n}, 1e-2, at::kFloat);
  cv::Mat pts(static_cast<int>(n), 3, CV_32F);
  std::memcpy(pts.data, xyz.to(at::kFloat).contiguous().data_ptr<float>(), n * 3 * sizeof(float));
  cv::flann::Index index(pts, cv::flann::KDTreeIndexParams(1));
  const int k = static_cast<int>(std::min<int64_t>(4, n));
  cv::Mat indices, dists;
  index.knnSearch(pts, indices, dists, k, cv::flann::SearchParams(64));
  at::Tensor out = at::empty({n}, at::kFloat);
  float* o = out.data_ptr<float>();
  for (int64_t i = 0; i < n; ++i) {
    double sum = 0;
    for (int j = 1; j < k; ++j) sum += dists.at<float>(static_cast<int>(i), j);  // j = 0 is the point itself
    o[i] = static_cast<float>(std::max(sum / (k - 1), 1e-7));
  }
  return out;
}

}  // namespace

GaussianModel gaussians_from_points(const PointCloud& points, int max_sh_degree) {
  const int64_t n = points.xyz.size(0);
  const int k = sh_coefficients(max_sh_degree);
  GaussianModel m;
  m.max_sh_degree = max_sh_degree;
  m.means = points.xyz.to(at::kFloat).contiguous();
  m.log_scales = at::log(at::sqrt(mean_sq_knn_distance(m.means))).unsqueeze(1).repeat({1, 3});
  m.quats = at::zeros({n, 4}, at::kFloat);
  m.quats.select(1, 0).fill_(1.0);
  m.opacity_logits = at::full({n}, std::log(0.1 / 0.9), at::kFloat);
  m.sh_dc = rgb_to_sh_dc(points.rgb.to(at::kFloat)).unsqueeze(1).contiguous();
  m.sh_rest = at::zeros({n, k - 1, 3}, at::kFloat);
  return m;
}

namespace {

std::vector<std::string> ply_names(int rest_coefficients) {
  std::vector<std::string> names = {"x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"};
  for (int i = 0; i < 3 * rest_coefficients; ++i) names.push_back(absl::StrCat("f_rest_", i));
  for (const char* n : {"opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"})
    names.push_back(n);
  return names;
}

}  // namespace

absl::Status save_gaussians_ply(const GaussianModel& model, const std::filesystem::path& path) {
  const GaussianModel m = model.to(at::kCPU);
  const int64_t n = m.size();
  const int rest = static_cast<int>(m.sh_rest.size(1));
  // 3DGS stores the SH rest coefficients channel-major: all of red, then green, then blue.
  const at::Tensor columns =
      at::cat({m.means, at::zeros({n, 3}), m.sh_dc.reshape({n, 3}), m.sh_rest.transpose(1, 2).reshape({n, 3 * rest}),
               m.opacity_logits.unsqueeze(1), m.log_scales, m.quats},
              1);
  return write_ply_vertices(path, ply_names(rest), columns);
}

GaussianModel with_sh_degree(GaussianModel model, int degree) {
  const int64_t rest = sh_coefficients(degree) - 1;
  const int64_t have = model.sh_rest.size(1);
  if (rest < have) {
    model.sh_rest = model.sh_rest.narrow(1, 0, rest).contiguous();
  } else if (rest > have) {
    model.sh_rest = at::cat({model.sh_rest, at::zeros({model.size(), rest - have, 3}, model.sh_rest.options())}, 1);
  }
  model.max_sh_degree = degree;
  model.sh_degree = std::min(model.sh_degree, degree);
  return model;
}

bool holds_gaussians(const PlyVertices& v) {
  for (const char* name : {"opacity", "scale_0", "rot_0"})
    if (!v.has(name)) return false;
  return true;
}

absl::StatusOr<GaussianModel> gaussians_from_ply_vertices(const PlyVertices& v, const std::string& where) {
  int rest_props = 0;
  while (v.has(absl::StrCat("f_rest_", rest_props))) ++rest_props;
  const int rest = rest_props / 3;
  int degree = 0;
  while (sh_coefficients(degree) - 1 < rest) ++degree;
  if (rest_props % 3 != 0 || sh_coefficients(degree) - 1 != rest || degree > 3)
    return absl::InvalidArgumentError(
        absl::StrCat(where, ": ", rest_props, " f_rest_* properties match no SH degree 0..3"));
  for (const auto& name : ply_names(rest))
    if (name[0] != 'n' && !v.has(name))
      return absl::InvalidArgumentError(absl::StrCat(where, ": missing property '", name, "'"));
  auto col = [&](const std::string& name) { return v.properties.at(name); };
  auto stack = [&](std::initializer_list<std::string> names) {
    std::vector<at::Tensor> cols;
    for (const auto& n : names) cols.push_back(col(n));
    return at::stack(cols, 1);
  };
  GaussianModel m;
  m.max_sh_degree = degree;
  m.sh_degree = degree;
  m.means = stack({"x", "y", "z"});
  m.sh_dc = stack({"f_dc_0", "f_dc_1", "f_dc_2"}).unsqueeze(1);
  std::vector<at::Tensor> rest_cols;
  for (int i = 0; i < rest_props; ++i) rest_cols.push_back(col(absl::StrCat("f_rest_", i)));
  m.sh_rest = rest_props ? at::stack(rest_cols, 1).view({v.count, 3, rest}).transpose(1, 2).contiguous()
                         : at::zeros({v.count, 0, 3});
  m.opacity_logits = col("opacity").contiguous();
  m.log_scales = stack({"scale_0", "scale_1", "scale_2"});
  m.quats = stack({"rot_0", "rot_1", "rot_2", "rot_3"});
  for (at::Tensor* p : m.parameters())
    if (!at::isfinite(*p).all().item<bool>())
      return absl::InvalidArgumentError(absl::StrCat(where, ": non-finite Gaussian parameters"));
  return m;
}

absl::StatusOr<GaussianModel> load_gaussians_ply(const std::filesystem::path& path) {
  GAPS_ASSIGN_OR_RETURN(const PlyVertices v, read_ply_vertices(path));
  return gaussians_from_ply_vertices(v, path.string());
}

}  // namespace gaps

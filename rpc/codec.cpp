#include "rpc/codec.h"

#include <cmath>
#include <cstring>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/image_io.h"
#include "common/status_macros.h"
#include "common/tensor_shape.h"
#include "gs_trainer/scene/scene.h"

namespace gaps::rpc {

void encode_raw(const at::Tensor& tensor, v1::Tensor* out) {
  const at::Tensor t = tensor.detach().to(at::kCPU, at::kFloat).contiguous();
  out->set_encoding(v1::Tensor::RAW_F32);
  out->clear_shape();
  for (int64_t d : t.sizes()) out->add_shape(d);
  out->set_data(t.data_ptr(), t.numel() * sizeof(float));
}

absl::Status encode_png(const at::Tensor& image, v1::Tensor* out) {
  GAPS_ASSIGN_OR_RETURN(std::string png, gaps::encode_png(image, "image"));
  out->set_encoding(v1::Tensor::PNG);
  out->clear_shape();
  out->add_shape(image.size(0));
  out->add_shape(image.size(1));
  out->add_shape(3);
  out->set_data(std::move(png));
  return absl::OkStatus();
}

absl::StatusOr<at::Tensor> decode_tensor(const v1::Tensor& tensor, const std::string& what) {
  std::vector<int64_t> shape(tensor.shape().begin(), tensor.shape().end());
  const absl::StatusOr<int64_t> checked = checked_element_count(shape, int64_t{1} << 40);
  if (!checked.ok()) return absl::InvalidArgumentError(absl::StrCat(what, ": ", checked.status().message()));
  switch (tensor.encoding()) {
    case v1::Tensor::RAW_F32: {
      const int64_t count = *checked;
      if (static_cast<uint64_t>(count) * sizeof(float) != tensor.data().size())
        return absl::InvalidArgumentError(absl::StrCat(what, ": shape [", absl::StrJoin(shape, ", "), "] needs ",
                                                       count * sizeof(float), " bytes, got ", tensor.data().size()));
      at::Tensor out = at::empty(shape, at::kFloat);
      // An empty tensor has no storage to copy into (its data pointer may be null).
      if (count > 0) std::memcpy(out.data_ptr(), tensor.data().data(), tensor.data().size());
      return out;
    }
    case v1::Tensor::PNG: {
      GAPS_ASSIGN_OR_RETURN(at::Tensor image, decode_image(tensor.data(), what));
      if (shape.size() >= 2 && (shape[0] != image.size(0) || shape[1] != image.size(1)))
        return absl::InvalidArgumentError(absl::StrCat(what, ": PNG is ", image.size(1), "x", image.size(0),
                                                       " but its shape says ", shape[1], "x", shape[0]));
      return image;
    }
    default:
      return absl::InvalidArgumentError(absl::StrCat(what, ": unknown tensor encoding ", tensor.encoding()));
  }
}

absl::StatusOr<at::Tensor> decode_tensor_shaped(const v1::Tensor& tensor, const std::vector<int64_t>& shape,
                                                const std::string& what) {
  GAPS_ASSIGN_OR_RETURN(at::Tensor t, decode_tensor(tensor, what));
  bool ok = t.dim() == static_cast<int64_t>(shape.size());
  for (size_t i = 0; ok && i < shape.size(); ++i) ok = shape[i] < 0 || shape[i] == t.size(i);
  if (!ok)
    return absl::InvalidArgumentError(absl::StrCat(what, ": expected shape [", absl::StrJoin(shape, ", "),
                                                   "] (-1: any), got [", absl::StrJoin(t.sizes().vec(), ", "), "]"));
  if (!at::isfinite(t).all().item<bool>())
    return absl::InvalidArgumentError(absl::StrCat(what, ": contains NaN or infinite values"));
  return t;
}

void encode_camera(const Camera& c, v1::Camera* out) {
  out->set_name(c.name);
  out->set_width(c.width);
  out->set_height(c.height);
  out->set_fx(c.fx);
  out->set_fy(c.fy);
  out->set_cx(c.cx);
  out->set_cy(c.cy);
  out->clear_rotation();
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) out->add_rotation(c.R(r, k));
  out->clear_translation();
  for (int r = 0; r < 3; ++r) out->add_translation(c.t(r));
  out->set_near(c.near);
  out->set_far(c.far);
}

absl::StatusOr<Camera> decode_camera(const v1::Camera& in, const std::string& what) {
  if (in.rotation_size() != 9 || in.translation_size() != 3)
    return absl::InvalidArgumentError(absl::StrCat(what, ": pose needs 9 rotation and 3 translation values, got ",
                                                   in.rotation_size(), " and ", in.translation_size()));
  for (double v : in.rotation())
    if (!std::isfinite(v))
      return absl::InvalidArgumentError(absl::StrCat(what, ": pose rotation is not finite (NaN or inf)"));
  for (double v : in.translation())
    if (!std::isfinite(v))
      return absl::InvalidArgumentError(absl::StrCat(what, ": pose translation is not finite (NaN or inf)"));
  for (double v : {in.fx(), in.fy(), in.cx(), in.cy(), in.near(), in.far()})
    if (!std::isfinite(v))
      return absl::InvalidArgumentError(absl::StrCat(what, ": intrinsics or bounds are not finite"));
  if (in.width() <= 0 || in.height() <= 0 || in.width() > 65536 || in.height() > 65536)
    return absl::InvalidArgumentError(absl::StrCat(what, ": invalid image size ", in.width(), "x", in.height()));
  if (!(in.fx() > 0 && in.fy() > 0))
    return absl::InvalidArgumentError(absl::StrCat(what, ": focal lengths must be positive"));
  Camera c;
  c.name = in.name();
  c.width = in.width();
  c.height = in.height();
  c.fx = in.fx();
  c.fy = in.fy();
  c.cx = in.cx();
  c.cy = in.cy();
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) c.R(r, k) = in.rotation(r * 3 + k);
    c.t(r) = in.translation(r);
  }
  c.near = in.near();
  c.far = in.far();
  GAPS_RETURN_IF_ERROR(check_camera(c, what));
  return c;
}

grpc::Status to_grpc(const absl::Status& status) {
  if (status.ok()) return grpc::Status::OK;
  return grpc::Status(static_cast<grpc::StatusCode>(status.code()), std::string(status.message()));
}

absl::Status from_grpc(const grpc::Status& status, const std::string& what) {
  if (status.ok()) return absl::OkStatus();
  return absl::Status(static_cast<absl::StatusCode>(status.error_code()),
                      absl::StrCat(what, ": ", status.error_message()));
}

}  // namespace gaps::rpc

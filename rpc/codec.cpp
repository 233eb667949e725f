#include "rpc/codec.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <vector>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/image_io.h"
#include "common/status_macros.h"
#include "common/tensor_shape.h"
#include "gs_trainer/scene/scene.h"
#include "rpc/shared_memory.h"

namespace gaps::rpc {

void encode_raw(const at::Tensor& tensor, v1::Tensor* out) {
  // Float32 into the message fails on nothing.
  encode_tensor(tensor, TensorEncoding::kFloat32, nullptr, "tensor", out).IgnoreError();
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

namespace {

size_t element_bytes(TensorEncoding encoding) {
  switch (encoding) {
    case TensorEncoding::kUint8:
      return 1;
    case TensorEncoding::kFloat16:
      return 2;
    case TensorEncoding::kFloat32:
      break;
  }
  return sizeof(float);
}

}  // namespace

uint64_t encoded_bytes(const at::Tensor& tensor, TensorEncoding encoding) {
  return static_cast<uint64_t>(tensor.numel()) * element_bytes(encoding);
}

namespace {

// The conversions below are plain loops on one thread, not ATen operations, on purpose. The hand-over runs
// beside training; on a busy host ATen's parallel regions wait for descheduled threads and GPU kernels wait for
// the GPU's time slices, and a phase's hand-over of ~57 tensors then took minutes (fern 3 with 30 runs sharing
// an H200: 434 s of encoding per job, against 1 s for a plain device-to-host copy, which uses the copy engine).
bool all_finite(const float* values, int64_t count) {
  bool finite = true;
  for (int64_t i = 0; i < count; ++i) finite &= std::isfinite(values[i]);
  return finite;
}

bool within_half_range(const float* values, int64_t count) {
  bool within = true;
  for (int64_t i = 0; i < count; ++i) within &= std::fabs(values[i]) <= kHalfMax;
  return within;
}

// Rounded to nearest even (c10::Half's conversion, the one at::Tensor::to(kHalf) uses). Converted into an aligned
// buffer, which the loop vectorises, then copied: a payload in a message or a region need not be aligned for it.
void to_halves(const float* values, int64_t count, uint8_t* out) {
  std::vector<uint16_t> halves(count);
  for (int64_t i = 0; i < count; ++i) halves[i] = c10::detail::fp16_ieee_from_fp32_value(values[i]);
  std::memcpy(out, halves.data(), count * sizeof(uint16_t));
}

// Clamped to [0, 1] and rounded half to even, as at::round does: adding and subtracting 1.5 * 2^23 leaves the
// nearest integer (ties to even) in IEEE arithmetic, and unlike std::nearbyint the loop vectorises.
void to_bytes(const float* values, int64_t count, uint8_t* out) {
  constexpr float kRound = 12582912.0f;
  for (int64_t i = 0; i < count; ++i) {
    const float v = std::min(std::max(values[i], 0.0f), 1.0f);
    out[i] = static_cast<uint8_t>((v * 255.0f + kRound) - kRound);
  }
}

}  // namespace

absl::StatusOr<DeferredPayload> lay_out_tensor(const at::Tensor& tensor, TensorEncoding encoding, SharedArena* arena,
                                               const std::string& what, v1::Tensor* out) {
  DeferredPayload payload{tensor.detach(), encoding, nullptr, what};
  if (encoding == TensorEncoding::kFloat16) {
    // Whether it fits half precision decides its size: the values are needed now. One device-to-host copy (the
    // copy engine); the other encodings leave it to fill_payload.
    payload.values = payload.values.to(at::kCPU, at::kFloat).contiguous();
    const float* values = payload.values.data_ptr<float>();
    if (!all_finite(values, payload.values.numel()))
      return absl::InvalidArgumentError(absl::StrCat(what, ": contains NaN or infinite values"));
    if (!within_half_range(values, payload.values.numel())) payload.encoding = TensorEncoding::kFloat32;
  }
  out->set_encoding(to_proto(payload.encoding));
  out->clear_shape();
  for (int64_t d : payload.values.sizes()) out->add_shape(d);
  const uint64_t bytes = encoded_bytes(payload.values, payload.encoding);
  if (arena == nullptr) {
    out->mutable_data()->resize(bytes);
    payload.destination = reinterpret_cast<uint8_t*>(out->mutable_data()->data());
  } else {
    GAPS_ASSIGN_OR_RETURN(const uint64_t offset, arena->allocate(bytes));
    payload.destination = arena->region().data() + offset;
    out->mutable_shared()->set_offset(offset);
    out->mutable_shared()->set_length(bytes);
  }
  return payload;
}

absl::Status fill_payload(const DeferredPayload& payload) {
  // One device-to-host copy (the copy engine), whatever the encoding.
  const at::Tensor t = payload.values.to(at::kCPU, at::kFloat).contiguous();
  const float* values = t.data_ptr<float>();
  const int64_t count = t.numel();
  if (payload.encoding != TensorEncoding::kFloat32 && !all_finite(values, count))
    return absl::InvalidArgumentError(absl::StrCat(payload.what, ": contains NaN or infinite values"));
  if (count == 0) return absl::OkStatus();
  if (payload.encoding == TensorEncoding::kUint8)
    to_bytes(values, count, payload.destination);
  else if (payload.encoding == TensorEncoding::kFloat16)
    to_halves(values, count, payload.destination);
  else
    std::memcpy(payload.destination, values, count * sizeof(float));
  return absl::OkStatus();
}

absl::Status encode_tensor(const at::Tensor& tensor, TensorEncoding encoding, SharedArena* arena,
                           const std::string& what, v1::Tensor* out) {
  GAPS_ASSIGN_OR_RETURN(const DeferredPayload payload, lay_out_tensor(tensor, encoding, arena, what, out));
  return fill_payload(payload);
}

absl::StatusOr<TensorEncoding> tensor_encoding(v1::Tensor::Encoding encoding, const std::string& what) {
  switch (encoding) {
    case v1::Tensor::ENCODING_UNSPECIFIED:
    case v1::Tensor::RAW_F32:
      return TensorEncoding::kFloat32;
    case v1::Tensor::RAW_U8:
      return TensorEncoding::kUint8;
    case v1::Tensor::RAW_F16:
      return TensorEncoding::kFloat16;
    default:
      return absl::InvalidArgumentError(
          absl::StrCat(what, ": encoding ", v1::Tensor::Encoding_Name(encoding), " is not RAW_F32, RAW_U8 or RAW_F16"));
  }
}

v1::Tensor::Encoding to_proto(TensorEncoding encoding) {
  switch (encoding) {
    case TensorEncoding::kUint8:
      return v1::Tensor::RAW_U8;
    case TensorEncoding::kFloat16:
      return v1::Tensor::RAW_F16;
    case TensorEncoding::kFloat32:
      break;
  }
  return v1::Tensor::RAW_F32;
}

namespace {

// The tensor's bytes: its `data`, or its slice of the shared region.
absl::StatusOr<std::string_view> payload(const v1::Tensor& tensor, const std::string& what,
                                         const SharedRegion* region) {
  if (!tensor.has_shared()) return std::string_view(tensor.data());
  if (region == nullptr)
    return absl::InvalidArgumentError(absl::StrCat(what, ": refers to shared memory, but the call has no region"));
  if (!tensor.data().empty())
    return absl::InvalidArgumentError(absl::StrCat(what, ": has both inline data and a shared slice"));
  const v1::SharedSlice& slice = tensor.shared();
  GAPS_RETURN_IF_ERROR(region->check_slice(slice.offset(), slice.length(), what));
  return std::string_view(reinterpret_cast<const char*>(region->data() + slice.offset()), slice.length());
}

absl::StatusOr<at::Tensor> decode_raw(std::string_view bytes, const std::vector<int64_t>& shape, int64_t count,
                                      size_t element_size, const std::string& what) {
  if (static_cast<uint64_t>(count) * element_size != bytes.size())
    return absl::InvalidArgumentError(absl::StrCat(what, ": shape [", absl::StrJoin(shape, ", "), "] needs ",
                                                   count * element_size, " bytes, got ", bytes.size()));
  if (element_size == sizeof(float)) {
    at::Tensor out = at::empty(shape, at::kFloat);
    // An empty tensor has no storage to copy into (its data pointer may be null).
    if (count > 0) std::memcpy(out.data_ptr(), bytes.data(), bytes.size());
    return out;
  }
  at::Tensor out = at::empty(shape, at::kFloat);
  float* values = out.data_ptr<float>();
  if (element_size == sizeof(uint16_t)) {
    std::vector<uint16_t> halves(count);
    if (count > 0) std::memcpy(halves.data(), bytes.data(), bytes.size());
    for (int64_t i = 0; i < count; ++i) values[i] = c10::detail::fp16_ieee_to_fp32_value(halves[i]);
    return out;
  }
  const auto* in = reinterpret_cast<const uint8_t*>(bytes.data());
  // Divided, not multiplied by 1/255: the values an 8-bit image decodes to everywhere else.
  for (int64_t i = 0; i < count; ++i) values[i] = static_cast<float>(in[i]) / 255.0f;
  return out;
}

}  // namespace

absl::StatusOr<at::Tensor> decode_tensor(const v1::Tensor& tensor, const std::string& what,
                                         const SharedRegion* region) {
  std::vector<int64_t> shape(tensor.shape().begin(), tensor.shape().end());
  const absl::StatusOr<int64_t> checked = checked_element_count(shape, int64_t{1} << 40);
  if (!checked.ok()) return absl::InvalidArgumentError(absl::StrCat(what, ": ", checked.status().message()));
  GAPS_ASSIGN_OR_RETURN(const std::string_view bytes, payload(tensor, what, region));
  switch (tensor.encoding()) {
    case v1::Tensor::RAW_F32:
      return decode_raw(bytes, shape, *checked, sizeof(float), what);
    case v1::Tensor::RAW_U8:
      return decode_raw(bytes, shape, *checked, 1, what);
    case v1::Tensor::RAW_F16:
      return decode_raw(bytes, shape, *checked, sizeof(uint16_t), what);
    case v1::Tensor::PNG: {
      GAPS_ASSIGN_OR_RETURN(at::Tensor image, decode_image(std::string(bytes), what));
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
                                                const std::string& what, const SharedRegion* region) {
  GAPS_ASSIGN_OR_RETURN(at::Tensor t, decode_tensor(tensor, what, region));
  bool ok = t.dim() == static_cast<int64_t>(shape.size());
  for (size_t i = 0; ok && i < shape.size(); ++i) ok = shape[i] < 0 || shape[i] == t.size(i);
  if (!ok)
    return absl::InvalidArgumentError(absl::StrCat(what, ": expected shape [", absl::StrJoin(shape, ", "),
                                                   "] (-1: any), got [", absl::StrJoin(t.sizes().vec(), ", "), "]"));
  // Bytes decode to finite values by construction.
  if (tensor.encoding() != v1::Tensor::RAW_U8 && !all_finite(t.contiguous().data_ptr<float>(), t.numel()))
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

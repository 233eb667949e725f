#include "gs_trainer/init/colmap_dense.h"

#include <array>
#include <cstdint>
#include <cstring>
#include <optional>
#include <system_error>
#include <utility>

#include <ATen/ATen.h>
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/colmap.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

// The byte images below are the host's; the formats are little endian, as are the hosts LibTorch supports
// here (x86-64, arm64).
template <typename T>
void append_raw(std::string* out, const T* values, size_t count) {
  out->append(reinterpret_cast<const char*>(values), count * sizeof(T));
}

absl::Status make_dirs(const fs::path& dir) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) return absl::InternalError(absl::StrCat(dir.string(), ": cannot create folder: ", ec.message()));
  return absl::OkStatus();
}

// "<width>&<height>&<channels>&" and the offset of the data after it; nullopt when the text is not that.
std::optional<std::pair<std::array<int64_t, 3>, size_t>> parse_mat_header(const std::string& bytes) {
  std::array<int64_t, 3> dims{};
  size_t pos = 0;
  for (int64_t& d : dims) {
    const size_t amp = bytes.find('&', pos);
    // 20 digits hold any int64; a longer field is not a header.
    if (amp == std::string::npos || amp - pos > 20 || !absl::SimpleAtoi(bytes.substr(pos, amp - pos), &d) || d <= 0)
      return std::nullopt;
    pos = amp + 1;
  }
  return std::make_pair(dims, pos);
}

}  // namespace

absl::Status write_colmap_mat(const fs::path& path, const at::Tensor& map) {
  if (map.dim() != 2 && map.dim() != 3)
    return absl::InvalidArgumentError(absl::StrCat(path.string(), ": a map is HxW or HxWxC, got ", map.dim(), "-d"));
  const at::Tensor hwc = map.dim() == 2 ? map.unsqueeze(2) : map;
  // Channel-major planes, as Mat<float> stores them (see the header).
  const at::Tensor planes = hwc.permute({2, 0, 1}).to(at::kCPU, at::kFloat).contiguous();
  std::string bytes = absl::StrCat(hwc.size(1), "&", hwc.size(0), "&", hwc.size(2), "&");
  append_raw(&bytes, planes.data_ptr<float>(), static_cast<size_t>(planes.numel()));
  return write_file_bytes(path, bytes);
}

absl::StatusOr<at::Tensor> read_colmap_mat(const fs::path& path) {
  GAPS_ASSIGN_OR_RETURN(const std::string bytes, read_file_bytes(path, "COLMAP map"));
  const auto header = parse_mat_header(bytes);
  if (!header)
    return absl::InvalidArgumentError(
        absl::StrCat(path.string(), ": not a COLMAP map (no \"width&height&channels&\" header)"));
  const auto [dims, offset] = *header;
  const auto [width, height, channels] = dims;
  const size_t available = (bytes.size() - offset) / sizeof(float);
  // Compared by division first: the product of three header fields may overflow.
  if (static_cast<uint64_t>(width) > available / static_cast<uint64_t>(height) / static_cast<uint64_t>(channels) ||
      static_cast<size_t>(width * height * channels) != available)
    return absl::InvalidArgumentError(absl::StrCat(path.string(), ": the header says ", width, "x", height, "x",
                                                   channels, " but the file holds ", available, " floats"));
  at::Tensor planes = at::empty({channels, height, width}, at::kFloat);
  std::memcpy(planes.data_ptr<float>(), bytes.data() + offset, available * sizeof(float));
  return channels == 1 ? planes[0] : planes.permute({1, 2, 0}).contiguous();
}

absl::Status write_colmap_fused_ply(const fs::path& path, const PointCloud& points, const at::Tensor& normals) {
  const int64_t n = points.xyz.size(0);
  if (normals.dim() != 2 || normals.size(0) != n || normals.size(1) != 3 || points.rgb.size(0) != n)
    return absl::InvalidArgumentError(absl::StrCat(path.string(), ": ", n, " points but normals ",
                                                   normals.dim() == 2 ? normals.size(0) : -1, " and colours ",
                                                   points.rgb.size(0)));
  const at::Tensor geometry = at::cat({points.xyz, normals}, 1).to(at::kCPU, at::kFloat).contiguous();
  const at::Tensor colour =
      (points.rgb.to(at::kCPU, at::kFloat).clamp(0.0, 1.0) * 255.0).round().to(at::kByte).contiguous();
  std::string bytes =
      absl::StrCat("ply\nformat binary_little_endian 1.0\nelement vertex ", n,
                   "\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\n"
                   "property float nz\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n");
  bytes.reserve(bytes.size() + static_cast<size_t>(n) * (6 * sizeof(float) + 3));
  const float* g = geometry.data_ptr<float>();
  const uint8_t* c = colour.data_ptr<uint8_t>();
  for (int64_t i = 0; i < n; ++i) {
    append_raw(&bytes, g + 6 * i, 6);
    append_raw(&bytes, c + 3 * i, 3);
  }
  return write_file_bytes(path, bytes);
}

std::string dense_image_name(const Camera& camera) {
  return fs::path(camera.name).filename().replace_extension(".png").string();
}

absl::Status write_colmap_dense_workspace(const fs::path& dir, const std::vector<ViewDepthNormal>& maps,
                                          const FusedCloud& fused, const std::optional<PointCloud>& sparse_points) {
  const fs::path depth_dir = dir / "stereo" / "depth_maps", normal_dir = dir / "stereo" / "normal_maps";
  for (const fs::path& d : {dir / "images", dir / "sparse", depth_dir, normal_dir}) GAPS_RETURN_IF_ERROR(make_dirs(d));
  std::vector<Camera> cameras;
  std::string fusion_cfg;
  for (const ViewDepthNormal& m : maps) {
    Camera c = m.camera;
    c.name = dense_image_name(m.camera);
    GAPS_RETURN_IF_ERROR(write_png(dir / "images" / c.name, m.image.to(at::kCPU)));
    GAPS_RETURN_IF_ERROR(write_colmap_mat(depth_dir / (c.name + ".geometric.bin"), m.depth));
    GAPS_RETURN_IF_ERROR(write_colmap_mat(normal_dir / (c.name + ".geometric.bin"), m.normal));
    absl::StrAppend(&fusion_cfg, c.name, "\n");
    cameras.push_back(std::move(c));
  }
  GAPS_RETURN_IF_ERROR(write_file_bytes(dir / "stereo" / "fusion.cfg", fusion_cfg));
  GAPS_RETURN_IF_ERROR(write_colmap_text(dir / "sparse", colmap_from_cameras(cameras, sparse_points)));
  return write_colmap_fused_ply(dir / "fused.ply", fused.points, fused.normals);
}

}  // namespace gaps

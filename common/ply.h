#pragma once
// Minimal PLY reader/writer for vertex elements with scalar properties (binary little endian or ASCII).
#include <filesystem>
#include <map>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "common/point_cloud.h"

namespace gaps {

// Vertex properties by name (order kept in `names`).
struct PlyVertices {
  int64_t count = 0;
  std::vector<std::string> names;
  std::map<std::string, at::Tensor> properties;  // name -> N float32 tensor
  bool has(const std::string& name) const { return properties.count(name) > 0; }
};

absl::StatusOr<PlyVertices> read_ply_vertices(const std::filesystem::path& path);
// Writes float32 properties, one column per name, binary little endian.
absl::Status write_ply_vertices(const std::filesystem::path& path, const std::vector<std::string>& names,
                                const at::Tensor& columns /* N x names.size() float32 */);

// A coloured point cloud from x y z [red green blue | f_dc_*] vertex properties.

absl::StatusOr<PointCloud> read_point_cloud_ply(const std::filesystem::path& path);
absl::Status write_point_cloud_ply(const PointCloud& points, const std::filesystem::path& path);

}  // namespace gaps

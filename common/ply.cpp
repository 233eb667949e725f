#include "common/ply.h"

#include <cstring>
#include <fstream>
#include <sstream>

#include <ATen/ATen.h>
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "common/io_util.h"
#include "common/spherical_harmonics.h"
#include "common/status_macros.h"

namespace gaps {
namespace {

struct PlyProperty {
  std::string name;
  std::string type;
  int size;
};

int type_size(const std::string& type) {
  if (type == "char" || type == "uchar" || type == "int8" || type == "uint8") return 1;
  if (type == "short" || type == "ushort" || type == "int16" || type == "uint16") return 2;
  if (type == "int" || type == "uint" || type == "float" || type == "int32" || type == "uint32" || type == "float32")
    return 4;
  if (type == "double" || type == "float64") return 8;
  return 0;
}

double decode(const char* p, const std::string& type) {
  auto as = [p](auto v) {
    std::memcpy(&v, p, sizeof(v));
    return static_cast<double>(v);
  };
  if (type == "char" || type == "int8") return as(int8_t{});
  if (type == "uchar" || type == "uint8") return as(uint8_t{});
  if (type == "short" || type == "int16") return as(int16_t{});
  if (type == "ushort" || type == "uint16") return as(uint16_t{});
  if (type == "int" || type == "int32") return as(int32_t{});
  if (type == "uint" || type == "uint32") return as(uint32_t{});
  if (type == "float" || type == "float32") return as(float{});
  return as(double{});
}

struct PlyHeader {
  std::string format;
  int64_t vertex_count = 0;
  std::vector<PlyProperty> properties;  // of the vertex element
  bool vertex_first = true;
};

absl::StatusOr<PlyHeader> parse_header(std::istream& in, const std::filesystem::path& path) {
  auto err = [&](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat(path.string(), ": ", what));
  };
  std::string line;
  if (!std::getline(in, line) || line.rfind("ply", 0) != 0) return err("not a PLY file (missing 'ply' magic)");
  PlyHeader h;
  std::string element;
  bool seen_vertex = false;
  while (std::getline(in, line)) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    std::istringstream ls(line);
    std::string word;
    ls >> word;
    if (word == "format") {
      ls >> h.format;
    } else if (word == "element") {
      ls >> element;
      if (element == "vertex") {
        std::string count;
        ls >> count;
        if (!absl::SimpleAtoi(count, &h.vertex_count) || h.vertex_count < 0)
          return err(absl::StrCat("vertex count '", count, "' is not a non-negative integer"));
        seen_vertex = true;
      } else if (!seen_vertex) {
        h.vertex_first = false;
      }
    } else if (word == "property" && element == "vertex") {
      PlyProperty p;
      ls >> p.type;
      if (p.type == "list") return err("list properties on vertices are not supported");
      ls >> p.name;
      p.size = type_size(p.type);
      if (p.size == 0) return err(absl::StrCat("unknown property type '", p.type, "'"));
      h.properties.push_back(p);
    } else if (word == "end_header") {
      if (!seen_vertex) return err("no vertex element");
      if (!h.vertex_first) return err("vertex element must come first");
      // Rows of no bytes cannot be bounded by the file's size (found by fuzz/ply_fuzz.cpp: 6e12 empty rows).
      if (h.properties.empty() && h.vertex_count > 0) return err("the vertex element has no properties");
      if (h.format != "binary_little_endian" && h.format != "ascii")
        return err(absl::StrCat("unsupported PLY format '", h.format, "'"));
      return h;
    }
  }
  return err("header has no end_header");
}

// The header's vertex count against the bytes that follow it, before anything is allocated for them: a
// binary vertex takes its row size, an ASCII value at least one byte.
absl::Status check_count_fits(std::istream& in, const PlyHeader& h, const std::filesystem::path& path) {
  const std::streampos data_start = in.tellg();
  in.seekg(0, std::ios::end);
  const int64_t available = static_cast<int64_t>(in.tellg() - data_start);
  in.seekg(data_start);
  int64_t vertex_bytes = 0;
  for (const auto& p : h.properties) vertex_bytes += h.format == "ascii" ? 1 : p.size;
  if (vertex_bytes > 0 && h.vertex_count > available / vertex_bytes)
    return absl::InvalidArgumentError(absl::StrCat(path.string(), ": the header announces ", h.vertex_count,
                                                   " vertices but the file holds data for at most ",
                                                   available / vertex_bytes));
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<PlyVertices> read_ply_vertices(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat(path.string(), ": cannot open PLY file"));
  GAPS_ASSIGN_OR_RETURN(PlyHeader h, parse_header(in, path));
  const int64_t n = h.vertex_count, np = static_cast<int64_t>(h.properties.size());
  GAPS_RETURN_IF_ERROR(check_count_fits(in, h, path));
  at::Tensor data = at::empty({n, np}, at::kDouble);
  double* out = data.data_ptr<double>();
  if (h.format == "ascii") {
    for (int64_t i = 0; i < n * np; ++i)
      if (!(in >> out[i])) return absl::DataLossError(absl::StrCat(path.string(), ": truncated ASCII vertex data"));
  } else {
    int row_size = 0;
    for (const auto& p : h.properties) row_size += p.size;
    std::vector<char> row(row_size);
    for (int64_t i = 0; i < n; ++i) {
      if (!in.read(row.data(), row_size))
        return absl::DataLossError(absl::StrCat(path.string(), ": truncated: vertex ", i, " of ", n, " missing"));
      int offset = 0;
      for (int64_t j = 0; j < np; ++j) {
        out[i * np + j] = decode(row.data() + offset, h.properties[j].type);
        offset += h.properties[j].size;
      }
    }
  }
  PlyVertices v;
  v.count = n;
  for (int64_t j = 0; j < np; ++j) {
    v.names.push_back(h.properties[j].name);
    v.properties[h.properties[j].name] = data.select(1, j).to(at::kFloat).contiguous();
  }
  return v;
}

absl::Status write_ply_vertices(const std::filesystem::path& path, const std::vector<std::string>& names,
                                const at::Tensor& columns) {
  TORCH_CHECK(columns.dim() == 2 && columns.size(1) == static_cast<int64_t>(names.size()), "PLY columns must be N x ",
              names.size());
  const auto data = columns.to(at::kCPU, at::kFloat).contiguous();
  return write_file_atomically(path, [&](std::ostream& out) {
    out << "ply\nformat binary_little_endian 1.0\nelement vertex " << data.size(0) << "\n";
    for (const auto& n : names) out << "property float " << n << "\n";
    out << "end_header\n";
    out.write(reinterpret_cast<const char*>(data.data_ptr<float>()), data.numel() * sizeof(float));
  });
}

absl::StatusOr<PointCloud> read_point_cloud_ply(const std::filesystem::path& path) {
  GAPS_ASSIGN_OR_RETURN(PlyVertices v, read_ply_vertices(path));
  for (const char* k : {"x", "y", "z"})
    if (!v.has(k)) return absl::InvalidArgumentError(absl::StrCat(path.string(), ": no '", k, "' property"));
  PointCloud pc;
  pc.xyz = at::stack({v.properties["x"], v.properties["y"], v.properties["z"]}, 1);
  if (v.has("red") && v.has("green") && v.has("blue")) {
    pc.rgb = at::stack({v.properties["red"], v.properties["green"], v.properties["blue"]}, 1) / 255.0;
  } else if (v.has("f_dc_0") && v.has("f_dc_1") && v.has("f_dc_2")) {
    pc.rgb = sh_dc_to_rgb(at::stack({v.properties["f_dc_0"], v.properties["f_dc_1"], v.properties["f_dc_2"]}, 1))
                 .clamp(0.0, 1.0);
  } else {
    pc.rgb = at::full({v.count, 3}, 0.5, at::kFloat);
  }
  GAPS_RETURN_IF_ERROR(check_point_cloud(pc, path.string()));
  return pc;
}

absl::Status write_point_cloud_ply(const PointCloud& points, const std::filesystem::path& path) {
  // Colours as float 0..255 under the usual names, which viewers and our reader both accept.
  return write_ply_vertices(path, {"x", "y", "z", "red", "green", "blue"},
                            at::cat({points.xyz.to(at::kFloat), points.rgb.to(at::kFloat) * 255.0}, 1));
}

}  // namespace gaps

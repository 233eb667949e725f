#include "common/npy.h"

#include <algorithm>
#include <cstring>
#include <limits>
#include <sstream>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "common/tensor_shape.h"

namespace gaps {
namespace {

constexpr absl::string_view kMagic = "\x93NUMPY";

struct Dtype {
  char kind = 0;  // 'f', 'i', 'u' or 'b'
  int size = 0;   // bytes per element
};

absl::Status npy_error(absl::string_view name, absl::string_view problem) {
  return absl::InvalidArgumentError(absl::StrCat(name, ": ", problem));
}

absl::string_view trim_left(absl::string_view s) {
  while (!s.empty() && (s.front() == ' ' || s.front() == '\t')) s.remove_prefix(1);
  return s;
}

// The header is a Python dict literal written by numpy, e.g.
// {'descr': '<f8', 'fortran_order': False, 'shape': (20, 17), }. Returns the text after "'key':".
absl::StatusOr<absl::string_view> dict_value(absl::string_view header, absl::string_view key) {
  for (char quote : {'\'', '"'}) {
    const std::string quoted = absl::StrCat(std::string(1, quote), key, std::string(1, quote));
    const size_t at = header.find(quoted);
    if (at == absl::string_view::npos) continue;
    absl::string_view rest = trim_left(header.substr(at + quoted.size()));
    if (rest.empty() || rest.front() != ':') break;
    return trim_left(rest.substr(1));
  }
  return absl::InvalidArgumentError(absl::StrCat("header has no '", key, "' entry"));
}

absl::StatusOr<Dtype> parse_descr(absl::string_view value) {
  if (!value.empty() && value.front() == '[') return absl::InvalidArgumentError("structured dtypes are not supported");
  if (value.size() < 2 || (value.front() != '\'' && value.front() != '"'))
    return absl::InvalidArgumentError("malformed 'descr'");
  const size_t end = value.find(value.front(), 1);
  if (end == absl::string_view::npos) return absl::InvalidArgumentError("malformed 'descr'");
  const absl::string_view descr = value.substr(1, end - 1);
  if (descr.size() < 3) return absl::InvalidArgumentError(absl::StrCat("unsupported dtype '", descr, "'"));
  Dtype dtype{descr[1], descr[2] - '0'};
  const bool one_byte = descr.size() == 3 && dtype.size == 1;
  if (descr[0] == '>' && !one_byte)
    return absl::InvalidArgumentError(absl::StrCat("big-endian dtype '", descr, "' is not supported"));
  const bool known_order = descr[0] == '<' || descr[0] == '|' || descr[0] == '=' || descr[0] == '>';
  const bool known_size =
      descr.size() == 3 && (dtype.size == 1 || dtype.size == 2 || dtype.size == 4 || dtype.size == 8);
  const bool float_ok = dtype.kind == 'f' && (dtype.size == 4 || dtype.size == 8);
  const bool int_ok = dtype.kind == 'i' || dtype.kind == 'u' || (dtype.kind == 'b' && dtype.size == 1);
  if (!known_order || !known_size || !(float_ok || int_ok))
    return absl::InvalidArgumentError(absl::StrCat("unsupported dtype '", descr, "'"));
  return dtype;
}

absl::StatusOr<std::vector<int64_t>> parse_shape(absl::string_view value) {
  if (value.empty() || value.front() != '(') return absl::InvalidArgumentError("malformed 'shape'");
  const size_t close = value.find(')');
  if (close == absl::string_view::npos) return absl::InvalidArgumentError("malformed 'shape'");
  std::vector<int64_t> shape;
  std::istringstream in{std::string(value.substr(1, close - 1))};
  std::string item;
  while (std::getline(in, item, ',')) {
    absl::string_view s = trim_left(item);
    while (!s.empty() && s.back() == ' ') s.remove_suffix(1);
    if (s.empty()) continue;  // the trailing comma of "(5,)"
    int64_t n = 0;
    for (char c : s) {
      if (c < '0' || c > '9' || n > std::numeric_limits<int64_t>::max() / 16)
        return absl::InvalidArgumentError(absl::StrCat("malformed 'shape' entry '", s, "'"));
      n = n * 10 + (c - '0');
    }
    shape.push_back(n);
  }
  return shape;
}

template <typename T>
void convert(const char* src, int64_t count, double* dst) {
  for (int64_t i = 0; i < count; ++i) {
    T v;
    std::memcpy(&v, src + i * sizeof(T), sizeof(T));
    dst[i] = static_cast<double>(v);
  }
}

void convert_elements(const Dtype& dtype, const char* src, int64_t count, double* dst) {
  switch (dtype.kind * 16 + dtype.size) {
    case 'f' * 16 + 4:
      return convert<float>(src, count, dst);
    case 'f' * 16 + 8:
      return convert<double>(src, count, dst);
    case 'i' * 16 + 1:
      return convert<int8_t>(src, count, dst);
    case 'i' * 16 + 2:
      return convert<int16_t>(src, count, dst);
    case 'i' * 16 + 4:
      return convert<int32_t>(src, count, dst);
    case 'i' * 16 + 8:
      return convert<int64_t>(src, count, dst);
    case 'u' * 16 + 2:
      return convert<uint16_t>(src, count, dst);
    case 'u' * 16 + 4:
      return convert<uint32_t>(src, count, dst);
    case 'u' * 16 + 8:
      return convert<uint64_t>(src, count, dst);
    default:
      return convert<uint8_t>(src, count, dst);  // u1 and b1
  }
}

// Splits the file into its header text and payload, checking magic and version.
absl::Status split_header(absl::string_view bytes, absl::string_view name, absl::string_view* header,
                          absl::string_view* payload) {
  if (bytes.size() < 10 || bytes.substr(0, kMagic.size()) != kMagic)
    return npy_error(name, "not a .npy file (bad magic)");
  const int major = static_cast<unsigned char>(bytes[6]);
  if (major < 1 || major > 3) return npy_error(name, absl::StrCat("unsupported .npy version ", major));
  const size_t len_bytes = major == 1 ? 2 : 4;
  if (bytes.size() < 8 + len_bytes) return npy_error(name, "truncated header");
  size_t header_len = 0;
  for (size_t i = 0; i < len_bytes; ++i) header_len |= size_t{static_cast<unsigned char>(bytes[8 + i])} << (8 * i);
  const size_t start = 8 + len_bytes;
  if (bytes.size() < start + header_len) return npy_error(name, "truncated header");
  *header = bytes.substr(start, header_len);
  *payload = bytes.substr(start + header_len);
  return absl::OkStatus();
}

absl::StatusOr<NpyArray> parse_header_and_data(absl::string_view header, absl::string_view payload) {
  NpyArray array;
  GAPS_ASSIGN_OR_RETURN(absl::string_view descr_text, dict_value(header, "descr"));
  GAPS_ASSIGN_OR_RETURN(Dtype dtype, parse_descr(descr_text));
  array.descr = std::string(descr_text.substr(1, descr_text.find(descr_text.front(), 1) - 1));
  GAPS_ASSIGN_OR_RETURN(absl::string_view fortran, dict_value(header, "fortran_order"));
  if (fortran.substr(0, 4) == "True")
    return absl::InvalidArgumentError("fortran_order arrays are not supported (save with C order)");
  if (fortran.substr(0, 5) != "False") return absl::InvalidArgumentError("malformed 'fortran_order'");
  GAPS_ASSIGN_OR_RETURN(absl::string_view shape_text, dict_value(header, "shape"));
  GAPS_ASSIGN_OR_RETURN(array.shape, parse_shape(shape_text));
  GAPS_ASSIGN_OR_RETURN(const int64_t count,
                        checked_element_count(array.shape, std::numeric_limits<int64_t>::max() / 16));
  const uint64_t expected = static_cast<uint64_t>(count) * dtype.size;
  if (payload.size() != expected)
    return absl::InvalidArgumentError(absl::StrCat("data has ", payload.size(), " bytes but shape (",
                                                   absl::StrJoin(array.shape, ", "), ") of '", array.descr, "' needs ",
                                                   expected));
  array.data = at::empty(array.shape, at::kDouble);
  convert_elements(dtype, payload.data(), count, array.data.data_ptr<double>());
  return array;
}

std::string npy_header(const std::string& descr, const std::vector<int64_t>& shape) {
  std::string dims = absl::StrJoin(shape, ", ");
  if (shape.size() == 1) dims += ",";
  std::string header = absl::StrCat("{'descr': '", descr, "', 'fortran_order': False, 'shape': (", dims, "), }");
  // numpy pads so the payload starts on a 64-byte boundary, ending the header with a newline.
  const size_t total = kMagic.size() + 4 + header.size() + 1;
  header.append((64 - total % 64) % 64, ' ');
  header += '\n';
  return header;
}

}  // namespace

absl::StatusOr<NpyArray> parse_npy(absl::string_view bytes, absl::string_view name) {
  absl::string_view header, payload;
  GAPS_RETURN_IF_ERROR(split_header(bytes, name, &header, &payload));
  absl::StatusOr<NpyArray> array = parse_header_and_data(header, payload);
  if (!array.ok()) return npy_error(name, array.status().message());
  return array;
}

absl::StatusOr<NpyArray> read_npy(const std::filesystem::path& path) {
  GAPS_ASSIGN_OR_RETURN(const std::string bytes, read_file_bytes(path, "npy file"));
  return parse_npy(bytes, path.string());
}

absl::Status write_npy(const std::filesystem::path& path, const at::Tensor& array) {
  const bool single = array.scalar_type() == at::kFloat;
  const at::Tensor data = array.to(at::kCPU, single ? at::kFloat : at::kDouble).contiguous();
  const std::string header = npy_header(single ? "<f4" : "<f8", data.sizes().vec());
  const uint16_t len = static_cast<uint16_t>(header.size());
  std::string bytes(kMagic);
  bytes += {1, 0, static_cast<char>(len & 0xff), static_cast<char>(len >> 8)};
  bytes += header;
  bytes.append(static_cast<const char*>(data.data_ptr()), data.numel() * data.element_size());
  return write_file_bytes(path, bytes);
}

}  // namespace gaps

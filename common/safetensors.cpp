#include "common/safetensors.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <fstream>
#include <memory>
#include <utility>
#include <vector>

#include <ATen/ATen.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"

namespace gaps::sdxl {
namespace {

struct Mapping {
  void* data = nullptr;
  size_t size = 0;
  ~Mapping() {
    if (data != nullptr) munmap(data, size);
  }
};

struct DtypeInfo {
  const char* name;
  at::ScalarType type;
};
constexpr DtypeInfo kDtypes[] = {{"F32", at::kFloat}, {"F16", at::kHalf}, {"BF16", at::kBFloat16}, {"F64", at::kDouble},
                                 {"I64", at::kLong},  {"I32", at::kInt},  {"I16", at::kShort},     {"I8", at::kChar},
                                 {"U8", at::kByte},   {"BOOL", at::kBool}};

bool dtype_from_name(const std::string& name, at::ScalarType* type) {
  for (const auto& d : kDtypes) {
    if (name == d.name) {
      *type = d.type;
      return true;
    }
  }
  return false;
}

const char* dtype_name(at::ScalarType type) {
  for (const auto& d : kDtypes) {
    if (d.type == type) return d.name;
  }
  return nullptr;
}

absl::Status header_error(const std::string& path, const std::string& what) {
  return absl::InvalidArgumentError(absl::StrCat("safetensors file ", path, ": ", what));
}

// The header of the safetensors data at bytes[0, size), checked to be a JSON object within it.
absl::StatusOr<nlohmann::json> parse_header(const uint8_t* bytes, size_t size, const std::string& path,
                                            uint64_t* header_size) {
  if (size < 8) return header_error(path, absl::StrCat("only ", size, " bytes, shorter than the 8-byte header length"));
  *header_size = 0;
  for (int i = 7; i >= 0; --i) *header_size = (*header_size << 8) | bytes[i];
  if (*header_size > size - 8)
    return header_error(path, absl::StrCat("header length ", *header_size, " exceeds the file (", size, " bytes)"));
  nlohmann::json header;
  try {
    header = nlohmann::json::parse(bytes + 8, bytes + 8 + *header_size);
  } catch (const std::exception& e) {
    return header_error(path, absl::StrCat("header is not valid JSON: ", e.what()));
  }
  if (!header.is_object()) return header_error(path, "header is not a JSON object");
  return header;
}

absl::StatusOr<SafetensorsMetadata> metadata_of(const nlohmann::json& header, const std::string& path) {
  SafetensorsMetadata metadata;
  if (!header.is_object() || !header.contains("__metadata__")) return metadata;
  const auto& entries = header["__metadata__"];
  if (!entries.is_object()) return header_error(path, "__metadata__ is not a JSON object");
  for (const auto& [key, value] : entries.items()) {
    if (!value.is_string()) return header_error(path, absl::StrCat("__metadata__ entry '", key, "' is not a string"));
    metadata.emplace(key, value.get<std::string>());
  }
  return metadata;
}

// The tensors of the safetensors data at bytes[0, size), viewing it; `owner` keeps it alive as long as any does.
absl::StatusOr<TensorMap> tensors_of(uint8_t* bytes, size_t size, const std::shared_ptr<void>& owner,
                                     const std::string& path) {
  uint64_t header_size = 0;
  GAPS_ASSIGN_OR_RETURN(const nlohmann::json header, parse_header(bytes, size, path, &header_size));
  uint8_t* base = bytes + 8 + header_size;
  const uint64_t data_size = size - 8 - header_size;

  TensorMap tensors;
  std::vector<std::pair<uint64_t, uint64_t>> ranges;
  for (const auto& item : header.items()) {
    // Named, not a structured binding: the lambda below captures it (C++17 forbids capturing bindings).
    const std::string& name = item.key();
    const nlohmann::json& entry = item.value();
    if (name == "__metadata__") continue;
    const auto fail = [&](const std::string& what) {
      return header_error(path, absl::StrCat("tensor '", name, "': ", what));
    };
    if (!entry.is_object() || !entry.contains("dtype") || !entry.contains("shape") || !entry.contains("data_offsets")) {
      return fail("entry needs dtype, shape and data_offsets");
    }
    at::ScalarType type;
    if (!entry["dtype"].is_string() || !dtype_from_name(entry["dtype"].get<std::string>(), &type)) {
      return fail(absl::StrCat("unsupported dtype ", entry["dtype"].dump()));
    }
    std::vector<int64_t> shape;
    uint64_t numel = 1;
    for (const auto& d : entry["shape"]) {
      if (!d.is_number_integer() || d.get<int64_t>() < 0) return fail("shape must hold non-negative integers");
      shape.push_back(d.get<int64_t>());
      numel *= static_cast<uint64_t>(shape.back());
    }
    const auto& offsets = entry["data_offsets"];
    if (!offsets.is_array() || offsets.size() != 2 || !offsets[0].is_number_unsigned() ||
        !offsets[1].is_number_unsigned()) {
      return fail("data_offsets must be two non-negative integers");
    }
    const uint64_t begin = offsets[0].get<uint64_t>(), end = offsets[1].get<uint64_t>();
    if (begin > end || end > data_size) {
      return fail(
          absl::StrCat("data_offsets [", begin, ", ", end, ") outside the data section (", data_size, " bytes)"));
    }
    const uint64_t expected = numel * at::elementSize(type);
    if (end - begin != expected) {
      return fail(absl::StrCat("holds ", end - begin, " bytes but its shape and dtype need ", expected));
    }
    ranges.emplace_back(begin, end);
    void* ptr = base + begin;
    at::Tensor t;
    if (reinterpret_cast<uintptr_t>(ptr) % at::elementSize(type) == 0) {
      t = at::from_blob(
          ptr, shape, [owner](void*) {}, at::TensorOptions().dtype(type));
    } else {
      // Misaligned data (a writer that does not pad the header) is copied rather than viewed.
      t = at::empty(shape, at::TensorOptions().dtype(type));
      std::memcpy(t.data_ptr(), ptr, expected);
    }
    tensors.emplace(name, std::move(t));
  }
  std::sort(ranges.begin(), ranges.end());
  for (size_t i = 1; i < ranges.size(); ++i) {
    if (ranges[i].first < ranges[i - 1].second && ranges[i].first != ranges[i].second) {
      return header_error(path, "tensors overlap in the data section");
    }
  }
  return tensors;
}

// The 8-byte length and the header (padded so that the data stays 8-byte aligned) of `tensors`, whose data,
// contiguous on the CPU, goes to *data in header order.
absl::StatusOr<std::string> header_bytes(const TensorMap& tensors, const SafetensorsMetadata& metadata,
                                         std::vector<at::Tensor>* data) {
  nlohmann::json header = nlohmann::json::object();
  if (!metadata.empty()) header["__metadata__"] = metadata;
  uint64_t offset = 0;
  for (const auto& [name, tensor] : tensors) {
    const char* dtype = dtype_name(tensor.scalar_type());
    if (dtype == nullptr)
      return absl::InvalidArgumentError(absl::StrCat("tensor '", name, "': dtype not writable as safetensors"));
    at::Tensor t = tensor.to(at::kCPU).contiguous();
    const uint64_t size = t.numel() * t.element_size();
    header[name] = {{"dtype", dtype}, {"shape", t.sizes().vec()}, {"data_offsets", {offset, offset + size}}};
    offset += size;
    data->push_back(std::move(t));
  }
  std::string text = header.dump();
  text.append((8 - text.size() % 8) % 8, ' ');
  std::string out(8, '\0');
  for (int i = 0; i < 8; ++i) out[i] = static_cast<char>((text.size() >> (8 * i)) & 0xff);
  return out + text;
}

}  // namespace

absl::StatusOr<TensorMap> read_safetensors(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY);
  if (fd < 0)
    return absl::NotFoundError(absl::StrCat("cannot open safetensors file ", path, ": ", std::strerror(errno)));
  struct stat st {};
  if (fstat(fd, &st) != 0) {
    ::close(fd);
    return absl::InternalError(absl::StrCat("cannot stat ", path));
  }
  auto mapping = std::make_shared<Mapping>();
  mapping->size = static_cast<size_t>(st.st_size);
  if (mapping->size < 8) {
    ::close(fd);
    return header_error(path, absl::StrCat("only ", mapping->size, " bytes, shorter than the 8-byte header length"));
  }
  // Copy-on-write private mapping: the tensors may be written to without touching the file.
  void* data = mmap(nullptr, mapping->size, PROT_READ | PROT_WRITE, MAP_PRIVATE, fd, 0);
  ::close(fd);
  if (data == MAP_FAILED) return absl::InternalError(absl::StrCat("cannot map ", path, ": ", std::strerror(errno)));
  mapping->data = data;
  return tensors_of(static_cast<uint8_t*>(data), mapping->size, mapping, path);
}

absl::StatusOr<DecodedSafetensors> decode_safetensors(std::string bytes, const std::string& source) {
  auto owner = std::make_shared<std::string>(std::move(bytes));
  auto* data = reinterpret_cast<uint8_t*>(owner->data());
  DecodedSafetensors decoded;
  GAPS_ASSIGN_OR_RETURN(decoded.tensors, tensors_of(data, owner->size(), owner, source));
  uint64_t header_size = 0;
  GAPS_ASSIGN_OR_RETURN(const nlohmann::json header, parse_header(data, owner->size(), source, &header_size));
  GAPS_ASSIGN_OR_RETURN(decoded.metadata, metadata_of(header, source));
  return decoded;
}

absl::StatusOr<std::string> encode_safetensors(const TensorMap& tensors, const SafetensorsMetadata& metadata) {
  std::vector<at::Tensor> data;
  GAPS_ASSIGN_OR_RETURN(std::string out, header_bytes(tensors, metadata, &data));
  for (const auto& t : data) out.append(static_cast<const char*>(t.const_data_ptr()), t.numel() * t.element_size());
  return out;
}

absl::StatusOr<SafetensorsMetadata> read_safetensors_metadata(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot open safetensors file ", path));
  unsigned char len[8] = {};
  if (!in.read(reinterpret_cast<char*>(len), 8)) return header_error(path, "shorter than the 8-byte header length");
  uint64_t header_size = 0;
  for (int i = 7; i >= 0; --i) header_size = (header_size << 8) | len[i];
  in.seekg(0, std::ios::end);
  const uint64_t file_size = static_cast<uint64_t>(in.tellg());
  if (header_size > file_size - 8)
    return header_error(path, absl::StrCat("header length ", header_size, " exceeds the file"));
  std::string text(header_size, '\0');
  in.seekg(8);
  if (!in.read(text.data(), static_cast<std::streamsize>(header_size)))
    return header_error(path, "cannot read the header");
  nlohmann::json header;
  try {
    header = nlohmann::json::parse(text);
  } catch (const std::exception& e) {
    return header_error(path, absl::StrCat("header is not valid JSON: ", e.what()));
  }
  return metadata_of(header, path);
}

absl::Status write_safetensors(const std::string& path, const TensorMap& tensors, const SafetensorsMetadata& metadata) {
  std::vector<at::Tensor> data;
  GAPS_ASSIGN_OR_RETURN(const std::string header, header_bytes(tensors, metadata, &data));
  // Streamed tensor by tensor: a whole model's weights are not held twice.
  std::ofstream out(path, std::ios::binary);
  if (!out) return absl::InternalError(absl::StrCat("cannot write ", path));
  out.write(header.data(), static_cast<std::streamsize>(header.size()));
  for (const auto& t : data) out.write(static_cast<const char*>(t.const_data_ptr()), t.numel() * t.element_size());
  if (!out) return absl::InternalError(absl::StrCat("failed writing ", path));
  return absl::OkStatus();
}

}  // namespace gaps::sdxl

#include "common/image_io.h"

#include <algorithm>
#include <csetjmp>
#include <cstdio>
#include <limits>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <jpeglib.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/io_util.h"
#include "common/status_macros.h"

// stb (PNG only; JPEG is libjpeg-turbo's) is compiled here with internal linkage, so no other library that bundles its
// own copy (or Debian's libstb.so, absent on the GPU machines) can clash with or be required for these symbols.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wunused-function"
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"
#define STB_IMAGE_STATIC
#define STB_IMAGE_IMPLEMENTATION
#define STBI_ONLY_PNG
#include <stb/stb_image.h>
#define STB_IMAGE_WRITE_STATIC
#define STB_IMAGE_WRITE_IMPLEMENTATION
#include <stb/stb_image_write.h>
#pragma GCC diagnostic pop

namespace gaps {
namespace {

namespace fs = std::filesystem;

absl::Status corrupt(const fs::path& path) {
  return absl::DataLossError(
      absl::StrCat(path.string(), ": not a readable PNG/JPEG image (", stbi_failure_reason(), ")"));
}

// stb hands back interleaved pixels with 1 (grey), 2 (grey+alpha), 3 (RGB) or 4 (RGBA) channels.
template <typename T>
at::Tensor to_rgb_float(const T* pixels, int width, int height, int channels, float scale) {
  at::Tensor image = at::empty({height, width, 3}, at::kFloat);
  float* out = image.data_ptr<float>();
  const int64_t count = int64_t{width} * height;
  for (int64_t i = 0; i < count; ++i) {
    const T* p = pixels + i * channels;
    const bool grey = channels < 3;
    for (int c = 0; c < 3; ++c) out[i * 3 + c] = static_cast<float>(p[grey ? 0 : c]) * scale;
  }
  return image;
}

// From the header, before a pixel is decoded: a small file can announce a huge image (a decompression bomb).
absl::Status check_image_size(const std::string& what, int width, int height) {
  if (width <= 0 || height <= 0)
    return absl::InvalidArgumentError(absl::StrCat(what, ": image of ", width, "x", height, " pixels"));
  if (int64_t{width} * height > kMaxImagePixels)
    return absl::InvalidArgumentError(
        absl::StrCat(what, ": image of ", width, "x", height, " pixels (", int64_t{width} * height / 1000000,
                     " megapixels) is over the limit of ", kMaxImagePixels / 1000000, " megapixels"));
  return absl::OkStatus();
}

struct ImageHeader {
  int width = 0, height = 0, channels = 0;
};

// A PNG's size from its IHDR chunk (always first, at a fixed offset), read before stb sees the file: stb
// refuses a header whose pixels would pass 1 GiB with a generic "unknown image type", which hides the
// real reason (the size) from the user.
bool png_header_size(const std::string& bytes, int* width, int* height) {
  static constexpr char kSignature[] = "\x89PNG\r\n\x1a\n";
  if (bytes.size() < 24 || bytes.compare(0, 8, kSignature, 8) != 0 || bytes.compare(12, 4, "IHDR") != 0) return false;
  const auto be32 = [&](size_t at) {
    uint32_t v = 0;
    for (size_t i = 0; i < 4; ++i) v = (v << 8) | static_cast<uint8_t>(bytes[at + i]);
    return v;
  };
  const uint32_t w = be32(16), h = be32(20);
  if (w > static_cast<uint32_t>(std::numeric_limits<int>::max()) ||
      h > static_cast<uint32_t>(std::numeric_limits<int>::max()))
    return false;
  *width = static_cast<int>(w);
  *height = static_cast<int>(h);
  return true;
}

bool is_jpeg(const std::string& bytes) {
  return bytes.size() >= 2 && static_cast<uint8_t>(bytes[0]) == 0xFF && static_cast<uint8_t>(bytes[1]) == 0xD8;
}

// JPEG goes through libjpeg-turbo, not stb_image: the stb of Debian builds a Huffman table from a DHT
// segment's code counts without checking that they fit it, so a crafted file writes past the table (found
// by fuzz/image_fuzz.cpp). libjpeg reports errors through a longjmp; nothing with a destructor lives
// between the setjmp and the calls that may jump.
struct JpegErrors {
  jpeg_error_mgr manager;
  jmp_buf jump;
  char message[JMSG_LENGTH_MAX];
};

void jpeg_fail(j_common_ptr info) {
  auto* errors = reinterpret_cast<JpegErrors*>(info->err);
  (*info->err->format_message)(info, errors->message);
  longjmp(errors->jump, 1);
}

void jpeg_quiet(j_common_ptr, int) {}  // warnings (e.g. extraneous bytes) do not stop a decode

// The header, and with `rgb` the pixels as 8-bit RGB (`rgb` must hold width * height * 3 bytes: call once
// without it for the size). `message` receives libjpeg's reason on failure.
bool jpeg_read(const std::string& bytes, ImageHeader* header, uint8_t* rgb, char* message) {
  jpeg_decompress_struct info;
  JpegErrors errors;
  info.err = jpeg_std_error(&errors.manager);
  errors.manager.error_exit = jpeg_fail;
  errors.manager.emit_message = jpeg_quiet;
  if (setjmp(errors.jump)) {
    std::snprintf(message, JMSG_LENGTH_MAX, "%s", errors.message);
    jpeg_destroy_decompress(&info);
    return false;
  }
  jpeg_create_decompress(&info);
  jpeg_mem_src(&info, reinterpret_cast<const unsigned char*>(bytes.data()), static_cast<unsigned long>(bytes.size()));
  jpeg_read_header(&info, TRUE);
  header->width = static_cast<int>(info.image_width);
  header->height = static_cast<int>(info.image_height);
  header->channels = info.num_components;
  if (rgb != nullptr) {
    info.out_color_space = JCS_RGB;
    jpeg_start_decompress(&info);
    while (info.output_scanline < info.output_height) {
      JSAMPROW row = rgb + static_cast<size_t>(info.output_scanline) * info.output_width * 3;
      jpeg_read_scanlines(&info, &row, 1);
    }
    jpeg_finish_decompress(&info);
  }
  jpeg_destroy_decompress(&info);
  return true;
}

absl::StatusOr<ImageHeader> read_header(const fs::path& path, const std::string& bytes) {
  // stb and libjpeg take an int / long length; a larger file cannot be an image we would accept anyway.
  if (bytes.size() > static_cast<size_t>(std::numeric_limits<int>::max()))
    return absl::InvalidArgumentError(
        absl::StrCat(path.string(), ": ", bytes.size(), " bytes is too large an image file"));
  ImageHeader h;
  if (png_header_size(bytes, &h.width, &h.height))
    GAPS_RETURN_IF_ERROR(check_image_size(path.string(), h.width, h.height));
  if (is_jpeg(bytes)) {
    char message[JMSG_LENGTH_MAX] = {0};
    if (!jpeg_read(bytes, &h, nullptr, message))
      return absl::DataLossError(absl::StrCat(path.string(), ": not a readable JPEG image (", message, ")"));
  } else if (!stbi_info_from_memory(reinterpret_cast<const stbi_uc*>(bytes.data()), static_cast<int>(bytes.size()),
                                    &h.width, &h.height, &h.channels)) {
    return corrupt(path);
  }
  GAPS_RETURN_IF_ERROR(check_image_size(path.string(), h.width, h.height));
  return h;
}

absl::StatusOr<at::Tensor> decode_jpeg(const fs::path& path, const std::string& bytes, ImageHeader header) {
  std::vector<uint8_t> rgb(static_cast<size_t>(header.width) * header.height * 3);
  char message[JMSG_LENGTH_MAX] = {0};
  if (!jpeg_read(bytes, &header, rgb.data(), message))
    return absl::DataLossError(absl::StrCat(path.string(), ": not a readable JPEG image (", message, ")"));
  return to_rgb_float(rgb.data(), header.width, header.height, 3, 1.0f / 255.0f);
}

absl::StatusOr<at::Tensor> decode(const fs::path& path, const std::string& bytes) {
  GAPS_ASSIGN_OR_RETURN(const ImageHeader header, read_header(path, bytes));
  if (is_jpeg(bytes)) return decode_jpeg(path, bytes, header);
  const auto* data = reinterpret_cast<const stbi_uc*>(bytes.data());
  const int size = static_cast<int>(bytes.size());
  int width = header.width, height = header.height, channels = header.channels;
  if (channels < 1 || channels > 4)
    return absl::InvalidArgumentError(absl::StrCat(path.string(), ": unsupported channel count ", channels));
  at::Tensor image;
  if (stbi_is_16_bit_from_memory(data, size)) {
    stbi_us* pixels = stbi_load_16_from_memory(data, size, &width, &height, &channels, 0);
    if (pixels == nullptr) return corrupt(path);
    image = to_rgb_float(pixels, width, height, channels, 1.0f / 65535.0f);
    stbi_image_free(pixels);
  } else {
    stbi_uc* pixels = stbi_load_from_memory(data, size, &width, &height, &channels, 0);
    if (pixels == nullptr) return corrupt(path);
    image = to_rgb_float(pixels, width, height, channels, 1.0f / 255.0f);
    stbi_image_free(pixels);
  }
  return image;
}

void append_bytes(void* context, void* data, int size) {
  static_cast<std::string*>(context)->append(static_cast<const char*>(data), size);
}

}  // namespace

absl::StatusOr<at::Tensor> read_image(const fs::path& path) {
  absl::StatusOr<std::string> bytes = read_file_bytes(path, "image file");
  if (!bytes.ok()) return bytes.status();
  return decode(path, *bytes);
}

absl::StatusOr<std::pair<int, int>> read_image_size(const fs::path& path) {
  // The whole file, not stb's file reader: the header checks (read_header) need the bytes.
  GAPS_ASSIGN_OR_RETURN(const std::string bytes, read_file_bytes(path, "image file"));
  GAPS_ASSIGN_OR_RETURN(const ImageHeader header, read_header(path, bytes));
  return std::make_pair(header.width, header.height);
}

absl::StatusOr<std::string> encode_png(const at::Tensor& image, const std::string& what) {
  const bool shape_ok = image.dim() == 3 && (image.size(2) == 3 || image.size(2) == 1);
  if (!shape_ok)
    return absl::InvalidArgumentError(absl::StrCat(what, ": PNG encoding needs an HxWx3 or HxWx1 image, got shape [",
                                                   absl::StrJoin(image.sizes().vec(), ", "), "]"));
  const at::Tensor bytes = image.detach()
                               .to(at::kCPU, at::kFloat)
                               .nan_to_num(0.0)
                               .clamp(0.0, 1.0)
                               .mul(255.0f)
                               .round()
                               .to(at::kByte)
                               .contiguous();
  const int height = static_cast<int>(image.size(0)), width = static_cast<int>(image.size(1));
  const int channels = static_cast<int>(image.size(2));
  std::string png;
  if (!stbi_write_png_to_func(append_bytes, &png, width, height, channels, bytes.data_ptr<uint8_t>(), width * channels))
    return absl::InternalError(absl::StrCat(what, ": PNG encoding failed"));
  return png;
}

absl::Status write_png(const fs::path& path, const at::Tensor& image) {
  absl::StatusOr<std::string> png = encode_png(image, path.string());
  if (!png.ok()) return png.status();
  return write_file_bytes(path, *png);
}

absl::Status write_pngs(const std::vector<std::pair<fs::path, at::Tensor>>& images) {
  std::vector<absl::Status> written(images.size());
  at::parallel_for(0, static_cast<int64_t>(images.size()), 1, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) written[i] = write_png(images[i].first, images[i].second);
  });
  for (const absl::Status& st : written)
    if (!st.ok()) return st;
  return absl::OkStatus();
}

absl::StatusOr<at::Tensor> decode_image(const std::string& bytes, const std::string& what) {
  return decode(what, bytes);
}

absl::StatusOr<std::pair<int, int>> decode_image_size(const std::string& bytes, const std::string& what) {
  GAPS_ASSIGN_OR_RETURN(const ImageHeader header, read_header(what, bytes));
  return std::make_pair(header.width, header.height);
}

at::Tensor resize_image(const at::Tensor& image, int width, int height) {
  const at::Tensor src = image.to(at::kCPU, at::kFloat).contiguous();
  const int channels = static_cast<int>(src.size(2));
  if (src.size(0) == height && src.size(1) == width) return src.clone();
  const cv::Mat in(static_cast<int>(src.size(0)), static_cast<int>(src.size(1)), CV_32FC(channels),
                   src.data_ptr<float>());
  at::Tensor dst = at::empty({height, width, channels}, at::kFloat);
  cv::Mat out(height, width, CV_32FC(channels), dst.data_ptr<float>());
  cv::resize(in, out, out.size(), 0, 0, cv::INTER_AREA);
  return dst;
}

}  // namespace gaps

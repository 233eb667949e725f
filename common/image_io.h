#pragma once
// Image files <-> float tensors. Decoding/encoding uses stb (no OpenCV imgcodecs needed).
// Images in memory are HxWx3 float32 CPU tensors with values in [0, 1].
#include <cstdint>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"

namespace gaps {

// The largest image decoded, checked from the file's header before any pixel is: 100 megapixels (1.2 GB as
// float RGB), far above what few-view reconstruction trains on (LLFF and Mip-NeRF 360 at -r 8 are under 0.4).
inline constexpr int64_t kMaxImagePixels = 100'000'000;

// PNG or JPEG (8 or 16 bit, grey/RGB/RGBA; alpha is dropped). Errors name the file.
absl::StatusOr<at::Tensor> read_image(const std::filesystem::path& path);
// Width and height from the file header without decoding the pixels.
absl::StatusOr<std::pair<int, int>> read_image_size(const std::filesystem::path& path);
// 8-bit PNG; values are clamped to [0, 1]. Accepts HxWx3 or HxWx1 (grey).
absl::Status write_png(const std::filesystem::path& path, const at::Tensor& image);
// write_png for each (path, image), encoded in parallel (PNG compression dominates: a diffusion phase saves
// 16-24 pseudo-views at once); every file is attempted, the first error returned.
absl::Status write_pngs(const std::vector<std::pair<std::filesystem::path, at::Tensor>>& images);
// In-memory counterparts of read_image and write_png (for images travelling over the network); `what`
// names the image in errors.
absl::StatusOr<std::string> encode_png(const at::Tensor& image, const std::string& what);
absl::StatusOr<at::Tensor> decode_image(const std::string& bytes, const std::string& what);
// (width, height) from the header alone, checked as decode_image checks it; `what` names the image.
absl::StatusOr<std::pair<int, int>> decode_image_size(const std::string& bytes, const std::string& what);
// Area-averaging resize (exact box filter for integer factors), as used to build images_N folders.
at::Tensor resize_image(const at::Tensor& image, int width, int height);

}  // namespace gaps

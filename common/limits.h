#pragma once
// Upper bounds on what a request, a flag or an option can make gaps allocate, in one place. Each is a memory
// budget divided by what one unit costs, and is checked before anything is allocated, with a message that
// names the field, the value and the limit (check_limit). Decoded images have their own bound beside their
// reader (kMaxImagePixels in common/image_io.h).
#include <cstdint>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace gaps {

// A Gaussian's parameters (59 floats), their gradients, Adam's two moments and the densification statistics:
// about 1 KiB. A model, and so an initial point cloud, may take 64 GiB (more than a 24 GB card and most hosts
// hold: the bound stops the absurd, the machine's own memory stops the merely large).
inline constexpr int64_t kBytesPerGaussian = 1024;
inline constexpr int64_t kMaxModelBytes = int64_t{64} << 30;
inline constexpr int64_t kMaxGaussians = kMaxModelBytes / kBytesPerGaussian;  // 67,108,864

// A render keeps about 30 bytes per pixel alive (colour, depth, alpha, the per-pixel lists' heads); one render
// of a finished model may take 512 MiB: 4096 x 4096 pixels, 4K UHD frames with room to spare.
inline constexpr int64_t kBytesPerRenderedPixel = 32;
inline constexpr int64_t kMaxRenderBytes = int64_t{512} << 20;
inline constexpr int64_t kMaxRenderPixels = kMaxRenderBytes / kBytesPerRenderedPixel;  // 16,777,216

// Requests a trainer serves at once, beyond which it answers RESOURCE_EXHAUSTED and asks to retry: renders of
// finished models (each up to kMaxRenderBytes) and open WatchJob streams (a thread each).
inline constexpr int kMaxConcurrentRenders = 4;
inline constexpr int kMaxWatchStreams = 64;

// `what` (a flag or field name as the user wrote it) must be in [1, limit]; `why` says where the limit comes from.
inline absl::Status check_limit(const std::string& what, int64_t value, int64_t limit, const std::string& why) {
  if (value >= 1 && value <= limit) return absl::OkStatus();
  if (value < 1) return absl::InvalidArgumentError(absl::StrCat(what, " ", value, " must be at least 1"));
  return absl::InvalidArgumentError(absl::StrCat(what, " ", value, " is over the limit of ", limit, " (", why, ")"));
}

inline absl::Status check_gaussian_count(const std::string& what, int64_t value) {
  return check_limit(what, value, kMaxGaussians, "64 GiB of model at 1 KiB per Gaussian");
}

inline absl::Status check_render_size(const std::string& what, int64_t width, int64_t height) {
  if (width >= 1 && height >= 1 && width <= kMaxRenderPixels / height) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrCat(what, " ", width, "x", height, " is over the limit of ",
                                                 kMaxRenderPixels,
                                                 " pixels per render (4096x4096; 512 MiB at 32 "
                                                 "bytes per pixel)"));
}

}  // namespace gaps

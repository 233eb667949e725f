// PatchMatch's steps on the host: rows in parallel, each pixel through the same function the kernels call.
#include <cstdint>

#include <ATen/Parallel.h>

#include "gs_trainer/init/patchmatch_backend.h"

namespace gaps::pm {
namespace {

constexpr int kAllPixels = -1;

// f(x, y) for every pixel of `colour` (kAllPixels: every pixel). Pixels of one colour read only pixels of the
// other, so the order among them does not matter.
template <typename F>
void for_each_pixel(const Problem& p, int colour, const F& f) {
  at::parallel_for(0, p.cam.height, 1, [&](int64_t y0, int64_t y1) {
    for (int y = static_cast<int>(y0); y < y1; ++y) {
      const int step = colour == kAllPixels ? 1 : 2;
      for (int x = colour == kAllPixels ? 0 : ((y + colour) & 1); x < p.cam.width; x += step) f(x, y);
    }
  });
}

void init_cpu(const Problem& p) {
  for_each_pixel(p, kAllPixels, [&](int x, int y) { init_pixel(p, x, y); });
}

void update_cpu(const Problem& p, int colour, int iteration) {
  for_each_pixel(p, colour, [&](int x, int y) { update_pixel(p, x, y, iteration); });
}

void rescore_cpu(const Problem& p) {
  for_each_pixel(p, kAllPixels, [&](int x, int y) { rescore_pixel(p, x, y); });
}

void filter_cpu(const Problem& p) {
  for_each_pixel(p, kAllPixels, [&](int x, int y) { filter_pixel(p, x, y); });
}

}  // namespace

const Backend kCpuBackend{init_cpu, update_cpu, rescore_cpu, filter_cpu};

}  // namespace gaps::pm

#pragma once
// Dynamic scheduling for the CPU rasterizer: tiles differ in cost by orders of magnitude, so threads
// take the next tile from a shared counter instead of a static half of the image each.
#include <atomic>
#include <cstdint>

#include <ATen/Parallel.h>

namespace gaps::backend {

template <typename F>
void parallel_for_each_dynamic(int64_t count, const F& body) {
  std::atomic<int64_t> next{0};
  const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), count));
  at::parallel_for(0, workers, 1, [&](int64_t, int64_t) {
    for (int64_t i = next.fetch_add(1); i < count; i = next.fetch_add(1)) body(i);
  });
}

}  // namespace gaps::backend

// A run on CUDA reports its peak memory from the caching allocator (on the CPU, run_monitoring_test.cpp
// checks the resident-set figure).
#include <cstdint>
#include <string>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "gs_trainer/pipeline.h"
#include "tests/gpu/require_cuda.h"
#include "tests/run_monitoring_test_util.h"

namespace gaps {
namespace {

using test::RunMonitoring;

TEST_F(RunMonitoring, PeakMemoryOnCudaComesFromTheCachingAllocator) {
  GAPS_REQUIRE_CUDA();
  RunOptions o = options();
  o.config.device = "cuda";
  o.html_report = false;
  auto r = run_pipeline(o, nullptr, [](const std::string&) {});
  ASSERT_TRUE(r.ok()) << r.status();
  const auto m = test::read_json(o.out_dir / "metrics.json");
  EXPECT_EQ(m["peak_memory"]["kind"], "cuda_allocator");
  // At least the 2,000 initial Gaussians' parameters (59 floats each) were on the device at once.
  EXPECT_GT(m["peak_memory"]["bytes"].get<int64_t>(), 2000 * 59 * 4);
  EXPECT_GE(m["peak_memory"]["reserved_bytes"].get<int64_t>(), m["peak_memory"]["bytes"].get<int64_t>());
  EXPECT_EQ(m["curve"].size(), 3u);
}

}  // namespace
}  // namespace gaps

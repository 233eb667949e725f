// PLY files (--init-ply, uploaded point clouds, trained models) through the point cloud reader.
#include "common/ply.h"
#include "fuzz/fuzz_support.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto path = gaps::fuzz::write_scratch("input.ply", gaps::fuzz::as_bytes(data, size));
  (void)gaps::read_point_cloud_ply(path);
  return 0;
}

// COLMAP's binary model files. The first byte picks the file (cameras, images, points3D); the rest is it.
#include "fuzz/fuzz_support.h"
#include "gs_trainer/scene/colmap.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  const auto path = gaps::fuzz::write_scratch("model.bin", gaps::fuzz::as_bytes(data + 1, size - 1));
  switch (data[0] % 3) {
    case 0:
      (void)gaps::read_colmap_cameras_bin(path);
      break;
    case 1:
      (void)gaps::read_colmap_images_bin(path);
      break;
    default:
      (void)gaps::read_colmap_points_bin(path);
  }
  return 0;
}

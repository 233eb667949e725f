// An LLFF poses_bounds.npy beside three small images (images/000.png ...), loaded as a scene.
#include "fuzz/fuzz_support.h"
#include "gs_trainer/scene/scene.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const auto root = gaps::fuzz::scene_with_images("llff_scene", 3, 8, 6);
  gaps::fuzz::write_scratch("llff_scene/poses_bounds.npy", gaps::fuzz::as_bytes(data, size));
  const auto scene = gaps::load_llff_scene(root);
  if (scene.ok() && !scene->cameras.empty()) (void)gaps::load_camera_image(scene->cameras[0]);
  return 0;
}

// A NeRF-style transforms.json beside three small images (images/000.png ...), loaded as a scene.
#include "fuzz/fuzz_support.h"
#include "gs_trainer/scene/scene.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const auto root = gaps::fuzz::scene_with_images("transforms_scene", 3, 8, 6);
  gaps::fuzz::write_scratch("transforms_scene/transforms.json", gaps::fuzz::as_bytes(data, size));
  const auto scene = gaps::load_transforms_scene(root);
  if (scene.ok() && !scene->cameras.empty()) (void)gaps::load_camera_image(scene->cameras[0]);
  return 0;
}

// What a trainer decodes from a client before rendering a finished job (RenderViewRequest: the render-size
// bound first, then the camera), and what `gaps render --job` decodes from the trainer's answer to GetJobCameras
// (JobCameras: the cameras and depth bounds of the path). The first byte picks. A camera that decodes must be
// within the render bound and encode and decode again to itself.
#include "common/limits.h"
#include "fuzz/fuzz_support.h"
#include "rpc/codec.h"

namespace {

void round_trip(const gaps::Camera& camera) {
  gaps::v1::Camera again;
  gaps::rpc::encode_camera(camera, &again);
  const auto back = gaps::rpc::decode_camera(again, "camera");
  if (!back.ok() || back->width != camera.width || back->height != camera.height || back->fx != camera.fx ||
      back->near != camera.near || back->far != camera.far || !back->R.isApprox(camera.R, 0.0))
    __builtin_trap();
}

void render_view(const uint8_t* data, size_t size) {
  gaps::v1::RenderViewRequest request;
  if (!request.ParseFromArray(data, static_cast<int>(size))) return;
  const gaps::v1::Camera& c = request.camera();
  if (!gaps::check_render_size("camera", c.width(), c.height()).ok()) return;
  const auto camera = gaps::rpc::decode_camera(c, "camera");
  if (!camera.ok()) return;
  if (int64_t{camera->width} * camera->height > gaps::kMaxRenderPixels) __builtin_trap();
  round_trip(*camera);
}

void job_cameras(const uint8_t* data, size_t size) {
  gaps::v1::JobCameras cameras;
  if (!cameras.ParseFromArray(data, static_cast<int>(size))) return;
  for (const auto* list : {&cameras.train(), &cameras.test()})
    for (const gaps::v1::Camera& c : *list) {
      const auto camera = gaps::rpc::decode_camera(c, "camera");
      if (camera.ok()) round_trip(*camera);
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  if (data[0] % 2 == 0)
    render_view(data + 1, size - 1);
  else
    job_cameras(data + 1, size - 1);
  return 0;
}

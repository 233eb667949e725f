#pragma once
// A scene uploaded through SubmitJob: checked, then written as a transforms.json scene the pipeline loads
// (images/ as uploaded, camera-to-world matrices in the OpenGL convention, per-frame intrinsics) plus the
// optional initial point cloud. Every problem is INVALID_ARGUMENT naming the image or camera at fault.
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "gaps/v1/trainer.pb.h"

namespace gaps {

struct SceneUpload {
  v1::JobSpec spec;
  std::vector<std::string> images;  // encoded PNG/JPEG bytes, one per camera
  std::string points_ply;           // empty unless spec.has_points
};

// Checks the upload against itself and the spec's config (camera/image counts, decodable images of the
// cameras' sizes, finite poses with proper rotations, unique plain file names, a readable point cloud, a
// config the pipeline accepts and a view count the split can provide), then writes it to `scene_dir`.
absl::Status write_uploaded_scene(const SceneUpload& upload, const std::filesystem::path& scene_dir);

// Reads the per-file chunks of SubmitJob into `upload` (after the spec). `max_bytes` bounds the total.
class UploadAssembler {
 public:
  UploadAssembler(SceneUpload* upload, uint64_t max_bytes) : upload_(upload), max_bytes_(max_bytes) {}
  absl::Status add(const v1::FileChunk& chunk);
  // Checks every announced file arrived complete.
  absl::Status finish() const;

 private:
  SceneUpload* upload_;
  uint64_t max_bytes_;
  uint64_t received_ = 0;
  int complete_images_ = 0;
  bool points_complete_ = false;
};

}  // namespace gaps

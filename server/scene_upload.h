#pragma once
// A scene uploaded through SubmitJob: streamed to files as it arrives, checked, then written as a
// transforms.json scene the pipeline loads.
#include <cstdint>
#include <filesystem>
#include <functional>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "gaps/v1/trainer.pb.h"

namespace gaps {

// A scene as SubmitJob delivers it: the spec, and the files its chunks carried, already on disk in
// `dir`/upload (so an upload never sits in memory whole): image_<i> and larger_<i> for camera i, points.ply.
struct SceneUpload {
  v1::JobSpec spec;
  std::filesystem::path dir;
  int images = 0;                  // how many arrived complete
  std::vector<int> larger_images;  // the cameras whose larger view (FileChunk::LARGER_IMAGE) arrived complete
  std::filesystem::path image_file(int index) const;
  std::filesystem::path larger_image_file(int index) const;
  std::filesystem::path points_file() const;
};

// The folder of a written scene that holds the uploaded larger views, under the cameras' image names
// (RunOptions::larger_views_dir).
inline constexpr char kLargerViewsFolder[] = "larger_images";

// Reads SubmitJob's messages from `next` (false at the end of the stream): the JobSpec first, then file
// chunks in order, each appended to its file under `dir`/upload as it arrives. `max_bytes` bounds the
// files' total. Errors: INVALID_ARGUMENT for a malformed stream, RESOURCE_EXHAUSTED over the limit.
using UploadMessageSource = std::function<bool(v1::SubmitJobRequest*)>;
absl::StatusOr<SceneUpload> receive_upload(const UploadMessageSource& next, uint64_t max_bytes,
                                           const std::filesystem::path& dir);

// Checks the received upload against itself and the spec's config (camera/image counts, decodable images
// of the cameras' sizes, finite poses with proper rotations, unique plain file names, a readable point
// cloud, a config the pipeline accepts and a view count the split can provide), then makes `dir` the
// transforms.json scene the pipeline loads (images/ as uploaded, camera-to-world matrices in the OpenGL
// convention, per-frame intrinsics, points.ply, the larger views in kLargerViewsFolder, each checked to be
// twice its camera's size within a pixel) and removes upload/. Every problem is INVALID_ARGUMENT naming the
// image or camera at fault.
absl::Status write_uploaded_scene(const SceneUpload& upload);

}  // namespace gaps

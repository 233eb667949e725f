#include "server/scene_upload.h"

#include <set>

#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/ply.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/scene.h"
#include "rpc/codec.h"
#include "server/job_config.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

absl::Status invalid(const absl::Status& status) {
  if (status.ok()) return status;
  return absl::InvalidArgumentError(status.message());
}

bool plain_file_name(const std::string& name) {
  return !name.empty() && name != "." && name != ".." && name.find('/') == std::string::npos &&
         name.find('\\') == std::string::npos && name.find('\0') == std::string::npos;
}

nlohmann::json frame_json(const Camera& c, const std::string& file) {
  // OpenCV world-to-camera -> OpenGL camera-to-world (y and z axes flipped).
  Eigen::Matrix3d c2w = c.R.transpose();
  c2w.col(1) *= -1.0;
  c2w.col(2) *= -1.0;
  const Eigen::Vector3d centre = c.center();
  nlohmann::json m = nlohmann::json::array();
  for (int r = 0; r < 3; ++r) m.push_back({c2w(r, 0), c2w(r, 1), c2w(r, 2), centre(r)});
  m.push_back({0.0, 0.0, 0.0, 1.0});
  return {{"file_path", file}, {"transform_matrix", m}, {"fl_x", c.fx}, {"fl_y", c.fy}, {"cx", c.cx},
          {"cy", c.cy},        {"w", c.width},          {"h", c.height}};
}

}  // namespace

absl::Status write_uploaded_scene(const SceneUpload& upload, const fs::path& scene_dir) {
  const v1::JobSpec& spec = upload.spec;
  const int cameras = spec.cameras_size(), images = static_cast<int>(upload.images.size());
  if (cameras == 0) return absl::InvalidArgumentError("the upload has no cameras");
  if (cameras != images)
    return absl::InvalidArgumentError(
        absl::StrCat("camera count mismatch: ", cameras, " cameras for ", images, " images"));
  GAPS_RETURN_IF_ERROR(invalid(run_options_from_proto(spec.config(), spec.has_points(), "", "").status()));
  if (auto split = benchmark_split(cameras, spec.config().views()); !split.ok())
    return absl::InvalidArgumentError(
        absl::StrCat("config: views ", spec.config().views(), ": ", split.status().message()));

  std::vector<Camera> decoded;
  std::set<std::string> names;
  for (int i = 0; i < cameras; ++i) {
    const std::string what = absl::StrCat("camera ", i, " (", spec.cameras(i).name(), ")");
    GAPS_ASSIGN_OR_RETURN(Camera camera, rpc::decode_camera(spec.cameras(i), what));
    if (!plain_file_name(camera.name))
      return absl::InvalidArgumentError(absl::StrCat(what, ": image name must be a plain file name"));
    if (!names.insert(camera.name).second)
      return absl::InvalidArgumentError(absl::StrCat(what, ": duplicate image name"));
    const std::string image_what = absl::StrCat("image ", i, " (", camera.name, ")");
    absl::StatusOr<at::Tensor> decoded_image = decode_image(upload.images[i], image_what);
    if (!decoded_image.ok()) return invalid(decoded_image.status());
    const at::Tensor& image = *decoded_image;
    if (image.size(0) != camera.height || image.size(1) != camera.width)
      return absl::InvalidArgumentError(absl::StrCat(image_what, ": image is ", image.size(1), "x", image.size(0),
                                                     " but its camera says ", camera.width, "x", camera.height));
    decoded.push_back(std::move(camera));
  }

  fs::create_directories(scene_dir / "images");
  nlohmann::json frames = nlohmann::json::array();
  for (int i = 0; i < cameras; ++i) {
    const std::string file = "images/" + decoded[i].name;
    GAPS_RETURN_IF_ERROR(write_file_bytes(scene_dir / file, upload.images[i]));
    frames.push_back(frame_json(decoded[i], file));
  }
  if (spec.has_points()) {
    const fs::path ply = scene_dir / "points.ply";
    GAPS_RETURN_IF_ERROR(write_file_bytes(ply, upload.points_ply));
    // The reader names the file it read; the client knows it as the uploaded point cloud, not by our path.
    if (auto points = read_point_cloud_ply(ply); !points.ok())
      return absl::InvalidArgumentError(absl::StrCat(
          "uploaded point cloud: ", absl::StrReplaceAll(points.status().message(), {{ply.string() + ": ", ""}})));
  }
  const std::string doc = nlohmann::json{{"camera_model", "PINHOLE"}, {"frames", frames}}.dump(2);
  return write_file_bytes(scene_dir / "transforms.json", doc);
}

absl::Status UploadAssembler::add(const v1::FileChunk& chunk) {
  received_ += chunk.data().size();
  if (received_ > max_bytes_)
    return absl::ResourceExhaustedError(absl::StrCat("upload exceeds the limit of ", max_bytes_, " bytes"));
  const v1::JobSpec& spec = upload_->spec;
  switch (chunk.kind()) {
    case v1::FileChunk::IMAGE: {
      if (chunk.index() != complete_images_)
        return absl::InvalidArgumentError(absl::StrCat("image chunk for index ", chunk.index(), " while image ",
                                                       complete_images_, " is expected (images arrive in order)"));
      if (chunk.index() >= spec.cameras_size())
        return absl::InvalidArgumentError(absl::StrCat("camera count mismatch: image ", chunk.index(),
                                                       " has no camera (", spec.cameras_size(), " cameras)"));
      if (static_cast<int>(upload_->images.size()) <= chunk.index()) upload_->images.emplace_back();
      upload_->images[chunk.index()] += chunk.data();
      if (chunk.last()) ++complete_images_;
      return absl::OkStatus();
    }
    case v1::FileChunk::POINTS:
      if (!spec.has_points()) return absl::InvalidArgumentError("point cloud sent but the spec announced none");
      if (points_complete_) return absl::InvalidArgumentError("point cloud sent twice");
      upload_->points_ply += chunk.data();
      points_complete_ = chunk.last();
      return absl::OkStatus();
    default:
      return absl::InvalidArgumentError(absl::StrCat("file chunk of unknown kind ", chunk.kind()));
  }
}

absl::Status UploadAssembler::finish() const {
  if (complete_images_ != static_cast<int>(upload_->images.size()))
    return absl::InvalidArgumentError(
        absl::StrCat("image ", upload_->images.size() - 1, " is incomplete (no last chunk)"));
  if (upload_->spec.has_points() && !points_complete_)
    return absl::InvalidArgumentError("the announced point cloud is missing or incomplete");
  return absl::OkStatus();
}

}  // namespace gaps

#include "server/scene_upload.h"

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <set>

#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/ply.h"
#include "common/printable.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/cameras_json.h"
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

// The longest file name common file systems take.
constexpr size_t kMaxFileNameBytes = 255;

bool plain_file_name(const std::string& name) {
  return !name.empty() && name != "." && name != ".." && name.find('/') == std::string::npos &&
         name.find('\\') == std::string::npos && !has_control_characters(name);
}

nlohmann::json frame_json(const Camera& c, const std::string& file) {
  nlohmann::json frame = {{"file_path", file}, {"transform_matrix", transform_matrix_json(c)},
                          {"fl_x", c.fx},      {"fl_y", c.fy},
                          {"cx", c.cx},        {"cy", c.cy},
                          {"w", c.width},      {"h", c.height}};
  // The scene's depth bounds (LLFF gives them): random initial points are drawn between them, so a job
  // without them would start elsewhere than `gaps train` on the same scene.
  if (c.far > 0) {
    frame["near"] = c.near;
    frame["far"] = c.far;
  }
  return frame;
}

absl::Status store_failed(absl::string_view what, absl::string_view why) {
  // The data folder's path is the server's business; the client learns what failed and why.
  return absl::ResourceExhaustedError(absl::StrCat("the trainer could not store the upload (", what, ": ", why, ")"));
}

// Appends SubmitJob's file chunks to their files as they arrive: images in order, each complete before the
// next begins, and at most one point cloud.
class UploadWriter {
 public:
  UploadWriter(SceneUpload* upload, uint64_t max_bytes) : upload_(upload), max_bytes_(max_bytes) {}

  absl::Status add(const v1::FileChunk& chunk) {
    received_ += chunk.data().size();
    if (received_ > max_bytes_)
      return absl::ResourceExhaustedError(absl::StrCat("upload exceeds the limit of ", max_bytes_, " bytes"));
    switch (chunk.kind()) {
      case v1::FileChunk::IMAGE:
        return add_image(chunk);
      case v1::FileChunk::POINTS:
        return add_points(chunk);
      case v1::FileChunk::LARGER_IMAGE:
        return add_larger_image(chunk);
      default:
        return absl::InvalidArgumentError(absl::StrCat("file chunk of unknown kind ", chunk.kind()));
    }
  }

  // Checks every announced file arrived complete.
  absl::Status finish() {
    GAPS_RETURN_IF_ERROR(switch_to(fs::path()));
    if (started_images_ != upload_->images)
      return absl::InvalidArgumentError(absl::StrCat("image ", started_images_ - 1, " is incomplete (no last chunk)"));
    if (larger_open_ >= 0)
      return absl::InvalidArgumentError(absl::StrCat("larger image ", larger_open_, " is incomplete (no last chunk)"));
    if (upload_->spec.has_points() && !points_complete_)
      return absl::InvalidArgumentError("the announced point cloud is missing or incomplete");
    return absl::OkStatus();
  }

 private:
  absl::Status add_image(const v1::FileChunk& chunk) {
    const int index = chunk.index();
    if (index != upload_->images)
      return absl::InvalidArgumentError(absl::StrCat("image chunk for index ", index, " while image ", upload_->images,
                                                     " is expected (images arrive in order)"));
    if (index >= upload_->spec.cameras_size())
      return absl::InvalidArgumentError(absl::StrCat("camera count mismatch: image ", index, " has no camera (",
                                                     upload_->spec.cameras_size(), " cameras)"));
    if (index == started_images_) ++started_images_;
    GAPS_RETURN_IF_ERROR(append(upload_->image_file(index), chunk.data()));
    if (chunk.last()) ++upload_->images;
    return absl::OkStatus();
  }

  absl::Status add_larger_image(const v1::FileChunk& chunk) {
    const int index = chunk.index();
    if (upload_->images < upload_->spec.cameras_size())
      return absl::InvalidArgumentError(
          absl::StrCat("larger image for camera ", index, " before every image arrived (they follow the images)"));
    if (index != larger_open_) {
      if (larger_open_ >= 0)
        return absl::InvalidArgumentError(
            absl::StrCat("larger image ", larger_open_, " is incomplete (no last chunk)"));
      const int after = upload_->larger_images.empty() ? -1 : upload_->larger_images.back();
      if (index <= after || index >= upload_->spec.cameras_size())
        return absl::InvalidArgumentError(absl::StrCat("larger image for camera ", index, " out of order or range (",
                                                       upload_->spec.cameras_size(), " cameras, last sent ", after,
                                                       ")"));
      larger_open_ = index;
    }
    GAPS_RETURN_IF_ERROR(append(upload_->larger_image_file(index), chunk.data()));
    if (chunk.last()) {
      upload_->larger_images.push_back(index);
      larger_open_ = -1;
    }
    return absl::OkStatus();
  }

  absl::Status add_points(const v1::FileChunk& chunk) {
    if (!upload_->spec.has_points()) return absl::InvalidArgumentError("point cloud sent but the spec announced none");
    if (points_complete_) return absl::InvalidArgumentError("point cloud sent twice");
    GAPS_RETURN_IF_ERROR(append(upload_->points_file(), chunk.data()));
    points_complete_ = chunk.last();
    return absl::OkStatus();
  }

  absl::Status append(const fs::path& file, const std::string& data) {
    if (file != open_) GAPS_RETURN_IF_ERROR(switch_to(file));
    if (!out_.write(data.data(), static_cast<std::streamsize>(data.size())))
      return store_failed("write", std::strerror(errno));
    return absl::OkStatus();
  }

  // Closes the file being written (a failed close is a failed write) and opens `file`, if any, afresh.
  absl::Status switch_to(const fs::path& file) {
    if (out_.is_open()) {
      out_.close();
      if (!out_) return store_failed("write", std::strerror(errno));
    }
    open_ = file;
    if (file.empty()) return absl::OkStatus();
    out_.clear();
    out_.open(file, std::ios::binary | std::ios::trunc);
    if (!out_) return store_failed("create", std::strerror(errno));
    return absl::OkStatus();
  }

  SceneUpload* upload_;
  uint64_t max_bytes_;
  uint64_t received_ = 0;
  int started_images_ = 0;
  int larger_open_ = -1;  // the larger image being received, if any
  bool points_complete_ = false;
  std::ofstream out_;
  fs::path open_;
};

// One uploaded image: read back (one at a time), its header checked before decoding: `scale` times the camera's
// size, within `tolerance` pixels on each side (a larger view's size was rounded from the full one's).
absl::Status check_uploaded_image(const fs::path& file, const Camera& camera, const std::string& what, int scale = 1,
                                  int tolerance = 0) {
  absl::StatusOr<std::string> bytes = read_file_bytes(file, "uploaded image");
  if (!bytes.ok()) return store_failed("read back", absl::StatusCodeToString(bytes.status().code()));
  absl::StatusOr<std::pair<int, int>> size = decode_image_size(*bytes, what);
  if (!size.ok()) return invalid(size.status());
  const int width = scale * camera.width, height = scale * camera.height;
  if (std::abs(size->first - width) > tolerance || std::abs(size->second - height) > tolerance)
    return absl::InvalidArgumentError(absl::StrCat(what, ": image is ", size->first, "x", size->second, " but ",
                                                   scale == 1 ? "its camera says " : "twice its camera's size is ",
                                                   width, "x", height));
  return invalid(decode_image(*bytes, what).status());
}

}  // namespace

fs::path SceneUpload::image_file(int index) const { return dir / "upload" / absl::StrCat("image_", index); }
fs::path SceneUpload::larger_image_file(int index) const { return dir / "upload" / absl::StrCat("larger_", index); }
fs::path SceneUpload::points_file() const { return dir / "upload" / "points.ply"; }

absl::StatusOr<SceneUpload> receive_upload(const UploadMessageSource& next, uint64_t max_bytes, const fs::path& dir) {
  v1::SubmitJobRequest part;
  if (!next(&part) || !part.has_spec())
    return absl::InvalidArgumentError("SubmitJob's first message must carry the JobSpec");
  SceneUpload upload;
  upload.spec = part.spec();
  upload.dir = dir;
  std::error_code ec;
  fs::create_directories(dir / "upload", ec);
  if (ec) return store_failed("create folder", ec.message());
  UploadWriter writer(&upload, max_bytes);
  while (next(&part)) {
    if (!part.has_file()) return absl::InvalidArgumentError("only file chunks may follow the JobSpec");
    GAPS_RETURN_IF_ERROR(writer.add(part.file()));
  }
  GAPS_RETURN_IF_ERROR(writer.finish());
  return upload;
}

absl::Status write_uploaded_scene(const SceneUpload& upload) {
  const v1::JobSpec& spec = upload.spec;
  const int cameras = spec.cameras_size(), images = upload.images;
  if (cameras == 0) return absl::InvalidArgumentError("the upload has no cameras");
  // A job's name reaches other users' terminals (gaps list, watch): no control characters, a line's length.
  if (spec.name().size() > kMaxFileNameBytes)
    return absl::InvalidArgumentError(
        absl::StrCat("job name of ", spec.name().size(), " bytes, over the limit of ", kMaxFileNameBytes));
  if (has_control_characters(spec.name()))
    return absl::InvalidArgumentError(
        absl::StrCat("job name '", printable(spec.name()), "' has control characters (escapes, line breaks)"));
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
    const std::string what = absl::StrCat("camera ", i, " (", printable(spec.cameras(i).name().substr(0, 80)), ")");
    GAPS_ASSIGN_OR_RETURN(Camera camera, rpc::decode_camera(spec.cameras(i), what));
    if (camera.name.size() > kMaxFileNameBytes)
      return absl::InvalidArgumentError(absl::StrCat("camera ", i, ": image name of ", camera.name.size(),
                                                     " bytes, over the limit of ", kMaxFileNameBytes));
    if (!plain_file_name(camera.name))
      return absl::InvalidArgumentError(absl::StrCat("camera ", i, " (", printable(camera.name),
                                                     "): image name must be a plain file name (no "
                                                     "folders, no control characters)"));
    if (!names.insert(camera.name).second)
      return absl::InvalidArgumentError(absl::StrCat(what, ": duplicate image name"));
    GAPS_RETURN_IF_ERROR(
        check_uploaded_image(upload.image_file(i), camera, absl::StrCat("image ", i, " (", camera.name, ")")));
    decoded.push_back(std::move(camera));
  }
  for (int i : upload.larger_images)
    GAPS_RETURN_IF_ERROR(check_uploaded_image(upload.larger_image_file(i), decoded[i],
                                              absl::StrCat("larger image of camera ", i, " (", decoded[i].name, ")"),
                                              /*scale=*/2, /*tolerance=*/1));
  if (spec.has_points()) {
    // The reader names the file it read; the client knows it as the uploaded point cloud, not by our path.
    const fs::path ply = upload.points_file();
    if (auto points = read_point_cloud_ply(ply); !points.ok())
      return absl::InvalidArgumentError(absl::StrCat(
          "uploaded point cloud: ", absl::StrReplaceAll(points.status().message(), {{ply.string() + ": ", ""}})));
  }

  std::error_code ec;
  fs::create_directories(upload.dir / "images", ec);
  if (ec) return store_failed("create folder", ec.message());
  nlohmann::json frames = nlohmann::json::array();
  for (int i = 0; i < cameras; ++i) {
    const std::string file = "images/" + decoded[i].name;
    fs::rename(upload.image_file(i), upload.dir / file, ec);
    if (ec) return store_failed("rename", ec.message());
    frames.push_back(frame_json(decoded[i], file));
  }
  if (!upload.larger_images.empty()) {
    fs::create_directories(upload.dir / kLargerViewsFolder, ec);
    if (ec) return store_failed("create folder", ec.message());
  }
  for (int i : upload.larger_images) {
    fs::rename(upload.larger_image_file(i), upload.dir / kLargerViewsFolder / decoded[i].name, ec);
    if (ec) return store_failed("rename", ec.message());
  }
  if (spec.has_points()) {
    fs::rename(upload.points_file(), upload.dir / "points.ply", ec);
    if (ec) return store_failed("rename", ec.message());
  }
  remove_tree(upload.dir / "upload");
  const std::string doc = nlohmann::json{{"camera_model", "PINHOLE"}, {"frames", frames}}.dump(2);
  return write_file_bytes(upload.dir / "transforms.json", doc);
}

}  // namespace gaps

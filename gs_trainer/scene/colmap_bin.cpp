// COLMAP's binary model format (colmap/scene/reconstruction_io.cc): little-endian, counts as uint64.
#include <cstring>

#include "absl/strings/str_cat.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/colmap.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

class BinReader {
 public:
  BinReader(std::string bytes, const fs::path& file) : bytes_(std::move(bytes)), file_(file.string()) {}

  template <typename T>
  bool read(T* value) {
    if (bytes_.size() - pos_ < sizeof(T)) return false;
    std::memcpy(value, bytes_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return true;
  }

  bool read_string(std::string* value) {
    const size_t end = bytes_.find('\0', pos_);
    if (end == std::string::npos) return false;
    value->assign(bytes_, pos_, end - pos_);
    pos_ = end + 1;
    return true;
  }

  // A count read from a corrupt file must not trigger a huge allocation: each element takes at least
  // `min_bytes`, so the count cannot exceed what is left.
  bool read_count(uint64_t* count, size_t min_bytes) {
    return read(count) && *count <= (bytes_.size() - pos_) / min_bytes;
  }

  bool at_end() const { return pos_ == bytes_.size(); }

  absl::Status error(absl::string_view what, uint64_t index) const {
    return absl::DataLossError(absl::StrCat(file_, ": truncated or corrupt ", what, " at record ", index));
  }
  absl::Status trailing() const {
    return absl::DataLossError(absl::StrCat(file_, ": ", bytes_.size() - pos_, " unexpected trailing bytes"));
  }

 private:
  std::string bytes_;
  std::string file_;
  size_t pos_ = 0;
};

bool read_doubles(BinReader& in, double* out, int n) {
  for (int i = 0; i < n; ++i) {
    if (!in.read(&out[i])) return false;
  }
  return true;
}

bool read_camera(BinReader& in, ColmapCamera* camera, std::string* problem) {
  int32_t id = 0, model_id = 0;
  uint64_t width = 0, height = 0;
  if (!in.read(&id) || !in.read(&model_id) || !in.read(&width) || !in.read(&height)) return false;
  const std::optional<std::string> model = colmap_model_name(model_id);
  if (!model) {
    *problem = absl::StrCat("unknown camera model id ", model_id);
    return false;
  }
  *camera = ColmapCamera{id, *model, static_cast<int64_t>(width), static_cast<int64_t>(height), {}};
  camera->params.resize(*colmap_model_num_params(*model));
  return read_doubles(in, camera->params.data(), static_cast<int>(camera->params.size()));
}

bool read_image(BinReader& in, ColmapImage* image) {
  int32_t id = 0, camera_id = 0;
  uint64_t num_points = 0;
  if (!in.read(&id) || !read_doubles(in, image->qvec.data(), 4) || !read_doubles(in, image->tvec.data(), 3) ||
      !in.read(&camera_id) || !in.read_string(&image->name) || !in.read_count(&num_points, 24))
    return false;
  image->id = id;
  image->camera_id = camera_id;
  image->xys.resize(num_points);
  image->point3d_ids.resize(num_points);
  for (uint64_t i = 0; i < num_points; ++i) {
    if (!read_doubles(in, image->xys[i].data(), 2) || !in.read(&image->point3d_ids[i])) return false;
  }
  return true;
}

bool read_point(BinReader& in, ColmapPoint* point) {
  uint64_t id = 0, track_length = 0;
  if (!in.read(&id) || !read_doubles(in, point->xyz.data(), 3)) return false;
  for (uint8_t& c : point->rgb) {
    if (!in.read(&c)) return false;
  }
  if (!in.read(&point->error) || !in.read_count(&track_length, 8)) return false;
  point->id = static_cast<int64_t>(id);
  point->track.resize(track_length);
  for (ColmapTrackElement& element : point->track) {
    int32_t image_id = 0, idx = 0;
    if (!in.read(&image_id) || !in.read(&idx)) return false;
    element = {image_id, idx};
  }
  return true;
}

}  // namespace

absl::StatusOr<std::map<int, ColmapCamera>> read_colmap_cameras_bin(const fs::path& file) {
  GAPS_ASSIGN_OR_RETURN(std::string bytes, read_file_bytes(file, "COLMAP cameras file"));
  BinReader in(std::move(bytes), file);
  uint64_t count = 0;
  if (!in.read_count(&count, 24)) return in.error("camera count", 0);
  std::map<int, ColmapCamera> cameras;
  for (uint64_t i = 0; i < count; ++i) {
    ColmapCamera camera;
    std::string problem;
    if (!read_camera(in, &camera, &problem)) {
      if (problem.empty()) return in.error("camera", i);
      return absl::InvalidArgumentError(absl::StrCat(file.string(), ": camera record ", i, ": ", problem));
    }
    cameras[camera.id] = std::move(camera);
  }
  if (!in.at_end()) return in.trailing();
  return cameras;
}

absl::StatusOr<std::map<int, ColmapImage>> read_colmap_images_bin(const fs::path& file) {
  GAPS_ASSIGN_OR_RETURN(std::string bytes, read_file_bytes(file, "COLMAP images file"));
  BinReader in(std::move(bytes), file);
  uint64_t count = 0;
  if (!in.read_count(&count, 72)) return in.error("image count", 0);
  std::map<int, ColmapImage> images;
  for (uint64_t i = 0; i < count; ++i) {
    ColmapImage image;
    if (!read_image(in, &image)) return in.error("image", i);
    images[image.id] = std::move(image);
  }
  if (!in.at_end()) return in.trailing();
  return images;
}

absl::StatusOr<std::vector<ColmapPoint>> read_colmap_points_bin(const fs::path& file) {
  GAPS_ASSIGN_OR_RETURN(std::string bytes, read_file_bytes(file, "COLMAP points3D file"));
  BinReader in(std::move(bytes), file);
  uint64_t count = 0;
  if (!in.read_count(&count, 43)) return in.error("point count", 0);
  std::vector<ColmapPoint> points(count);
  for (uint64_t i = 0; i < count; ++i) {
    if (!read_point(in, &points[i])) return in.error("point", i);
  }
  if (!in.at_end()) return in.trailing();
  return points;
}

}  // namespace gaps

// COLMAP's text model format: '#' comments, whitespace-separated fields, and in images.txt two lines per
// image (the pose line, then the 2D points line, which may be empty).
#include <charconv>
#include <sstream>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/colmap.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

// Lines of one file with their 1-based numbers, for error messages.
class LineReader {
 public:
  LineReader(const std::string& text, const fs::path& file) : in_(text), file_(file.string()) {}

  // Next line that is neither empty nor a comment.
  bool next_data(std::vector<absl::string_view>* fields) {
    while (next_any(fields)) {
      if (!fields->empty() && fields->front()[0] != '#') return true;
    }
    return false;
  }

  // Next line whatever it holds (the possibly empty points line of images.txt).
  bool next_any(std::vector<absl::string_view>* fields) {
    if (!std::getline(in_, line_)) return false;
    ++number_;
    *fields = absl::StrSplit(line_, absl::ByAnyChar(" \t\r"), absl::SkipEmpty());
    return true;
  }

  absl::Status error(absl::string_view problem) const {
    return absl::InvalidArgumentError(absl::StrCat(file_, ":", number_, ": ", problem));
  }

 private:
  std::istringstream in_;
  std::string file_;
  std::string line_;
  int number_ = 0;
};

bool parse(absl::string_view s, double* v) { return absl::SimpleAtod(s, v); }
bool parse(absl::string_view s, int* v) { return absl::SimpleAtoi(s, v); }
bool parse(absl::string_view s, int64_t* v) { return absl::SimpleAtoi(s, v); }
bool parse(absl::string_view s, uint8_t* v) {
  int i = 0;
  if (!absl::SimpleAtoi(s, &i) || i < 0 || i > 255) return false;
  *v = static_cast<uint8_t>(i);
  return true;
}

// Parses fields[first, first + n) into out[0..n).
template <typename T>
bool parse_fields(const std::vector<absl::string_view>& fields, size_t first, size_t n, T* out) {
  if (fields.size() < first + n) return false;
  for (size_t i = 0; i < n; ++i) {
    if (!parse(fields[first + i], &out[i])) return false;
  }
  return true;
}

absl::StatusOr<ColmapCamera> parse_camera(const std::vector<absl::string_view>& f, const LineReader& in) {
  ColmapCamera camera;
  if (f.size() < 4 || !parse(f[0], &camera.id) || !parse(f[2], &camera.width) || !parse(f[3], &camera.height))
    return in.error("expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]");
  camera.model = std::string(f[1]);
  camera.params.resize(f.size() - 4);
  if (!parse_fields(f, 4, camera.params.size(), camera.params.data())) return in.error("malformed camera parameter");
  const std::optional<int> expected = colmap_model_num_params(camera.model);
  if (!expected) return in.error(absl::StrCat("unknown camera model ", camera.model));
  if (*expected != static_cast<int>(camera.params.size()))
    return in.error(absl::StrCat(camera.model, " needs ", *expected, " parameters, found ", camera.params.size()));
  return camera;
}

absl::Status parse_image_points(const std::vector<absl::string_view>& f, const LineReader& in, ColmapImage* image) {
  if (f.size() % 3 != 0) return in.error("2D points line must hold X Y POINT3D_ID triples");
  for (size_t i = 0; i < f.size(); i += 3) {
    Eigen::Vector2d xy;
    int64_t id = 0;
    if (!parse_fields(f, i, 2, xy.data()) || !parse(f[i + 2], &id)) return in.error("malformed 2D point");
    image->xys.push_back(xy);
    image->point3d_ids.push_back(id);
  }
  return absl::OkStatus();
}

absl::StatusOr<ColmapImage> parse_image(const std::vector<absl::string_view>& f, LineReader& in) {
  ColmapImage image;
  if (f.size() < 10 || !parse(f[0], &image.id) || !parse_fields(f, 1, 4, image.qvec.data()) ||
      !parse_fields(f, 5, 3, image.tvec.data()) || !parse(f[8], &image.camera_id))
    return in.error("expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME");
  image.name = std::string(f[9]);
  std::vector<absl::string_view> points;
  if (!in.next_any(&points)) return image;  // a final image without its points line
  GAPS_RETURN_IF_ERROR(parse_image_points(points, in, &image));
  return image;
}

absl::StatusOr<ColmapPoint> parse_point(const std::vector<absl::string_view>& f, const LineReader& in) {
  ColmapPoint point;
  if (f.size() < 8 || (f.size() - 8) % 2 != 0 || !parse(f[0], &point.id) || !parse_fields(f, 1, 3, point.xyz.data()) ||
      !parse_fields(f, 4, 3, point.rgb.data()) || !parse(f[7], &point.error))
    return in.error("expected POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID POINT2D_IDX) pairs");
  for (size_t i = 8; i < f.size(); i += 2) {
    ColmapTrackElement element;
    if (!parse(f[i], &element.image_id) || !parse(f[i + 1], &element.point2d_idx)) return in.error("malformed track");
    point.track.push_back(element);
  }
  return point;
}

// Shortest text that reads back to exactly the same double.
std::string num(double v) {
  char buffer[32];
  const auto result = std::to_chars(buffer, buffer + sizeof(buffer), v);
  return std::string(buffer, result.ptr);
}

std::string cameras_text(const ColmapModel& model) {
  std::string out = absl::StrCat("# Camera list with one line of data per camera:\n",
                                 "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n",
                                 "# Number of cameras: ", model.cameras.size(), "\n");
  for (const auto& [id, camera] : model.cameras) {
    absl::StrAppend(&out, id, " ", camera.model, " ", camera.width, " ", camera.height);
    for (double p : camera.params) absl::StrAppend(&out, " ", num(p));
    out += "\n";
  }
  return out;
}

std::string images_text(const ColmapModel& model) {
  std::string out = absl::StrCat(
      "# Image list with two lines of data per image:\n", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n",
      "#   POINTS2D[] as (X, Y, POINT3D_ID)\n", "# Number of images: ", model.images.size(), "\n");
  for (const auto& [id, image] : model.images) {
    absl::StrAppend(&out, id);
    for (double q : image.qvec) absl::StrAppend(&out, " ", num(q));
    for (double t : image.tvec) absl::StrAppend(&out, " ", num(t));
    absl::StrAppend(&out, " ", image.camera_id, " ", image.name, "\n");
    for (size_t i = 0; i < image.xys.size(); ++i) {
      absl::StrAppend(&out, i ? " " : "", num(image.xys[i].x()), " ", num(image.xys[i].y()), " ", image.point3d_ids[i]);
    }
    out += "\n";
  }
  return out;
}

std::string points_text(const ColmapModel& model) {
  std::string out = absl::StrCat("# 3D point list with one line of data per point:\n",
                                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n",
                                 "# Number of points: ", model.points.size(), "\n");
  for (const ColmapPoint& p : model.points) {
    absl::StrAppend(&out, p.id, " ", num(p.xyz.x()), " ", num(p.xyz.y()), " ", num(p.xyz.z()), " ", int{p.rgb[0]}, " ",
                    int{p.rgb[1]}, " ", int{p.rgb[2]}, " ", num(p.error));
    for (const ColmapTrackElement& e : p.track) absl::StrAppend(&out, " ", e.image_id, " ", e.point2d_idx);
    out += "\n";
  }
  return out;
}

}  // namespace

absl::StatusOr<std::map<int, ColmapCamera>> read_colmap_cameras_txt(const fs::path& file) {
  GAPS_ASSIGN_OR_RETURN(const std::string text, read_file_bytes(file, "COLMAP cameras file"));
  LineReader in(text, file);
  std::map<int, ColmapCamera> cameras;
  for (std::vector<absl::string_view> fields; in.next_data(&fields);) {
    GAPS_ASSIGN_OR_RETURN(ColmapCamera camera, parse_camera(fields, in));
    cameras[camera.id] = std::move(camera);
  }
  return cameras;
}

absl::StatusOr<std::map<int, ColmapImage>> read_colmap_images_txt(const fs::path& file) {
  GAPS_ASSIGN_OR_RETURN(const std::string text, read_file_bytes(file, "COLMAP images file"));
  LineReader in(text, file);
  std::map<int, ColmapImage> images;
  for (std::vector<absl::string_view> fields; in.next_data(&fields);) {
    GAPS_ASSIGN_OR_RETURN(ColmapImage image, parse_image(fields, in));
    images[image.id] = std::move(image);
  }
  return images;
}

absl::StatusOr<std::vector<ColmapPoint>> read_colmap_points_txt(const fs::path& file) {
  GAPS_ASSIGN_OR_RETURN(const std::string text, read_file_bytes(file, "COLMAP points3D file"));
  LineReader in(text, file);
  std::vector<ColmapPoint> points;
  for (std::vector<absl::string_view> fields; in.next_data(&fields);) {
    GAPS_ASSIGN_OR_RETURN(ColmapPoint point, parse_point(fields, in));
    points.push_back(std::move(point));
  }
  return points;
}

absl::Status write_colmap_text(const fs::path& dir, const ColmapModel& model) {
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) return absl::PermissionDeniedError(absl::StrCat(dir.string(), ": cannot create folder: ", ec.message()));
  GAPS_RETURN_IF_ERROR(write_file_bytes(dir / "cameras.txt", cameras_text(model)));
  GAPS_RETURN_IF_ERROR(write_file_bytes(dir / "images.txt", images_text(model)));
  return write_file_bytes(dir / "points3D.txt", points_text(model));
}

}  // namespace gaps

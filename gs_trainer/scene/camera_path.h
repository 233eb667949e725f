#pragma once
// Camera paths through a reconstructed scene, for `gaps render`: pure pose maths on the run's cameras.
//   orbit   around the scene's centre, in the plane orthogonal to the cameras' mean up vector, at their mean
//           distance from the centre (and their mean height above it), looking at the centre;
//   spiral  the LLFF / nerfstudio spiral for forward-facing captures: around the mean pose, with radii the 90th
//           percentile of the camera positions' spread in the mean pose's frame, two turns, looking at a focus
//           depth taken from the scene's depth bounds;
//   interp  through the training cameras in order: positions on a Catmull-Rom spline, rotations slerped;
//   test    the test cameras themselves;
//   FILE.json  the cameras of a cameras.json list (gs_trainer/scene/cameras_json.h), with their own intrinsics.
// The generated paths (orbit, spiral, interp) take the intrinsics and image size of the first training camera.
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <Eigen/Core>
#include "absl/status/statusor.h"
#include "gs_trainer/scene/camera.h"

namespace gaps {

// What a path is built from.
struct PathScene {
  std::vector<Camera> train;  // the training cameras, in the run's order
  std::vector<Camera> test;
  // Depth bounds of the scene in front of the training cameras (near < far; see path_depth_bounds).
  double near = 0.0;
  double far = 0.0;
};

// The depth bounds a path uses: the cameras' own (LLFF gives them: the smallest near and the largest far),
// else the 1st and 99th percentiles of the depths of `points` (N x 3, e.g. the model's means) in front of the
// cameras. InvalidArgument when neither gives any.
absl::StatusOr<std::pair<double, double>> path_depth_bounds(const std::vector<Camera>& cameras,
                                                            const at::Tensor& points);

// The cameras' mean up vector (-y of OpenCV axes), normalised.
Eigen::Vector3d mean_up(const std::vector<Camera>& cameras);

// A camera with the intrinsics and size of `intrinsics` at `position`, looking at `target`, its image up as
// close to `up` as the viewing direction allows. No distortion, no depth bounds.
Camera look_at(const Camera& intrinsics, const Eigen::Vector3d& position, const Eigen::Vector3d& target,
               const Eigen::Vector3d& up);

// LLFF's focus depth: 1 / ((1 - 0.75) / (0.9 near) + 0.75 / (5 far)), a depth between the near bound and far
// beyond it, weighted towards the near content, which a forward-facing capture frames.
double spiral_focus_depth(double near, double far);

// The point the orbit turns around: where the training cameras' optical axes pass closest together when that
// lies in front of every camera (a capture around an object), otherwise the point at the focus depth
// (spiral_focus_depth) along the cameras' mean viewing direction from their mean centre (forward-facing).
Eigen::Vector3d scene_centre(const PathScene& scene);

// `frames` cameras (>= 1) on each path; `scene.train` must not be empty.
std::vector<Camera> orbit_path(const PathScene& scene, int frames);
std::vector<Camera> spiral_path(const PathScene& scene, int frames);
// Frame k sits at spline parameter s = k (n - 1) / (frames - 1) over the n training cameras: training camera
// i is frame i (frames - 1) / (n - 1) whenever that is a whole number (e.g. frames = m (n - 1) + 1).
std::vector<Camera> interp_path(const PathScene& scene, int frames);

// A path by name: orbit, spiral, interp, test, or a .json file of cameras (cameras.json layout). Usage-level
// errors are InvalidArgument; an unreadable file keeps read_cameras_json's error.
absl::StatusOr<std::vector<Camera>> camera_path(const std::string& path, const PathScene& scene, int frames);

// The name of a path for folders and logs: the path itself, or the file's stem for a .json file.
std::string camera_path_name(const std::string& path);

}  // namespace gaps

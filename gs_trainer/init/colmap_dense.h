#pragma once
// The PatchMatch maps and the fused cloud as a COLMAP dense workspace, so that they can be compared with
// COLMAP's own (or fused again by `colmap stereo_fusion`):
//   <dir>/images/<name>.png                              the views at the working resolution
//   <dir>/sparse/{cameras,images,points3D}.txt           cameras at that resolution, the sparse points
//   <dir>/stereo/depth_maps/<name>.png.geometric.bin     depth (camera z, 0 = none), COLMAP Mat<float>
//   <dir>/stereo/normal_maps/<name>.png.geometric.bin    unit camera-frame normals, COLMAP Mat<float>
//   <dir>/stereo/fusion.cfg                              the image names stereo_fusion reads maps for
//   <dir>/fused.ply                                      x y z nx ny nz (float) red green blue (uchar)
// <name> is the view's file name with a .png extension, the name images.txt gives the view.
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "gs_trainer/init/fusion.h"
#include "gs_trainer/init/patchmatch.h"
#include "gs_trainer/scene/scene.h"

namespace gaps {

// COLMAP's Mat<float> file (src/colmap/mvs/mat.{h,cc}): the text header "<width>&<height>&<channels>&", then
// width * height * channels little-endian float32 values, channel-major: channel c, row r, column x is value
// c * width * height + r * width + x (each channel a full row-major plane). `map` is HxW (one channel) or
// HxWxC, any float type and device.
absl::Status write_colmap_mat(const std::filesystem::path& path, const at::Tensor& map);
// The reverse: HxW for one channel, else HxWxC (CPU float32). Errors name the file and what is wrong.
absl::StatusOr<at::Tensor> read_colmap_mat(const std::filesystem::path& path);

// Binary little-endian PLY as COLMAP writes fused.ply: x y z nx ny nz float, red green blue uchar.
absl::Status write_colmap_fused_ply(const std::filesystem::path& path, const PointCloud& points,
                                    const at::Tensor& normals);

// The name a view has in the workspace: its file name with a .png extension.
std::string dense_image_name(const Camera& camera);

// The whole workspace (layout above) from the PatchMatch maps, the fused cloud and, for points3D.txt, the
// sparse points (none: an empty points3D.txt). Existing files are overwritten.
absl::Status write_colmap_dense_workspace(const std::filesystem::path& dir, const std::vector<ViewDepthNormal>& maps,
                                          const FusedCloud& fused, const std::optional<PointCloud>& sparse_points);

}  // namespace gaps

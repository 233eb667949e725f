#pragma once
// The model as the viewer (assets/splats.js) reads it: a compact packed format that keeps what the
// rasterizer renders exactly (float32 means, activated scales and opacities, quaternions, SH DC) and the SH
// rest coefficients as float16; and the antimatter15 `.splat` layout that common web splat viewers read.
#include <cstdint>
#include <string>

#include "absl/status/status.h"
#include "gs_trainer/model/gaussians.h"

namespace gaps::viewer {

// Packed layout, little endian: a 32-byte header ("GAPSVW01", u32 count, u32 SH degree, 16 zero bytes), then
// float32 means (3N), scales (3N, exp applied), quaternions (4N, w x y z, as stored), opacities (N, sigmoid
// applied), SH DC (3N), and float16 SH rest (N x ((degree + 1)^2 - 1) x 3, the rasterizer's order).
inline constexpr char kPackMagic[] = "GAPSVW01";
inline constexpr int64_t kPackHeaderBytes = 32;

// The SH degree worth packing: the model's active degree, lowered while its highest band's coefficients are
// all zero (a run shorter than the first degree increase leaves them so), as they add exactly nothing.
int effective_sh_degree(const GaussianModel& model);
int64_t packed_model_bytes(int64_t count, int sh_degree);
std::string pack_model(const GaussianModel& model);

// antimatter15's .splat: 32 bytes per Gaussian: position 3 x f32, scale 3 x f32 (linear), RGBA u8 (colour
// 0.5 + C0 * dc clamped to [0, 1], sigmoid opacity; both x 255 rounded), rotation 4 x u8 (q / |q| * 128 + 128
// rounded, clamped to [0, 255], w first). Degree 0: view-dependent colour is lost. Sorted as that project's
// converter sorts: by exp(scale sum) * opacity, largest first (ties by index).
inline constexpr int64_t kSplatRecordBytes = 32;
std::string splat_file_bytes(const GaussianModel& model);
// Whether `bytes` can be a .splat file (a positive multiple of 32 bytes); errors name `where`.
absl::Status check_splat_bytes(const std::string& bytes, const std::string& where);

}  // namespace gaps::viewer

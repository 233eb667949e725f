#include "diffusion_worker/reproject_generator.h"

#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <exception>
#include <limits>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/photo.hpp>
#include <optional>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/status_macros.h"

namespace gaps {
namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr float kInf = std::numeric_limits<float>::infinity();
// Weight of a footprint pixel the tent kernel barely reaches: it still counts as covered (no crack when
// the warp magnifies), but any sample that lands properly outweighs it by four orders of magnitude.
constexpr float kMinSplatWeight = 1e-4f;

// ---------------------------------------------------------------------------------------------------
// Input checks. Messages name the request / reference and the field, so a caller can tell which of many
// tensors is wrong.

std::string shape_of(const at::Tensor& t) { return absl::StrJoin(t.sizes(), "x"); }

at::Tensor cpu_float(const at::Tensor& t) { return t.to(at::kCPU, at::kFloat).contiguous(); }

struct ValueRange {
  float min = kInf, max = -kInf;
};

// One pass over the values (a dozen ATen reductions cost more than the warp itself); nullopt when one
// is NaN or infinite.
std::optional<ValueRange> finite_range(const at::Tensor& t) {
  const at::Tensor values = cpu_float(t);
  const float* v = values.data_ptr<float>();
  ValueRange r;
  bool finite = true;
  for (int64_t i = 0, n = values.numel(); i < n; ++i) {
    finite &= std::isfinite(v[i]);
    r.min = std::min(r.min, v[i]);
    r.max = std::max(r.max, v[i]);
  }
  return finite ? std::optional<ValueRange>(r) : std::nullopt;
}

// Shape, dtype and finiteness; returns the value range for further checks.
absl::StatusOr<ValueRange> check_tensor(const at::Tensor& t, const std::vector<int64_t>& expected,
                                        const std::string& what) {
  if (!t.defined()) return absl::InvalidArgumentError(absl::StrCat(what, " is missing"));
  if (t.sizes() != at::IntArrayRef(expected)) {
    return absl::InvalidArgumentError(
        absl::StrCat(what, " is ", shape_of(t), ", expected ", absl::StrJoin(expected, "x"), " (from its camera)"));
  }
  if (!t.is_floating_point()) {
    return absl::InvalidArgumentError(
        absl::StrCat(what, " must be floating point, got ", std::string(c10::toString(t.scalar_type()))));
  }
  const std::optional<ValueRange> range = finite_range(t);
  if (!range) return absl::InvalidArgumentError(absl::StrCat(what, " has NaN or infinite values"));
  return *range;
}

absl::Status check_camera(const Camera& c, const std::string& what) {
  const bool finite = std::isfinite(c.fx) && std::isfinite(c.fy) && std::isfinite(c.cx) && std::isfinite(c.cy) &&
                      c.R.allFinite() && c.t.allFinite();
  if (c.width <= 0 || c.height <= 0 || !finite || c.fx <= 0 || c.fy <= 0) {
    return absl::InvalidArgumentError(absl::StrCat(what, " camera is invalid (", c.width, "x", c.height, ", fx ", c.fx,
                                                   ", fy ", c.fy, ", pose ", finite ? "finite" : "not finite", ")"));
  }
  return absl::OkStatus();
}

// Image, depth and alpha of one view at its camera's size; depth/alpha finite and non-negative.
absl::Status check_view(const Camera& camera, const at::Tensor& image, const at::Tensor& depth, const at::Tensor& alpha,
                        const std::string& image_name, const std::string& what) {
  GAPS_RETURN_IF_ERROR(check_camera(camera, what));
  const int64_t h = camera.height, w = camera.width;
  GAPS_RETURN_IF_ERROR(check_tensor(image, {h, w, 3}, absl::StrCat(what, " ", image_name)).status());
  GAPS_ASSIGN_OR_RETURN(const ValueRange d, check_tensor(depth, {h, w}, absl::StrCat(what, " render_depth")));
  GAPS_ASSIGN_OR_RETURN(const ValueRange a, check_tensor(alpha, {h, w}, absl::StrCat(what, " render_alpha")));
  if (d.min < 0) return absl::InvalidArgumentError(absl::StrCat(what, " render_depth has negative values"));
  // A little slack above 1 for rounding in the compositing.
  if (a.min < 0 || a.max > 1.0001f) {
    return absl::InvalidArgumentError(absl::StrCat(what, " render_alpha has values outside [0, 1]"));
  }
  return absl::OkStatus();
}

absl::Status check_reference(const ReferenceView& r, const std::string& what) {
  return check_view(r.camera, r.image, r.render_depth, r.render_alpha, "image", what);
}

// The request's own fields: its render, strength and that it has references.
absl::Status check_request_fields(const GenerationRequest& q, const std::string& what) {
  GAPS_RETURN_IF_ERROR(check_view(q.camera, q.render_rgb, q.render_depth, q.render_alpha, "render_rgb", what));
  if (!std::isfinite(q.strength) || q.strength < 0 || q.strength > 1) {
    return absl::InvalidArgumentError(absl::StrCat(what, " strength ", q.strength, " is not in [0, 1]"));
  }
  if (q.references.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat(what, " has no references (the reproject backend warps ground-truth views)"));
  }
  return absl::OkStatus();
}

// The same reference: the same tensors with the same camera (a check of one is a check of the other).
bool same_reference(const ReferenceView& a, const ReferenceView& b) {
  const Camera &p = a.camera, &q = b.camera;
  return a.image.unsafeGetTensorImpl() == b.image.unsafeGetTensorImpl() &&
         a.render_depth.unsafeGetTensorImpl() == b.render_depth.unsafeGetTensorImpl() &&
         a.render_alpha.unsafeGetTensorImpl() == b.render_alpha.unsafeGetTensorImpl() && p.width == q.width &&
         p.height == q.height && p.fx == q.fx && p.fy == q.fy && p.cx == q.cx && p.cy == q.cy && p.R == q.R &&
         p.t == q.t;
}

// Every request in order, each with the references the backend uses (the rest are ignored anyway); the first
// problem in that order. The checks read every value, as much work as the warps, so they run in parallel, and a
// reference that several requests carry (in a phase, the nearest few of the same training views) is checked once,
// named after the first request that uses it.
absl::Status check_requests(const std::vector<GenerationRequest>& requests, int num_references) {
  struct Check {
    const GenerationRequest* request = nullptr;  // its own fields, or
    const ReferenceView* reference = nullptr;    // one of its references
    std::string what;
  };
  std::vector<Check> checks;
  std::vector<const ReferenceView*> checked;
  for (size_t i = 0; i < requests.size(); ++i) {
    const std::string what = absl::StrCat("request ", i);
    checks.push_back({&requests[i], nullptr, what});
    const int used = std::min<int>(num_references, static_cast<int>(requests[i].references.size()));
    for (int k = 0; k < used; ++k) {
      const ReferenceView& r = requests[i].references[k];
      if (std::any_of(checked.begin(), checked.end(), [&](const ReferenceView* c) { return same_reference(*c, r); }))
        continue;
      checked.push_back(&r);
      checks.push_back({nullptr, &r, absl::StrCat(what, " reference ", k)});
    }
  }
  std::vector<absl::Status> results(checks.size());
  at::parallel_for(0, static_cast<int64_t>(checks.size()), 1, [&](int64_t begin, int64_t end) {
    for (int64_t c = begin; c < end; ++c) {
      const Check& check = checks[c];
      results[c] = check.request ? check_request_fields(*check.request, check.what)
                                 : check_reference(*check.reference, check.what);
    }
  });
  for (const absl::Status& st : results) GAPS_RETURN_IF_ERROR(st);
  return absl::OkStatus();
}

// ---------------------------------------------------------------------------------------------------
// Step 1: forward warp of one reference.

// A reference pixel lifted to 3D and projected into the pseudo camera.
struct Splat {
  float u, v;   // pseudo-image pixel coordinates (pixel centres at +0.5)
  float z;      // pseudo-camera z
  float alpha;  // reference alpha, scales the splat's weight
  int64_t src;  // reference pixel index
};

struct ReferenceWarp {
  at::Tensor color;        // H x W x 3, splat-weighted mean of the nearest surface; 0 where nothing landed
  at::Tensor weight;       // H x W, W_k: sum of splat weights (tent x alpha) that made the colour
  at::Tensor depth;        // H x W pseudo-camera z of the nearest surface, +inf where nothing landed
  Eigen::Vector3f center;  // reference camera centre in pseudo-camera coordinates
};

// Reference pixels with alpha >= min_alpha at their expected distance depth/alpha (render.h), in the pseudo
// camera. Points behind it or too far outside the image to touch it are dropped.
std::vector<Splat> project_reference(const Camera& ref, const at::Tensor& depth, const at::Tensor& alpha,
                                     const Camera& target, float min_alpha, int footprint) {
  // x_target = M x_ref + b, both in camera coordinates.
  const Eigen::Matrix3f M = (target.R * ref.R.transpose()).cast<float>();
  const Eigen::Vector3f b = (target.t - target.R * ref.R.transpose() * ref.t).cast<float>();
  const float fx = ref.fx, fy = ref.fy, cx = ref.cx, cy = ref.cy;
  const float tfx = target.fx, tfy = target.fy, tcx = target.cx, tcy = target.cy;
  const float margin = static_cast<float>(footprint);
  const float* d = depth.data_ptr<float>();
  const float* a = alpha.data_ptr<float>();
  std::vector<Splat> splats;
  splats.reserve(static_cast<size_t>(ref.width) * ref.height);
  for (int i = 0; i < ref.height; ++i) {
    for (int j = 0; j < ref.width; ++j) {
      const int64_t idx = static_cast<int64_t>(i) * ref.width + j;
      if (!(a[idx] >= min_alpha)) continue;
      const float distance = d[idx] / a[idx];
      if (!(distance > 0)) continue;
      const Eigen::Vector3f ray((j + 0.5f - cx) / fx, (i + 0.5f - cy) / fy, 1.0f);
      const Eigen::Vector3f q = M * (ray.normalized() * distance) + b;
      if (!(q.z() > 0)) continue;
      const float u = tfx * q.x() / q.z() + tcx, v = tfy * q.y() / q.z() + tcy;
      if (!(u > -margin && u < target.width + margin && v > -margin && v < target.height + margin)) continue;
      splats.push_back({u, v, q.z(), a[idx], idx});
    }
  }
  return splats;
}

float tent(float distance, float inv_radius) { return std::max(0.0f, 1.0f - std::abs(distance) * inv_radius); }

// Calls f(pixel index, weight) for the footprint x footprint pseudo pixels whose centres are nearest the
// splat, with tent weights of radius footprint/2 (bilinear weights for 2x2).
template <typename F>
void for_each_footprint_pixel(const Splat& s, int footprint, int width, int height, F&& f) {
  const float radius = 0.5f * footprint, inv_radius = 1.0f / radius;
  const int x0 = static_cast<int>(std::floor(s.u + 0.5f - radius));
  const int y0 = static_cast<int>(std::floor(s.v + 0.5f - radius));
  for (int y = std::max(y0, 0); y < std::min(y0 + footprint, height); ++y) {
    const float wy = tent(y + 0.5f - s.v, inv_radius);
    for (int x = std::max(x0, 0); x < std::min(x0 + footprint, width); ++x) {
      const float w = std::max(kMinSplatWeight, wy * tent(x + 0.5f - s.u, inv_radius));
      f(static_cast<int64_t>(y) * width + x, w);
    }
  }
}

// Soft z-buffer: pass 1 finds the nearest z per pixel, pass 2 averages the splats within the tolerance
// band of it. Averaging (instead of keeping a single winner) turns the splat into proper resampling.
ReferenceWarp splat_reference(const ReferenceView& ref, const Camera& target, const ReprojectOptions& o) {
  const at::Tensor image = cpu_float(ref.image);
  const std::vector<Splat> splats =
      project_reference(ref.camera, cpu_float(ref.render_depth), cpu_float(ref.render_alpha), target,
                        static_cast<float>(o.min_reference_alpha), o.splat_footprint);
  const int w = target.width, h = target.height;
  at::Tensor depth = at::full({h, w}, kInf, at::kFloat);
  at::Tensor weight = at::zeros({h, w}, at::kFloat);
  at::Tensor color = at::zeros({h, w, 3}, at::kFloat);
  float* zbuf = depth.data_ptr<float>();
  float* wsum = weight.data_ptr<float>();
  float* acc = color.data_ptr<float>();
  const float* src = image.data_ptr<float>();

  for (const Splat& s : splats) {
    for_each_footprint_pixel(s, o.splat_footprint, w, h, [&](int64_t p, float) { zbuf[p] = std::min(zbuf[p], s.z); });
  }
  const float band = 1.0f + static_cast<float>(o.depth_tolerance);
  for (const Splat& s : splats) {
    for_each_footprint_pixel(s, o.splat_footprint, w, h, [&](int64_t p, float tw) {
      if (s.z > zbuf[p] * band) return;
      const float sw = tw * s.alpha;
      wsum[p] += sw;
      for (int c = 0; c < 3; ++c) acc[3 * p + c] += sw * src[3 * s.src + c];
    });
  }
  for (int64_t p = 0; p < static_cast<int64_t>(w) * h; ++p) {
    if (wsum[p] > 0) {
      const float inv = 1.0f / wsum[p];
      for (int c = 0; c < 3; ++c) acc[3 * p + c] *= inv;
    }
  }
  const Eigen::Vector3d center = target.R * ref.camera.center() + target.t;
  return {color, weight, depth, center.cast<float>()};
}

// ---------------------------------------------------------------------------------------------------
// Step 2: blend the references.

struct Blend {
  at::Tensor color;    // H x W x 3, 0 where uncovered
  at::Tensor covered;  // H x W bool
};

// Angle (radians) at point X between the rays to the pseudo camera centre (the origin) and to `center`.
float viewing_angle(const Eigen::Vector3f& X, const Eigen::Vector3f& center) {
  const Eigen::Vector3f to_pseudo = -X, to_ref = center - X;
  return std::atan2(to_pseudo.cross(to_ref).norm(), to_pseudo.dot(to_ref));
}

Blend blend_references(const std::vector<ReferenceWarp>& warps, const Camera& target, const ReprojectOptions& o) {
  const int w = target.width, h = target.height;
  const float band = 1.0f + static_cast<float>(o.depth_tolerance);
  const float angle_floor = static_cast<float>(o.angle_floor_deg * kPi / 180.0);
  at::Tensor color = at::zeros({h, w, 3}, at::kFloat);
  at::Tensor covered = at::zeros({h, w}, at::kBool);
  float* out = color.data_ptr<float>();
  bool* cov = covered.data_ptr<bool>();
  std::vector<const float*> zs, ws, cs;
  for (const ReferenceWarp& r : warps) {
    zs.push_back(r.depth.data_ptr<float>());
    ws.push_back(r.weight.data_ptr<float>());
    cs.push_back(r.color.data_ptr<float>());
  }
  for (int i = 0; i < h; ++i) {
    for (int j = 0; j < w; ++j) {
      const int64_t p = static_cast<int64_t>(i) * w + j;
      float zmin = kInf;
      for (const float* z : zs) zmin = std::min(zmin, z[p]);
      if (zmin == kInf) continue;
      cov[p] = true;
      // Another reference may see a nearer surface here; only those on the nearest one take part.
      int on_surface = 0, last = 0;
      for (size_t k = 0; k < warps.size(); ++k) {
        if (zs[k][p] <= zmin * band) {
          ++on_surface;
          last = static_cast<int>(k);
        }
      }
      if (on_surface == 1) {  // its weight would normalise to 1: skip the angle
        for (int ch = 0; ch < 3; ++ch) out[3 * p + ch] = cs[last][3 * p + ch];
        continue;
      }
      const Eigen::Vector3f ray((j + 0.5f - target.cx) / target.fx, (i + 0.5f - target.cy) / target.fy, 1.0f);
      float total = 0, sum[3] = {0, 0, 0};
      for (size_t k = 0; k < warps.size(); ++k) {
        if (zs[k][p] > zmin * band) continue;
        const float theta = viewing_angle(zs[k][p] * ray, warps[k].center);
        const float c = std::min(1.0f, ws[k][p]) / ((theta + angle_floor) * (theta + angle_floor));
        total += c;
        for (int ch = 0; ch < 3; ++ch) sum[ch] += c * cs[k][3 * p + ch];
      }
      for (int ch = 0; ch < 3; ++ch) out[3 * p + ch] = sum[ch] / total;
    }
  }
  return {color, covered};
}

// ---------------------------------------------------------------------------------------------------
// Steps 3 and 4: anchoring on the render, two-stage fill.

// Stage 1 (header, step 3): (1 - sigma) render + sigma warped where both exist, else whichever exists, 0
// where neither.
at::Tensor anchor_on_render(const at::Tensor& render, const at::Tensor& render_covered, const Blend& warp,
                            double sigma) {
  const at::Tensor both = (render_covered & warp.covered).unsqueeze(-1);
  const at::Tensor mixed = (1.0 - sigma) * render + sigma * warp.color;
  const at::Tensor single = at::where(render_covered.unsqueeze(-1), render, warp.color);
  return at::where(both, mixed, single);
}

cv::Mat to_cv_mask(const at::Tensor& mask) {
  at::Tensor bytes = mask.to(at::kByte).mul(255).contiguous();
  return cv::Mat(static_cast<int>(mask.size(0)), static_cast<int>(mask.size(1)), CV_8UC1, bytes.data_ptr<uint8_t>())
      .clone();
}

at::Tensor from_cv_mask(const cv::Mat& mask) {
  return at::from_blob(mask.data, {mask.rows, mask.cols}, at::kByte).gt(0).clone();
}

at::Tensor dilate(const at::Tensor& mask, int size) {
  cv::Mat out;
  cv::dilate(to_cv_mask(mask), out, cv::getStructuringElement(cv::MORPH_RECT, cv::Size(size, size)));
  return from_cv_mask(out);
}

// cv::inpaint takes 3-channel images only as 8 bit; the quantisation only touches the inpainted pixels.
at::Tensor inpaint_telea(const at::Tensor& image, const at::Tensor& mask, double radius) {
  at::Tensor bytes = image.clamp(0, 1).mul(255).round().to(at::kByte).contiguous();
  const cv::Mat src(static_cast<int>(image.size(0)), static_cast<int>(image.size(1)), CV_8UC3,
                    bytes.data_ptr<uint8_t>());
  cv::Mat dst;
  cv::inpaint(src, to_cv_mask(mask), dst, radius, cv::INPAINT_TELEA);
  return at::from_blob(dst.data, {dst.rows, dst.cols, 3}, at::kByte).to(at::kFloat).div(255);
}

// Stage 2 and eq:two_stage. Returns the image and the mask M actually inpainted.
std::pair<at::Tensor, at::Tensor> fill_uncovered(const at::Tensor& stage1, const at::Tensor& uncovered,
                                                 const at::Tensor& fallback_color, const ReprojectOptions& o) {
  if (!uncovered.any().item<bool>()) return {stage1, uncovered};
  if (uncovered.all().item<bool>()) {
    // Nothing to propagate from: a flat colour is the least wrong guess.
    return {fallback_color.view({1, 1, 3}).expand_as(stage1).clone(), uncovered};
  }
  at::Tensor mask = dilate(uncovered, o.inpaint_dilation);
  // Inpainting needs some known pixels; the dilation must not swallow them all.
  if (mask.all().item<bool>()) mask = uncovered;
  const at::Tensor stage2 = inpaint_telea(stage1, mask, o.inpaint_radius);
  return {at::where(mask.unsqueeze(-1), stage2, stage1), mask};
}

ReprojectResult reproject(const GenerationRequest& q, const ReprojectOptions& o) {
  const int used = std::min<int>(o.num_references, static_cast<int>(q.references.size()));
  std::vector<ReferenceWarp> warps;
  for (int k = 0; k < used; ++k) warps.push_back(splat_reference(q.references[k], q.camera, o));
  const Blend warp = blend_references(warps, q.camera, o);

  const at::Tensor render = cpu_float(q.render_rgb);
  const at::Tensor render_covered = cpu_float(q.render_alpha) >= o.render_alpha_threshold;
  const at::Tensor stage1 = anchor_on_render(render, render_covered, warp, q.strength);
  const at::Tensor uncovered = ~(render_covered | warp.covered);
  const at::Tensor fallback = cpu_float(q.references.front().image).mean(at::IntArrayRef{0, 1});
  auto [image, mask] = fill_uncovered(stage1, uncovered, fallback, o);
  return {image.clamp(0, 1).contiguous(), warp.color, warp.covered, render_covered, mask};
}

}  // namespace

const OptionTable<ReprojectOptions>& reproject_option_table() {
  using O = ReprojectOptions;
  static const OptionTable<O> table(
      "reproject",
      {
          number_option<O>("min_reference_alpha", &O::min_reference_alpha, between(0, 1, "(]"),
                           "reference pixels below this alpha are not warped"),
          integer_option<O>("num_references", &O::num_references, at_least(1), "nearest references warped"),
          integer_option<O>("splat_footprint", &O::splat_footprint, between(1, 8, "[]"),
                            "side of the block one reference pixel is splatted to"),
          number_option<O>("depth_tolerance", &O::depth_tolerance, between(0, 1, "[)"),
                           "relative camera-z band of one surface in the soft z-buffer"),
          number_option<O>("angle_floor_deg", &O::angle_floor_deg, between(0, 180, "()"),
                           "degrees added to theta_k in the blend weight"),
          number_option<O>("render_alpha_threshold", &O::render_alpha_threshold, between(0, 1, "(]"),
                           "render alpha at which a pixel is covered"),
          number_option<O>("inpaint_radius", &O::inpaint_radius, between(0, 1000, "()"),
                           "cv::inpaint neighbourhood radius in pixels"),
          integer_option<O>("inpaint_dilation", &O::inpaint_dilation, odd_at_least(1),
                            "side of the uncovered mask's dilation before inpainting"),
      });
  return table;
}

absl::Status validate_reproject_options(const ReprojectOptions& o) { return reproject_option_table().validate(o); }

absl::StatusOr<ReprojectOptions> parse_reproject_options(const std::string& json_or_empty) {
  ReprojectOptions options;
  if (absl::StripAsciiWhitespace(json_or_empty).empty()) return options;
  const nlohmann::json j = nlohmann::json::parse(json_or_empty, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.is_object()) {
    return absl::InvalidArgumentError(absl::StrCat("reproject options must be a JSON object, got: ", json_or_empty));
  }
  GAPS_RETURN_IF_ERROR(reproject_option_table().apply(j, options));
  return options;
}

ReprojectGenerator::ReprojectGenerator(ReprojectOptions options) : options_(std::move(options)) {}

std::string ReprojectGenerator::name() const { return "reproject 1"; }

absl::Status ReprojectGenerator::adapt(const std::vector<ReferenceView>& views,
                                       const std::optional<SceneAdaptation>& adaptation) {
  notes_.clear();
  if (views.empty()) return absl::InvalidArgumentError("reproject adapt: no ground-truth views");
  for (size_t i = 0; i < views.size(); ++i) {
    GAPS_RETURN_IF_ERROR(check_reference(views[i], absl::StrCat("view ", i)));
  }
  if (adaptation && adaptation->lora_steps > 0) {
    notes_.push_back(absl::StrCat("reproject has no model to adapt: the ", adaptation->lora_steps, " LoRA steps (rank ",
                                  adaptation->lora_rank, ") asked for were not run"));
  }
  return absl::OkStatus();
}

absl::StatusOr<ReprojectResult> ReprojectGenerator::generate_one(const GenerationRequest& request) const {
  GAPS_RETURN_IF_ERROR(validate_reproject_options(options_));
  GAPS_RETURN_IF_ERROR(check_requests({request}, options_.num_references));
  try {
    return reproject(request, options_);
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("reproject failed: ", e.what()));
  }
}

absl::StatusOr<std::vector<at::Tensor>> ReprojectGenerator::generate(const std::vector<GenerationRequest>& requests) {
  notes_.clear();
  GAPS_RETURN_IF_ERROR(validate_reproject_options(options_));
  GAPS_RETURN_IF_ERROR(check_requests(requests, options_.num_references));
  // Requests are independent, so they run in parallel; each is computed serially, so the result does not
  // depend on the thread count.
  std::vector<at::Tensor> images(requests.size());
  std::vector<std::string> errors(requests.size());
  at::parallel_for(0, static_cast<int64_t>(requests.size()), 1, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      try {
        images[i] = reproject(requests[i], options_).image;
      } catch (const std::exception& e) {
        errors[i] = e.what();
      }
    }
  });
  for (size_t i = 0; i < requests.size(); ++i) {
    if (!errors[i].empty()) return absl::InternalError(absl::StrCat("reproject request ", i, " failed: ", errors[i]));
  }
  if (auto note = unapplied_ip_adapter_note("reproject has no IP-Adapter", requests)) notes_.push_back(*note);
  return images;
}

}  // namespace gaps

#include "server/finished_model.h"

#include <utility>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/scene/camera_path.h"
#include "rpc/codec.h"
#include "server/job_config.h"

namespace gaps {

absl::StatusOr<FinishedModel> FinishedModels::get(const std::string& job_id) {
  GAPS_ASSIGN_OR_RETURN(const v1::JobStatus job, store_.get(job_id));
  if (job.state() != v1::SUCCEEDED)
    return absl::FailedPreconditionError(absl::StrCat("job ", job_id, " has no finished model"));
  GAPS_ASSIGN_OR_RETURN(const v1::JobSpec spec, store_.spec(job_id));
  FinishedModel out;
  GAPS_ASSIGN_OR_RETURN(out.options, run_options_from_proto(spec.config(), spec.has_points(), "", ""));
  out.options.scene_dir = job_dir(options_, job_id) / "scene";
  std::lock_guard<std::mutex> lock(mutex_);
  if (cached_job_ != job_id || !cached_model_) {
    GAPS_ASSIGN_OR_RETURN(const GaussianModel model,
                          load_gaussians_ply(job_dir(options_, job_id) / "out" / "point_cloud.ply"));
    cached_model_ = std::make_shared<const GaussianModel>(model.to(at::Device(options_.device)));
    cached_job_ = job_id;
  }
  out.model = cached_model_;
  return out;
}

absl::Status render_view(const FinishedModel& finished, const Camera& camera, v1::RenderViewResponse* response) {
  at::AutoGradMode no_grad(false);
  const GaussianModel& model = *finished.model;
  RenderOptions render_options;
  render_options.background = at::full({3}, finished.options.config.background, model.means.options());
  const at::Tensor rgb = render(model, camera, render_options).rgb.clamp(0, 1).cpu();
  return rpc::encode_png(rgb, response->mutable_image());
}

absl::Status job_cameras(const FinishedModel& finished, v1::JobCameras* response) {
  const RunOptions& o = finished.options;
  SceneLoadOptions load;
  load.resolution = o.resolution;
  GAPS_ASSIGN_OR_RETURN(const Scene scene, load_scene(o.scene_dir, load));
  GAPS_ASSIGN_OR_RETURN(const Split split, benchmark_split(static_cast<int>(scene.cameras.size()), o.views));
  std::vector<Camera> train;
  for (int i : split.train) {
    train.push_back(scene.cameras[i]);
    rpc::encode_camera(scene.cameras[i], response->add_train());
  }
  for (int i : split.test) rpc::encode_camera(scene.cameras[i], response->add_test());
  GAPS_ASSIGN_OR_RETURN(const auto bounds, path_depth_bounds(train, finished.model->means));
  response->set_background(o.config.background);
  response->set_near(bounds.first);
  response->set_far(bounds.second);
  return absl::OkStatus();
}

}  // namespace gaps

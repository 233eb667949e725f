#pragma once
// What the Trainer service serves of a SUCCEEDED job's model: RenderView's frames and GetJobCameras' cameras,
// from the model its run left in the job's output folder.
#include <memory>
#include <mutex>
#include <string>

#include "absl/status/statusor.h"
#include "gaps/v1/trainer.pb.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/pipeline.h"
#include "server/job_store.h"
#include "server/trainer_options.h"

namespace gaps {

struct FinishedModel {
  std::shared_ptr<const GaussianModel> model;  // on the service's device
  RunOptions options;                          // the run's, with scene_dir the job's scene
};

// The last job's model stays loaded, so that the frames of a camera path (one RenderView each) do not each
// read its PLY again. Thread-safe.
class FinishedModels {
 public:
  FinishedModels(const TrainerServiceOptions& options, JobStore& store) : options_(options), store_(store) {}
  // FAILED_PRECONDITION for a job that did not succeed.
  absl::StatusOr<FinishedModel> get(const std::string& job_id);

 private:
  const TrainerServiceOptions& options_;
  JobStore& store_;
  std::mutex mutex_;  // guards the two below
  std::string cached_job_;
  std::shared_ptr<const GaussianModel> cached_model_;
};

// The model seen from `camera` over the run's background, as a PNG.
absl::Status render_view(const FinishedModel& finished, const Camera& camera, v1::RenderViewResponse* response);
// The run's training and test cameras as its split chose them, its background and the model's depth bounds:
// what a client builds a camera path from.
absl::Status job_cameras(const FinishedModel& finished, v1::JobCameras* response);

}  // namespace gaps

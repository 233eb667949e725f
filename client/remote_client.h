#pragma once
// Client side of the Trainer service: scene upload (a scene folder loaded as `gaps train` would load it,
// images sent as PNG at the chosen resolution), event watching, job queries, cancellation and artifact
// download. The `gaps submit|watch|list|cancel|fetch` commands and the service tests use it.
#include <chrono>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/statusor.h"
#include "gaps/v1/trainer.grpc.pb.h"
#include "gs_trainer/pipeline.h"
#include "rpc/security.h"

namespace gaps::client {

// A scene ready to upload: cameras (at the upload resolution, undistorted) and their PNG images.
struct PreparedScene {
  std::vector<v1::Camera> cameras;
  std::vector<std::string> images;
  // Some cameras' views at twice their size, PNG, by camera index in increasing order (FileChunk::LARGER_IMAGE).
  std::vector<std::pair<int, std::string>> larger_images;
  std::string points_ply;              // optional initial point cloud
  std::vector<Camera> source_cameras;  // the scene's cameras as loaded, in the order of `cameras`
};

// Loads a scene folder (LLFF, COLMAP or transforms.json) at downscale factor `resolution`.
absl::StatusOr<PreparedScene> prepare_scene(const std::filesystem::path& scene_dir, int resolution);

// Adds to `scene` (prepare_scene's, from options.scene_dir at options.resolution) the job's training views at twice
// their size, read from the scene at half the resolution, when the job's "auto" reads them (auto_reads_larger_views),
// so that the trainer initialises from what `gaps train` would. Nothing otherwise. NotFound, with nothing added,
// when it would but the scene has no views that large (the trainer then reads the training views).
absl::Status add_larger_training_views(const RunOptions& options, PreparedScene* scene);

class TrainerClient {
 public:
  static absl::StatusOr<TrainerClient> connect(const std::string& address, const rpc::ClientSecurity& security);

  // Whether the trainer answers within `timeout` (the connection, TLS handshake included; not the token): an
  // UNAVAILABLE error tagged unreachable (common/error_kind.h) saying what to do otherwise. A refused
  // connection fails at once.
  absl::Status check_reachable(std::chrono::milliseconds timeout) const;

  // Uploads the scene with the spec (its cameras are replaced by the scene's); returns the job id.
  absl::StatusOr<std::string> submit(v1::JobSpec spec, const PreparedScene& scene);
  // Streams events to `on_event` until the job ends; returns its final status.
  absl::StatusOr<v1::JobStatus> watch(const std::string& job_id,
                                      const std::function<void(const v1::JobEvent&)>& on_event,
                                      int64_t from_sequence = 0);
  absl::StatusOr<v1::JobStatus> get(const std::string& job_id);
  absl::StatusOr<std::vector<v1::JobStatus>> list();
  absl::StatusOr<v1::JobStatus> cancel(const std::string& job_id);
  // A finished job's model rendered at `camera`: H x W x 3 in [0, 1]. DEADLINE_EXCEEDED after `deadline`.
  absl::StatusOr<at::Tensor> render(const std::string& job_id, const v1::Camera& camera,
                                    std::chrono::milliseconds deadline = std::chrono::minutes(2));
  // A finished job's cameras as its run split them, background and depth bounds (GetJobCameras).
  absl::StatusOr<v1::JobCameras> job_cameras(const std::string& job_id,
                                             std::chrono::milliseconds deadline = std::chrono::minutes(1));
  // Writes the job's artifacts below `out_dir`; returns their relative paths.
  absl::StatusOr<std::vector<std::string>> fetch(const std::string& job_id, const std::filesystem::path& out_dir);

 private:
  TrainerClient(std::string address, std::shared_ptr<grpc::Channel> channel, rpc::ClientSecurity security);
  // A call's status; an UNAVAILABLE one says what stops the connection when the TLS settings do (gRPC itself
  // reports every TLS failure alike), tagged unreachable.
  absl::Status checked(const grpc::Status& status, const std::string& call) const;
  // Why the channel cannot connect: the TLS settings' problem, or that no trainer listens.
  absl::Status unreachable(const std::string& detail) const;
  // The token; a deadline for the calls that answer at once (GetJob, ListJobs, CancelJob, RenderView,
  // GetJobCameras). The streams have none: WatchJob follows a job for as long as it runs, and SubmitJob and
  // FetchArtifacts move scenes and results whose size sets their time.
  void prepare(grpc::ClientContext& context, std::optional<std::chrono::milliseconds> deadline = std::nullopt) const;

  std::string address_;
  std::shared_ptr<grpc::Channel> channel_;
  std::shared_ptr<v1::Trainer::Stub> stub_;
  rpc::ClientSecurity security_;
};

}  // namespace gaps::client

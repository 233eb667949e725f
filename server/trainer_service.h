#pragma once
// The Trainer gRPC service: validates and stores uploaded scenes, runs training jobs it claims from the job
// store's queue (a configurable number at once, each under a lease it renews), records everything in the
// store (so a restarted trainer, or another replica of a shared PostgreSQL store, knows every job, replays
// its events and takes over the ones whose runner died) and serves events, artifacts and renders. Jobs of the method
// variants get pseudo-views from a pool of diffusion workers (server/remote_generator.h); a phase no worker answers is
// skipped and reported, never fatal. A write the job store refuses is never dropped silently: a submission or
// cancellation fails with the store's error, a lost event or progress update of a running job is logged with the job
// id, and a job end the store refused is retried in the background while GetJob/ListJobs/WatchJob report it as
// unrecorded. The jobs run in server/job_runner.h; artifacts are server/artifacts.h's, renders
// server/finished_model.h's; this class answers the RPCs.
#include <atomic>
#include <memory>
#include <string>

#include "gaps/v1/trainer.grpc.pb.h"
#include "server/data_dir_lock.h"
#include "server/finished_model.h"
#include "server/job_runner.h"
#include "server/job_store.h"
#include "server/trainer_options.h"

namespace gaps {

class TrainerService final : public v1::Trainer::Service {
 public:
  static absl::StatusOr<std::unique_ptr<TrainerService>> create(TrainerServiceOptions options);
  ~TrainerService() override;

  // Starts the job threads, which claim queued jobs and jobs whose runner died (with SQLite: every job a
  // previous process left running).
  absl::Status start();
  // Stops taking jobs, interrupts running ones without marking them finished (they go on after a restart or
  // on another replica, from their checkpoint) and joins the threads.
  void shutdown();
  const std::string& replica_id() const { return options_.replica_id; }
  std::string store_description() const { return store_->describe(); }

  grpc::Status SubmitJob(grpc::ServerContext* context, grpc::ServerReader<v1::SubmitJobRequest>* reader,
                         v1::SubmitJobResponse* response) override;
  grpc::Status WatchJob(grpc::ServerContext* context, const v1::WatchJobRequest* request,
                        grpc::ServerWriter<v1::JobEvent>* writer) override;
  grpc::Status GetJob(grpc::ServerContext* context, const v1::GetJobRequest* request, v1::JobStatus* response) override;
  grpc::Status ListJobs(grpc::ServerContext* context, const v1::ListJobsRequest* request,
                        v1::ListJobsResponse* response) override;
  grpc::Status CancelJob(grpc::ServerContext* context, const v1::CancelJobRequest* request,
                         v1::JobStatus* response) override;
  grpc::Status FetchArtifacts(grpc::ServerContext* context, const v1::FetchArtifactsRequest* request,
                              grpc::ServerWriter<v1::ArtifactChunk>* writer) override;
  grpc::Status RenderView(grpc::ServerContext* context, const v1::RenderViewRequest* request,
                          v1::RenderViewResponse* response) override;
  grpc::Status GetJobCameras(grpc::ServerContext* context, const v1::GetJobCamerasRequest* request,
                             v1::JobCameras* response) override;

 private:
  TrainerService(TrainerServiceOptions options, std::unique_ptr<DataDirLock> lock, std::unique_ptr<JobStore> store);

  TrainerServiceOptions options_;
  std::unique_ptr<DataDirLock> lock_;  // held for the service's lifetime
  std::unique_ptr<JobStore> store_;
  JobRunner runner_;                       // after what it uses: it stops before they go
  FinishedModels models_;                  // RenderView's and GetJobCameras'
  std::atomic<int> renders_in_flight_{0};  // RenderView calls being served (at most kMaxConcurrentRenders)
  std::atomic<int> watch_streams_{0};      // open WatchJob streams (at most kMaxWatchStreams)
};

}  // namespace gaps

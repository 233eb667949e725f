#include "server/trainer_service.h"

#include <unistd.h>

#include <cstdio>

#include <algorithm>
#include <chrono>
#include <mutex>
#include <random>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "common/io_util.h"
#include "common/limits.h"
#include "common/status_macros.h"
#include "rpc/codec.h"
#include "rpc/security.h"
#include "server/artifacts.h"
#include "server/job_config.h"
#include "server/job_events.h"
#include "server/scene_upload.h"

namespace gaps {
namespace {

// One request of a kind that the trainer serves a bounded number of at once (kMaxConcurrentRenders,
// kMaxWatchStreams): taken() is false beyond the limit, and the slot is given back when it goes.
class InFlightSlot {
 public:
  InFlightSlot(std::atomic<int>& count, int limit) : count_(count), taken_(count.fetch_add(1) < limit) {
    if (!taken_) count_.fetch_sub(1);
  }
  ~InFlightSlot() {
    if (taken_) count_.fetch_sub(1);
  }
  InFlightSlot(const InFlightSlot&) = delete;
  InFlightSlot& operator=(const InFlightSlot&) = delete;
  bool taken() const { return taken_; }

 private:
  std::atomic<int>& count_;
  bool taken_;
};

grpc::Status busy(const std::string& what, int limit) {
  return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED, absl::StrCat("the trainer serves ", limit, " ", what,
                                                                         " at once and all are taken; retry in a "
                                                                         "few seconds"));
}

namespace fs = std::filesystem;

std::string new_job_id() {
  static std::mt19937_64 rng(std::random_device{}());
  static std::mutex mutex;
  std::lock_guard<std::mutex> lock(mutex);
  return absl::StrFormat("job-%012x", rng() & 0xffffffffffffULL);
}

std::string default_replica_id() {
  char host[256] = {0};
  if (gethostname(host, sizeof(host) - 1) != 0) std::snprintf(host, sizeof(host), "trainer");
  static std::mt19937_64 rng(std::random_device{}());
  return absl::StrFormat("%s-%d-%06x", host, static_cast<int>(getpid()), rng() & 0xffffff);
}

// Upload folders not touched for `age`: what a trainer that died while receiving them left behind.
void remove_stale_uploads(const fs::path& uploads, std::chrono::hours age) {
  std::error_code ec;
  const auto now = fs::file_time_type::clock::now();
  for (const auto& entry : fs::directory_iterator(uploads, ec)) {
    const auto written = entry.last_write_time(ec);
    if (!ec && now - written > age) remove_tree(entry.path());
  }
}

absl::Status move_folder(const fs::path& from, const fs::path& to) {
  std::error_code ec;
  fs::create_directories(to.parent_path(), ec);
  if (!ec) fs::rename(from, to, ec);
  if (ec) return absl::ResourceExhaustedError(absl::StrCat("the trainer could not store the upload: ", ec.message()));
  return absl::OkStatus();
}

}  // namespace

TrainerService::TrainerService(TrainerServiceOptions options, std::unique_ptr<DataDirLock> lock,
                               std::unique_ptr<JobStore> store)
    : options_(std::move(options)),
      lock_(std::move(lock)),
      store_(std::move(store)),
      runner_(options_, *store_),
      models_(options_, *store_) {}

TrainerService::~TrainerService() { shutdown(); }

absl::StatusOr<std::unique_ptr<TrainerService>> TrainerService::create(TrainerServiceOptions options) {
  if (options.data_dir.empty()) return absl::InvalidArgumentError("the trainer needs a data folder");
  if (options.concurrency < 1) return absl::InvalidArgumentError("concurrency must be at least 1");
  if (options.threads_per_job < 0)
    return absl::InvalidArgumentError("threads_per_job must be 0 (automatic) or positive");
  if (!(options.lease_seconds > 0)) return absl::InvalidArgumentError("the lease must last longer than 0 seconds");
  if (options.replica_id.empty()) options.replica_id = default_replica_id();
  std::error_code ec;
  fs::create_directories(options.data_dir / "jobs", ec);
  if (ec) return absl::PermissionDeniedError(absl::StrCat(options.data_dir.string(), ": ", ec.message()));
  const bool shared = !options.job_store.empty();
  GAPS_ASSIGN_OR_RETURN(std::unique_ptr<DataDirLock> lock, DataDirLock::acquire(options.data_dir, shared));
  GAPS_ASSIGN_OR_RETURN(std::unique_ptr<JobStore> store, JobStore::open_location(options.job_store, options.data_dir));
  return std::unique_ptr<TrainerService>(new TrainerService(std::move(options), std::move(lock), std::move(store)));
}

absl::Status TrainerService::start() {
  if (store_->shared()) {
    // Other replicas may be receiving uploads right now: only what no upload can still be using goes.
    remove_stale_uploads(options_.data_dir / "uploads", std::chrono::hours(24));
  } else {
    // This process holds the folder alone: uploads being received when an earlier one stopped never
    // became jobs, and the leases of jobs it ran died with it (they are taken over at once).
    remove_tree(options_.data_dir / "uploads");
    GAPS_RETURN_IF_ERROR(store_->expire_leases());
  }
  runner_.start();
  return absl::OkStatus();
}

void TrainerService::shutdown() { runner_.shutdown(); }

grpc::Status TrainerService::SubmitJob(grpc::ServerContext* context, grpc::ServerReader<v1::SubmitJobRequest>* reader,
                                       v1::SubmitJobResponse* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  // The upload streams into a staging folder and becomes the job's scene only once checked whole, so a
  // trainer that dies mid-upload leaves no half-written job behind (start() clears what it left, with a
  // shared store once it is a day old).
  const std::string job_id = new_job_id();
  const fs::path staging = options_.data_dir / "uploads" / job_id;
  const fs::path dir = job_dir(options_, job_id);
  absl::StatusOr<SceneUpload> received = receive_upload(
      [reader](v1::SubmitJobRequest* part) { return reader->Read(part); }, options_.max_upload_bytes, staging);
  absl::Status stored_scene = received.ok() ? write_uploaded_scene(*received) : received.status();
  if (stored_scene.ok()) stored_scene = move_folder(staging, dir / "scene");
  if (!stored_scene.ok()) {
    remove_tree(staging);
    remove_tree(dir);
    return rpc::to_grpc(stored_scene);
  }
  const SceneUpload& upload = *received;
  v1::JobStatus status;
  status.set_job_id(job_id);
  status.set_name(upload.spec.name());
  status.set_state(v1::QUEUED);
  status.set_submitted_at(now_seconds());
  absl::StatusOr<RunOptions> o =
      run_options_from_proto(upload.spec.config(), upload.spec.has_points(), "", options_.device);
  status.set_iterations(o.ok() ? o->config.iterations : 0);
  if (auto st = store_->insert(status, upload.spec); !st.ok()) {
    remove_tree(dir);
    return rpc::to_grpc(st);
  }
  v1::JobEvent queued = event_for(job_id);
  queued.set_state_changed(v1::QUEUED);
  runner_.publish(queued);
  runner_.job_queued();
  response->set_job_id(job_id);
  return grpc::Status::OK;
}

grpc::Status TrainerService::WatchJob(grpc::ServerContext* context, const v1::WatchJobRequest* request,
                                      grpc::ServerWriter<v1::JobEvent>* writer) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  if (auto job = store_->get(request->job_id()); !job.ok()) return rpc::to_grpc(job.status());
  const InFlightSlot slot(watch_streams_, kMaxWatchStreams);
  if (!slot.taken()) return busy("WatchJob streams", kMaxWatchStreams);
  int64_t next = std::max<int64_t>(0, request->from_sequence());
  bool read_again = false;
  while (!context->IsCancelled()) {
    absl::StatusOr<std::vector<v1::JobEvent>> events = store_->events(request->job_id(), next);
    if (!events.ok()) return rpc::to_grpc(events.status());
    for (const auto& e : *events) {
      if (!writer->Write(e)) return grpc::Status(grpc::StatusCode::CANCELLED, "watcher went away");
      next = e.sequence() + 1;
      if (e.has_finished() || e.has_failed() || e.has_cancelled()) return grpc::Status::OK;
    }
    // Its end will not be in the events until the store takes it; but a retry may have recorded it since the read
    // above (and not yet dropped its unrecorded entry), so the events are read once more before the error goes.
    if (auto st = runner_.unrecorded_end(request->job_id()); !st.ok()) {
      if (!std::exchange(read_again, true)) continue;
      return rpc::to_grpc(st);
    }
    read_again = false;
    if (!runner_.wait_for_events(std::chrono::milliseconds(250)))
      return grpc::Status(grpc::StatusCode::UNAVAILABLE, "trainer shutting down");
  }
  return grpc::Status(grpc::StatusCode::CANCELLED, "watcher went away");
}

grpc::Status TrainerService::GetJob(grpc::ServerContext* context, const v1::GetJobRequest* request,
                                    v1::JobStatus* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  absl::StatusOr<v1::JobStatus> job = store_->get(request->job_id());
  if (!job.ok()) return rpc::to_grpc(job.status());
  *response = *job;
  runner_.note_unrecorded_end(*response);
  return grpc::Status::OK;
}

grpc::Status TrainerService::ListJobs(grpc::ServerContext* context, const v1::ListJobsRequest*,
                                      v1::ListJobsResponse* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  absl::StatusOr<std::vector<v1::JobStatus>> jobs = store_->list();
  if (!jobs.ok()) return rpc::to_grpc(jobs.status());
  for (auto& j : *jobs) {
    runner_.note_unrecorded_end(j);
    *response->add_jobs() = std::move(j);
  }
  return grpc::Status::OK;
}

grpc::Status TrainerService::CancelJob(grpc::ServerContext* context, const v1::CancelJobRequest* request,
                                       v1::JobStatus* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  absl::StatusOr<v1::JobStatus> job = store_->get(request->job_id());
  if (!job.ok()) return rpc::to_grpc(job.status());
  if (terminal(job->state()))
    return grpc::Status(
        grpc::StatusCode::FAILED_PRECONDITION,
        absl::StrCat("job ", request->job_id(), " already ended (", v1::JobState_Name(job->state()), ")"));
  if (auto st = runner_.unrecorded_end(request->job_id()); !st.ok())
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION, std::string(st.message()));
  v1::JobStatus cancelled = *job;
  cancelled.set_state(v1::CANCELLED);
  cancelled.set_error("cancelled before it started");
  cancelled.set_finished_at(now_seconds());
  v1::JobEvent closing = closing_event(cancelled);
  // A job nobody runs ends here; a running one (here or on another replica) gets the request and stops at
  // its next iteration, in its own thread.
  const absl::StatusOr<bool> ended = store_->cancel(cancelled, closing);
  if (!ended.ok()) {
    if (ended.status().code() == absl::StatusCode::kFailedPrecondition) return rpc::to_grpc(ended.status());
    return rpc::to_grpc(absl::Status(
        ended.status().code(), absl::StrCat("job ", request->job_id(), " stays queued: ", ended.status().message())));
  }
  if (*ended) {
    runner_.job_ended();
    *response = cancelled;
    return grpc::Status::OK;
  }
  runner_.cancel_if_running(request->job_id());
  *response = *job;
  return grpc::Status::OK;
}

grpc::Status TrainerService::FetchArtifacts(grpc::ServerContext* context, const v1::FetchArtifactsRequest* request,
                                            grpc::ServerWriter<v1::ArtifactChunk>* writer) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  absl::StatusOr<v1::JobStatus> job = store_->get(request->job_id());
  if (!job.ok()) return rpc::to_grpc(job.status());
  if (!terminal(job->state()))
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        absl::StrCat("job ", request->job_id(), " is ", v1::JobState_Name(job->state()),
                                     "; artifacts are served once it ends"));
  absl::StatusOr<std::vector<JobStore::Artifact>> artifacts = store_->artifacts(request->job_id());
  if (!artifacts.ok()) return rpc::to_grpc(artifacts.status());
  return stream_artifacts(job_dir(options_, request->job_id()) / "out", *artifacts, writer);
}

grpc::Status TrainerService::RenderView(grpc::ServerContext* context, const v1::RenderViewRequest* request,
                                        v1::RenderViewResponse* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  // Before anything is decoded or allocated: a render's memory grows with its pixels.
  if (auto st = check_render_size("camera", request->camera().width(), request->camera().height()); !st.ok())
    return rpc::to_grpc(st);
  absl::StatusOr<Camera> camera = rpc::decode_camera(request->camera(), "camera");
  if (!camera.ok()) return rpc::to_grpc(camera.status());
  const InFlightSlot slot(renders_in_flight_, kMaxConcurrentRenders);
  if (!slot.taken()) return busy("renders", kMaxConcurrentRenders);
  absl::StatusOr<FinishedModel> finished = models_.get(request->job_id());
  if (!finished.ok()) return rpc::to_grpc(finished.status());
  return rpc::to_grpc(render_view(*finished, *camera, response));
}

grpc::Status TrainerService::GetJobCameras(grpc::ServerContext* context, const v1::GetJobCamerasRequest* request,
                                           v1::JobCameras* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  absl::StatusOr<FinishedModel> finished = models_.get(request->job_id());
  if (!finished.ok()) return rpc::to_grpc(finished.status());
  return rpc::to_grpc(job_cameras(*finished, response));
}

}  // namespace gaps

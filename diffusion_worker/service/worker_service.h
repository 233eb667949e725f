#pragma once
// The DiffusionWorker gRPC service: hosts one in-process generator backend (diffusion_worker/) for remote
// trainers. Calls run one at a time on the backend; up to `queue_capacity` more wait, later ones are
// answered RESOURCE_EXHAUSTED at once. A call whose deadline passes while it waits is answered
// DEADLINE_EXCEEDED without running. The backend's notes (Generator::notes()) go back with each answer.
#include <condition_variable>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "gaps/v1/diffusion_worker.grpc.pb.h"
#include "gs_trainer/gaps/generator.h"
#include "rpc/generation_codec.h"
#include "rpc/shared_memory.h"

namespace gaps {

struct WorkerServiceOptions {
  std::string backend;  // registry name, reported by GetInfo
  std::string device = "cpu";
  int max_batch = 64;                       // poses per Generate call
  uint64_t max_request_bytes = 1ull << 30;  // serialized request size limit
  int queue_capacity = 4;                   // calls that may wait behind the running one
  std::string token;                        // required bearer token (empty: none)
  // Accept payloads in shared memory from trainers that share this host's /dev/shm (rpc/shared_memory.h).
  bool shared_memory = true;
  // Convert the answer's images one by one while the converted ones are sent (rpc/streamed_send.h); false:
  // convert them all, then send (kept for side-by-side measurement in bench/rpc_bench).
  bool convert_while_sending = true;
  // When scenes alternate (jobs sharing the worker), install what a scene's adaptation learnt when it comes
  // back; false: adapt it anew each time (LoRA training again; kept for side-by-side measurement).
  bool keep_scene_adaptations = true;
  // Scenes kept at most (reference views and what their adaptation learnt, e.g. 13 MB of LoRA adapters): past
  // it the least recently used is forgotten, and a Generate for it gets NOT_FOUND, on which a trainer adapts the
  // worker again. Trainers release their scenes when a job ends; this bounds what crashed ones leave behind.
  int max_scenes = 16;
};

class WorkerService final : public v1::DiffusionWorker::Service {
 public:
  WorkerService(std::unique_ptr<Generator> generator, WorkerServiceOptions options);

  grpc::Status GetInfo(grpc::ServerContext* context, const v1::GetInfoRequest* request,
                       v1::WorkerInfo* response) override;
  grpc::Status AdaptScene(grpc::ServerContext* context,
                          grpc::ServerReaderWriter<v1::AdaptSceneProgress, v1::Chunk>* stream) override;
  grpc::Status Generate(grpc::ServerContext* context, grpc::ServerReaderWriter<v1::Chunk, v1::Chunk>* stream) override;
  grpc::Status ReleaseScene(grpc::ServerContext* context, const v1::ReleaseSceneRequest* request,
                            v1::ReleaseSceneResponse* response) override;
  // The scene's Generator::export_adaptation, kept when the scene was adapted (empty for a backend that learns
  // nothing to hand over); NOT_FOUND for an unknown handle.
  grpc::Status ExportAdaptation(grpc::ServerContext* context, const v1::ExportAdaptationRequest* request,
                                grpc::ServerWriter<v1::Chunk>* writer) override;

 private:
  class BackendTurn;
  // Admission to the backend: RESOURCE_EXHAUSTED when the queue is full, DEADLINE_EXCEEDED or CANCELLED
  // when the call ends while waiting. On OK the caller holds the backend until `turn` is destroyed.
  grpc::Status wait_for_backend(grpc::ServerContext* context, std::unique_ptr<BackendTurn>* turn);
  // Makes the backend adapted to `handle` (again when another scene was adapted since: installing what its
  // adaptation learnt, or adapting anew); says which it did. Needs the turn.
  enum class Readaptation { kNone, kInstalled, kAdapted };
  absl::StatusOr<Readaptation> ensure_adapted(const std::string& handle);
  // The batch's shared region mapped (null when it has none); FAILED_PRECONDITION when this worker offers no
  // shared memory, the mapping's error when the caller's region cannot be opened here.
  // Beyond max_scenes, forgets the least recently used scenes (under mutex_).
  void forget_oldest_scenes();
  // Drops everything kept for the scene (under mutex_); false when there was none.
  bool forget_scene(const std::string& handle);
  absl::StatusOr<std::unique_ptr<rpc::SharedRegion>> open_region(const v1::GenerateBatch& batch);

  std::unique_ptr<Generator> generator_;
  WorkerServiceOptions options_;
  std::unique_ptr<rpc::SharedMemoryProbe> probe_;  // null: no shared memory offered
  std::mutex mutex_;
  std::condition_variable backend_free_;
  bool backend_busy_ = false;
  int waiting_ = 0;
  // Adapted scenes: their reference views, adaptation and what another worker learnt for them (when it came
  // with the AdaptScene call), so the backend can be re-adapted when scenes alternate.
  std::map<std::string, rpc::AdaptRequest> scenes_;
  // What the backend's own adaptation learnt per scene (Generator::export_adaptation; empty: nothing to keep).
  std::map<std::string, std::string> learnt_;
  std::map<std::string, uint64_t> last_use_;  // per scene: use_clock_ at its AdaptScene or latest Generate
  uint64_t use_clock_ = 0;
  std::string adapted_handle_;
  uint64_t next_handle_ = 1;
};

}  // namespace gaps

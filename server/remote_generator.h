#pragma once
#include <functional>
// A gaps::Generator that asks diffusion workers (gaps-worker) over gRPC. It spreads each call's poses over
// the pool's usable workers (fan_out), skips workers that failed recently until a health check passes again,
// retries with exponential backoff, and puts a deadline on every RPC. When no worker answers, generate() and adapt()
// return UNAVAILABLE, which the training loop treats as "skip this phase" (gs_trainer/gaps/training.h).
#include <chrono>
#include <condition_variable>
#include <future>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "gaps/v1/diffusion_worker.grpc.pb.h"
#include "gaps/v1/diffusion_worker.pb.h"
#include "gs_trainer/gaps/generator.h"
#include "rpc/codec.h"
#include "rpc/security.h"

namespace gaps {

struct WorkerPoolOptions {
  // HOST:PORT addresses, or dns:///NAME:PORT names that stand for every address NAME resolves to (a
  // Kubernetes headless Service: one per worker pod); see resolve_worker_addresses.
  std::vector<std::string> addresses;
  rpc::ClientSecurity security;
  std::chrono::milliseconds generate_timeout{300000};  // per Generate / AdaptScene call
  std::chrono::milliseconds probe_timeout{2000};       // per health check
  int max_rounds = 3;                                  // passes over the pool before giving up
  std::chrono::milliseconds backoff_initial{200};      // wait after a failed pass, doubled each pass
  std::chrono::milliseconds backoff_max{5000};
  // A worker that failed is not called again before this long, unless a health check says it is back.
  std::chrono::milliseconds failure_cooldown{10000};
  std::string scene_id;  // passed to AdaptScene (e.g. the job id)
  // Polled while a call is in flight: once it is true the call is cancelled (a cancelled job or a stopping
  // trainer does not wait out generate_timeout on a worker that never answers) and generate() returns
  // UNAVAILABLE, so that the phase is skipped and recorded as such.
  std::function<bool()> should_stop;
  // How renders, reference photos and the answer's images travel: kUint8 (a quarter of the bytes; 8-bit
  // photographs lose nothing) or kFloat32 (what an in-process backend sees, bit for bit).
  rpc::TensorEncoding encoding = rpc::TensorEncoding::kUint8;
  // How depth maps travel; unset: rpc::depth_encoding_for(encoding, whether the call uses shared memory).
  std::optional<rpc::TensorEncoding> depth_encoding;
  // Pass payloads through shared memory to workers that share this host's /dev/shm (found out per worker by
  // its probe, rpc/shared_memory.h); the others, and all when false, get them in the messages.
  bool shared_memory = true;
  // Convert the payloads pose by pose while the converted poses are sent (rpc/streamed_send.h); false: convert
  // them all, then send (the hand-over before that, kept for side-by-side measurement in bench/rpc_bench).
  bool convert_while_sending = true;
  // Split every generate() call into contiguous shards, one per usable worker, asked at once, so that a
  // phase's pseudo-views are made by every GPU of the pool; a shard whose worker fails goes to the others.
  // Shards are sized by each worker's measured speed (shard_sizes), so that a worker on a GPU it shares with
  // the trainer, or on a slower one, does not hold the phase up.
  // Each worker is adapted to the scene before its first shard: an adaptation that trains (sdxl's LoRA) runs
  // on every worker, in parallel. False: one worker per call, the others stand by.
  bool fan_out = true;
  // With fan_out, generate() waits for the workers' background adaptations (adapt()) until one has ended and then
  // at most this much longer; a worker still adapting then sits out the calls until its adaptation ends, so that
  // one whose adaptation is slow (on the GPU the trainer trains on) does not hold the first phases up.
  std::chrono::milliseconds adaptation_grace{1000};
  // With fan_out, the first worker of the pool adapts to the scene and the others install what it learnt
  // (ExportAdaptation; sdxl: its LoRA adapters) instead of each training its own: one LoRA training per scene
  // instead of one per worker, and every worker's pseudo-views from the same adapters. A worker with other
  // weights, or one that cannot install them, adapts itself. List first the worker whose GPU is not the trainer's.
  bool share_adaptation = true;
  // How long the other workers wait for the first one's adaptation before adapting themselves (a first worker
  // that hangs must not hold the job up for generate_timeout; sdxl's LoRA training takes 5-20 s on a GPU).
  std::chrono::milliseconds share_wait{60000};
};

// The workers behind `targets`: a dns:///NAME:PORT (or dns:NAME:PORT) target becomes one HOST:PORT per
// address NAME resolves to now; anything else stays as it is, and so does a name that resolves to nothing
// (gRPC then reports it unreachable, like any worker that is down). The pool resolves names itself rather
// than leave them to gRPC's load balancing, because a worker keeps per-scene state (the adaptation made by
// AdaptScene) that the scene's Generate calls must find: each address is one worker.
std::vector<std::string> resolve_worker_addresses(const std::vector<std::string>& targets);

// How many of `poses` consecutive poses each worker is given, in proportion to its speed (1 / its seconds per
// pose, measured on its earlier shards; 0: not measured yet, counted as the mean of the measured ones, so an
// unmeasured pool splits evenly). Every worker gets at least one pose, so that its speed keeps being measured;
// needs poses >= seconds_per_pose.size() >= 1. The sizes sum to `poses`.
std::vector<size_t> shard_sizes(size_t poses, const std::vector<double>& seconds_per_pose);

class RemoteGenerator final : public Generator {
 public:
  static absl::StatusOr<std::unique_ptr<RemoteGenerator>> create(WorkerPoolOptions options);
  ~RemoteGenerator() override;

  // "remote <backend version>" once a worker answered GetInfo, else "remote (no worker reached yet)".
  std::string name() const override;
  // Remembers the views and the adaptation and starts adapting the workers in the background (every usable
  // worker with fan_out, else the one asked next), so that a LoRA trains while the model does; returns at once.
  // generate() waits for those calls (with fan_out, for the first and adaptation_grace more: a worker still
  // adapting sits out the call); a worker whose adaptation failed is marked failed, and any worker not adapted
  // yet is adapted before it generates.
  absl::Status adapt(const std::vector<ReferenceView>& views,
                     const std::optional<SceneAdaptation>& adaptation) override;
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override;
  // After generate(): the answering worker's notes, "<address>: <note>", those of its adaptation (when this
  // call adapted it) first.
  std::vector<std::string> notes() const override { return notes_; }
  // After generate(), summed over the workers that shared the call: "adapt_scene" (the AdaptScene call, LoRA
  // training included, when this call or the adaptation adapt() started adapted the worker), "adaptation_wait"
  // (how long this call waited for that background adaptation; the rest of it overlapped training), "worker_generate"
  // (the backend's own seconds), "transfer" (the rest of the Generate call), its parts on this side ("client_encode":
  // tensors laid out and converted into the message or shared memory, on a thread of their own that overlaps
  // "client_send": the request serialised and sent as its parts are converted, "client_receive": from the last chunk
  // sent to the answer parsed, the worker's work included, "client_decode") and on the worker's
  // (GenerateResult.transfer_seconds; its "worker_encode" overlaps its sending likewise), and the backend's stages
  // (GenerateResult.stage_seconds) of the answering worker.
  std::map<std::string, double> stage_seconds() const override { return stage_seconds_; }
  // After generate(): "request_bytes" and "answer_bytes" (serialized messages), "shared_memory_bytes" (payload
  // passed through shared memory), summed over the answering workers' calls, "shared_memory" (1 when one of
  // them used it), "workers" (how many workers answered a shard) and, when the call was shared, "shard
  // <address>" (the poses given to that worker).
  std::map<std::string, double> counters() const override { return counters_; }

 private:
  struct Worker;
  // What the calls that made one shard report: their stages, counters and the workers' notes.
  struct Attempt {
    std::map<std::string, double> stages, counters;
    std::vector<std::string> notes;
    void add(const Attempt& other);
  };
  explicit RemoteGenerator(WorkerPoolOptions options);
  // True when the worker may be called now (healthy, or its cooldown passed and a probe succeeded).
  bool usable(Worker& worker);
  absl::Status probe(Worker& worker);
  // Adapts the worker unless it is adapted to the current views, installing the shared adaptation where one
  // fits it (export_for); appends the worker's notes to the attempt.
  absl::Status adapt_on(Worker& worker, Attempt& attempt);
  // ReleaseScene of `handle` on the worker, best effort (a short deadline, errors ignored).
  void release_scene(Worker& worker, const std::string& handle);
  // One AdaptScene call, installing `exported` when it is not empty.
  absl::Status call_adapt_scene(Worker& worker, Attempt& attempt, const std::string& exported);
  // After the worker adapted to the current views: its ExportAdaptation, kept as shared_export_ (a failure is
  // a note: the other workers then adapt themselves).
  void fetch_export(Worker& worker, Attempt& attempt);
  // The shared adaptation when it is for the current views and the worker's weights, else empty.
  std::string export_for(const Worker& worker);
  // One Generate call; through shared memory when the worker shares it, falling back to the messages (with
  // a note) when the worker cannot open the region after all.
  absl::StatusOr<std::vector<at::Tensor>> generate_on(Worker& worker, const std::vector<GenerationRequest>& requests,
                                                      Attempt& attempt);
  // The worker's notes go to *worker_notes (kept only when the call is the one that answers).
  absl::StatusOr<std::vector<at::Tensor>> call_generate(Worker& worker, const std::vector<GenerationRequest>& requests,
                                                        bool shared, Attempt& attempt,
                                                        std::vector<std::string>* worker_notes);
  // adapt_on, then generate_on; a worker that no longer knows its scene handle (restarted between two calls,
  // so no call failed to tell us) is adapted again and asked once more.
  absl::StatusOr<std::vector<at::Tensor>> adapt_and_generate_on(Worker& worker,
                                                                const std::vector<GenerationRequest>& requests,
                                                                Attempt& attempt);
  // The whole of `requests` from one worker, the next usable one in round-robin order, moving on when one
  // fails, for max_rounds passes over the pool.
  absl::StatusOr<std::vector<at::Tensor>> generate_with_failover(const std::vector<GenerationRequest>& requests,
                                                                 Attempt& attempt);
  // One shard per worker of `ready`, asked at once; a shard whose worker failed goes to generate_with_failover.
  absl::StatusOr<std::vector<at::Tensor>> generate_fanned_out(const std::vector<GenerationRequest>& requests,
                                                              const std::vector<Worker*>& ready, Attempt& attempt);
  bool stopping() const { return options_.should_stop && options_.should_stop(); }
  void mark_failed(Worker& worker);
  // adapt()'s background AdaptScene calls, one thread per worker (each writes only its worker and its Attempt).
  void start_adaptation();
  struct Adaptation;
  // One worker's AdaptScene call; a worker that failed in a way another worker may not sits out its cooldown.
  void adapt_in_background(Adaptation& a);
  // Waits for all of them (`all`), or until one has ended and adaptation_grace has passed since; the stages and
  // notes of those that ended go to *into (when given), the wait to its "adaptation_wait", and the workers still
  // adapting to adapting_, which no call uses until their adaptation ends.
  void join_adaptation(Attempt* into, bool all);
  // The usable workers that are not adapting.
  std::vector<Worker*> ready_workers();

  WorkerPoolOptions options_;
  std::vector<std::unique_ptr<Worker>> workers_;
  size_t next_ = 0;  // round-robin start
  std::vector<ReferenceView> views_;
  std::optional<SceneAdaptation> adaptation_;
  uint64_t views_version_ = 0;
  std::vector<std::string> notes_;
  std::map<std::string, double> stage_seconds_;
  std::map<std::string, double> counters_;
  mutable std::mutex name_mutex_;
  std::string backend_version_;
  // One background adaptation: its worker, what it reports, its thread (at a fixed address while it runs).
  struct Adaptation {
    Worker* worker = nullptr;
    Attempt attempt;
    std::future<void> call;
    bool ended = false;  // under adaptation_mutex_
  };
  std::set<Worker*> adapting_;  // workers whose adaptation is still running (join_adaptation)
  std::mutex adaptation_mutex_;
  std::condition_variable adaptation_ended_;
  // When the first of the current views' adaptations ended (under adaptation_mutex_).
  std::optional<std::chrono::steady_clock::time_point> first_adaptation_end_;
  // The first worker's exported adaptation (under adaptation_mutex_).
  struct SharedExport {
    uint64_t views_version = 0;
    std::string weights_identity, adaptation;
  };
  std::optional<SharedExport> shared_export_;
  std::vector<std::unique_ptr<Adaptation>> adaptations_;  // declared last: joined (destroyed) before the rest
};

}  // namespace gaps

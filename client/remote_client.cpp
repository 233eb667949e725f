#include "client/remote_client.h"

#include <fstream>
#include <optional>

#include "absl/strings/str_cat.h"
#include "common/error_kind.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/printable.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/scene.h"
#include "rpc/codec.h"
#include "rpc/transport_check.h"

namespace gaps::client {
namespace {

namespace fs = std::filesystem;

// Artifact paths come from the server: never let one escape the output folder.
bool safe_relative(const std::string& path) {
  const fs::path p(path);
  if (p.empty() || p.is_absolute()) return false;
  for (const auto& part : p)
    if (part == "..") return false;
  return true;
}

// An artifact's path as this machine names it: control characters in any component become '_'.
fs::path sanitised(const std::string& path) {
  fs::path out;
  for (const auto& part : fs::path(path)) out /= safe_file_name(part.string());
  return out;
}

}  // namespace

absl::StatusOr<PreparedScene> prepare_scene(const fs::path& scene_dir, int resolution) {
  SceneLoadOptions load;
  load.resolution = resolution;
  GAPS_ASSIGN_OR_RETURN(Scene scene, load_scene(scene_dir, load));
  PreparedScene out;
  for (const Camera& camera : scene.cameras) {
    GAPS_ASSIGN_OR_RETURN(at::Tensor image, load_camera_image(camera));
    GAPS_ASSIGN_OR_RETURN(std::string png, encode_png(image, camera.name));
    Camera sent = camera;
    sent.distortion.clear();  // load_camera_image undistorted the pixels
    sent.name = fs::path(camera.name).stem().string() + ".png";
    rpc::encode_camera(sent, &out.cameras.emplace_back());
    out.images.push_back(std::move(png));
  }
  out.source_cameras = std::move(scene.cameras);
  return out;
}

absl::Status add_larger_training_views(const RunOptions& o, PreparedScene* scene) {
  const std::vector<Camera>& at_training = scene->source_cameras;
  GAPS_ASSIGN_OR_RETURN(const Split split, benchmark_split(static_cast<int>(at_training.size()), o.views));
  std::vector<Camera> train;
  for (int i : split.train) train.push_back(at_training[i]);
  if (!auto_reads_larger_views(o, train)) return absl::OkStatus();
  // Any failure from here on means the scene has no usable views that large: NotFound, saying why.
  const auto none = [](const absl::Status& why) { return absl::NotFoundError(why.message()); };
  if (o.resolution < 2 || o.resolution % 2 != 0)
    return absl::NotFoundError(absl::StrCat("resolution ", o.resolution, " has no half"));
  SceneLoadOptions load;
  load.resolution = o.resolution / 2;
  const absl::StatusOr<Scene> larger = load_scene(o.scene_dir, load);
  if (!larger.ok()) return none(larger.status());
  if (larger->cameras.size() != at_training.size())
    return absl::NotFoundError(absl::StrCat("the scene lists ", larger->cameras.size(), " views at resolution ",
                                            load.resolution, " and ", at_training.size(), " at ", o.resolution));
  std::vector<std::pair<int, std::string>> images;
  for (int i : split.train) {
    const Camera& camera = larger->cameras[i];
    if (camera.name != at_training[i].name)
      return absl::NotFoundError(absl::StrCat("the scene lists ", camera.name, " at resolution ", load.resolution,
                                              " where it lists ", at_training[i].name, " at ", o.resolution));
    absl::StatusOr<at::Tensor> image = load_camera_image(camera);
    if (!image.ok()) return none(image.status());
    GAPS_ASSIGN_OR_RETURN(std::string png, encode_png(*image, camera.name));
    images.emplace_back(i, std::move(png));
  }
  scene->larger_images = std::move(images);
  return absl::OkStatus();
}

TrainerClient::TrainerClient(std::string address, std::shared_ptr<grpc::Channel> channel, rpc::ClientSecurity security)
    : address_(std::move(address)),
      channel_(std::move(channel)),
      stub_(v1::Trainer::NewStub(channel_)),
      security_(std::move(security)) {}

absl::StatusOr<TrainerClient> TrainerClient::connect(const std::string& address, const rpc::ClientSecurity& security) {
  GAPS_ASSIGN_OR_RETURN(std::shared_ptr<grpc::Channel> channel, rpc::make_channel(address, security));
  return TrainerClient(address, std::move(channel), security);
}

namespace {
// The probe of a channel that failed: one TCP connection and handshake.
constexpr std::chrono::seconds kProbeTimeout{5};
}  // namespace

absl::Status TrainerClient::unreachable(const std::string& detail) const {
  const std::string tls = rpc::diagnose_transport(address_, security_, kProbeTimeout);
  if (!tls.empty())
    return with_error_kind(
        absl::UnavailableError(absl::StrCat("cannot connect to the gaps-trainer at ", address_, ": ", tls)),
        ErrorKind::kUnreachable);
  return with_error_kind(
      absl::UnavailableError(absl::StrCat("cannot reach a gaps-trainer at ", address_, ": ", detail)),
      ErrorKind::kUnreachable);
}

absl::Status TrainerClient::checked(const grpc::Status& status, const std::string& call) const {
  absl::Status st = rpc::from_grpc(status, call);
  if (!absl::IsUnavailable(st)) return st;
  // TLS 1.3 lets the client finish its handshake before the server judges the client certificate, so a
  // refused certificate first shows as a call that fails, not as a channel that never connects.
  const std::string tls = rpc::diagnose_transport(address_, security_, kProbeTimeout);
  if (tls.empty()) return st;
  return with_error_kind(
      absl::UnavailableError(absl::StrCat("cannot connect to the gaps-trainer at ", address_, ": ", tls)),
      ErrorKind::kUnreachable);
}

absl::Status TrainerClient::check_reachable(std::chrono::milliseconds timeout) const {
  const auto deadline = std::chrono::system_clock::now() + timeout;
  grpc_connectivity_state state = channel_->GetState(/*try_to_connect=*/true);
  while (state != GRPC_CHANNEL_READY) {
    if (state == GRPC_CHANNEL_TRANSIENT_FAILURE || state == GRPC_CHANNEL_SHUTDOWN ||
        !channel_->WaitForStateChange(state, deadline))
      return unreachable(absl::StrCat("none is listening there (start one with gaps-trainer --listen ", address_,
                                      ", or point --trainer at it)"));
    state = channel_->GetState(/*try_to_connect=*/true);
  }
  return absl::OkStatus();
}

namespace {
// GetJob, ListJobs and CancelJob read or write one row of the job store.
constexpr std::chrono::seconds kUnaryDeadline{30};
}  // namespace

void TrainerClient::prepare(grpc::ClientContext& context, std::optional<std::chrono::milliseconds> deadline) const {
  rpc::attach_token(context, security_.token);
  if (deadline) context.set_deadline(std::chrono::system_clock::now() + *deadline);
}

absl::StatusOr<std::string> TrainerClient::submit(v1::JobSpec spec, const PreparedScene& scene) {
  spec.clear_cameras();
  for (const auto& c : scene.cameras) *spec.add_cameras() = c;
  spec.set_has_points(!scene.points_ply.empty());
  grpc::ClientContext context;
  prepare(context);
  v1::SubmitJobResponse response;
  std::unique_ptr<grpc::ClientWriter<v1::SubmitJobRequest>> writer(stub_->SubmitJob(&context, &response));
  v1::SubmitJobRequest first;
  *first.mutable_spec() = spec;
  bool open = writer->Write(first);
  const auto write = [&writer](const v1::SubmitJobRequest& request) { return writer->Write(request); };
  for (size_t i = 0; open && i < scene.images.size(); ++i)
    open = rpc::write_file_chunks(v1::FileChunk::IMAGE, static_cast<int>(i), scene.images[i], write);
  for (size_t k = 0; open && k < scene.larger_images.size(); ++k)
    open = rpc::write_file_chunks(v1::FileChunk::LARGER_IMAGE, scene.larger_images[k].first,
                                  scene.larger_images[k].second, write);
  if (open && !scene.points_ply.empty())
    open = rpc::write_file_chunks(v1::FileChunk::POINTS, 0, scene.points_ply, write);
  if (open) writer->WritesDone();
  GAPS_RETURN_IF_ERROR(checked(writer->Finish(), "SubmitJob"));
  return response.job_id();
}

absl::StatusOr<v1::JobStatus> TrainerClient::watch(const std::string& job_id,
                                                   const std::function<void(const v1::JobEvent&)>& on_event,
                                                   int64_t from_sequence) {
  grpc::ClientContext context;
  prepare(context);
  v1::WatchJobRequest request;
  request.set_job_id(job_id);
  request.set_from_sequence(from_sequence);
  std::unique_ptr<grpc::ClientReader<v1::JobEvent>> reader(stub_->WatchJob(&context, request));
  v1::JobEvent event;
  std::optional<v1::JobStatus> final_status;
  while (reader->Read(&event)) {
    on_event(event);
    if (event.has_finished()) final_status = event.finished();
    if (event.has_failed()) final_status = event.failed();
    if (event.has_cancelled()) final_status = event.cancelled();
  }
  GAPS_RETURN_IF_ERROR(checked(reader->Finish(), "WatchJob"));
  if (!final_status)
    return absl::UnavailableError(absl::StrCat("event stream of ", job_id, " ended before the job did"));
  return *final_status;
}

absl::StatusOr<v1::JobStatus> TrainerClient::get(const std::string& job_id) {
  grpc::ClientContext context;
  prepare(context, kUnaryDeadline);
  v1::GetJobRequest request;
  request.set_job_id(job_id);
  v1::JobStatus status;
  GAPS_RETURN_IF_ERROR(checked(stub_->GetJob(&context, request, &status), "GetJob"));
  return status;
}

absl::StatusOr<std::vector<v1::JobStatus>> TrainerClient::list() {
  grpc::ClientContext context;
  prepare(context, kUnaryDeadline);
  v1::ListJobsResponse response;
  GAPS_RETURN_IF_ERROR(checked(stub_->ListJobs(&context, v1::ListJobsRequest(), &response), "ListJobs"));
  return std::vector<v1::JobStatus>(response.jobs().begin(), response.jobs().end());
}

absl::StatusOr<v1::JobStatus> TrainerClient::cancel(const std::string& job_id) {
  grpc::ClientContext context;
  prepare(context, kUnaryDeadline);
  v1::CancelJobRequest request;
  request.set_job_id(job_id);
  v1::JobStatus status;
  GAPS_RETURN_IF_ERROR(checked(stub_->CancelJob(&context, request, &status), "CancelJob"));
  return status;
}

absl::StatusOr<at::Tensor> TrainerClient::render(const std::string& job_id, const v1::Camera& camera,
                                                 std::chrono::milliseconds deadline) {
  grpc::ClientContext context;
  prepare(context, deadline);
  v1::RenderViewRequest request;
  request.set_job_id(job_id);
  *request.mutable_camera() = camera;
  v1::RenderViewResponse response;
  GAPS_RETURN_IF_ERROR(checked(stub_->RenderView(&context, request, &response), "RenderView"));
  return rpc::decode_tensor_shaped(response.image(), {camera.height(), camera.width(), 3}, "rendered view");
}

absl::StatusOr<v1::JobCameras> TrainerClient::job_cameras(const std::string& job_id,
                                                          std::chrono::milliseconds deadline) {
  grpc::ClientContext context;
  prepare(context, deadline);
  v1::GetJobCamerasRequest request;
  request.set_job_id(job_id);
  v1::JobCameras response;
  GAPS_RETURN_IF_ERROR(checked(stub_->GetJobCameras(&context, request, &response), "GetJobCameras"));
  return response;
}

absl::StatusOr<std::vector<std::string>> TrainerClient::fetch(const std::string& job_id, const fs::path& out_dir) {
  grpc::ClientContext context;
  prepare(context);
  v1::FetchArtifactsRequest request;
  request.set_job_id(job_id);
  std::unique_ptr<grpc::ClientReader<v1::ArtifactChunk>> reader(stub_->FetchArtifacts(&context, request));
  std::vector<std::string> paths;
  std::ofstream file;
  std::string current;
  v1::ArtifactChunk chunk;
  absl::Status status;
  while (status.ok() && reader->Read(&chunk)) {
    if (chunk.path() != current) {
      if (!safe_relative(chunk.path())) {
        status =
            absl::DataLossError(absl::StrCat("server sent an unsafe artifact path '", printable(chunk.path()), "'"));
        break;
      }
      current = chunk.path();
      const fs::path target = out_dir / sanitised(current);
      std::error_code ec;
      fs::create_directories(target.parent_path(), ec);
      file = std::ofstream(target, std::ios::binary | std::ios::trunc);
      if (!file)
        status = usage_error(absl::StrCat(target.string(), ": cannot write (", ec ? ec.message() : "file", ")"));
      paths.push_back(sanitised(current).string());
    }
    file.write(chunk.data().data(), chunk.data().size());
    if (chunk.last()) file.close();
  }
  if (!status.ok()) {
    context.TryCancel();
    reader->Finish();
    return status;
  }
  GAPS_RETURN_IF_ERROR(checked(reader->Finish(), "FetchArtifacts"));
  return paths;
}

}  // namespace gaps::client

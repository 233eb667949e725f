#include "gs_trainer/run/checkpoint.h"

#include <sstream>
#include <vector>

#include <ATen/ATen.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "common/io_util.h"
#include "common/npy.h"
#include "common/status_macros.h"

namespace gaps {

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

constexpr int kVersion = 1;

json camera_json(const Camera& c) {
  json j = {{"name", c.name}, {"width", c.width}, {"height", c.height}, {"fx", c.fx},  {"fy", c.fy},
            {"cx", c.cx},     {"cy", c.cy},       {"near", c.near},     {"far", c.far}};
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) j["R"].push_back(c.R(r, k));
    j["t"].push_back(c.t(r));
  }
  return j;
}

Camera camera_from_json(const json& j) {
  Camera c;
  c.name = j.at("name");
  c.width = j.at("width");
  c.height = j.at("height");
  c.fx = j.at("fx");
  c.fy = j.at("fy");
  c.cx = j.at("cx");
  c.cy = j.at("cy");
  c.near = j.at("near");
  c.far = j.at("far");
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) c.R(r, k) = j.at("R").at(r * 3 + k);
    c.t(r) = j.at("t").at(r);
  }
  return c;
}

// Tensors go to <name>.npy; state.json records each one's dtype (or that it was undefined).
class TensorFiles {
 public:
  TensorFiles(fs::path dir, json* dtypes) : dir_(std::move(dir)), dtypes_(dtypes) {}
  absl::Status put(const std::string& name, const at::Tensor& t) {
    if (!t.defined()) {
      (*dtypes_)[name] = nullptr;
      return absl::OkStatus();
    }
    (*dtypes_)[name] = static_cast<int>(t.scalar_type());
    return write_npy(dir_ / (name + ".npy"), t.detach());
  }
  absl::StatusOr<at::Tensor> get(const std::string& name, const at::Device& device) const {
    if (!dtypes_->contains(name)) return absl::DataLossError(absl::StrCat("checkpoint lacks tensor ", name));
    if ((*dtypes_)[name].is_null()) return at::Tensor();
    absl::StatusOr<NpyArray> read = read_npy(dir_ / (name + ".npy"));
    // Not NotFound: that would read as "no checkpoint" and silently start the run over.
    if (!read.ok()) return absl::DataLossError(absl::StrCat("corrupt checkpoint: ", read.status().message()));
    NpyArray& array = *read;
    const auto dtype = static_cast<at::ScalarType>((*dtypes_)[name].get<int>());
    return array.data.reshape(array.shape).to(device, dtype).contiguous();
  }

 private:
  fs::path dir_;
  json* dtypes_;
};

}  // namespace

struct CheckpointAccess {
  static absl::Status save(const fs::path& dir, const Trainer& trainer, const GapsTraining* method, json& state) {
    TensorFiles files(dir, &state["tensors"]);
    Trainer& t = const_cast<Trainer&>(trainer);
    const char* names[] = {"means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest"};
    const auto params = t.model_.parameters();
    for (size_t i = 0; i < params.size(); ++i)
      GAPS_RETURN_IF_ERROR(files.put(absl::StrCat("model_", names[i]), *params[i]));
    state["sh_degree"] = t.model_.sh_degree;
    state["iteration"] = t.iteration_;
    state["view_order"] = t.view_order_;
    state["view_cursor"] = t.view_cursor_;
    state["rng_state"] = t.rng_state_;
    state["adam_steps"] = t.adam_.steps_;
    for (size_t i = 0; i < t.adam_.groups_.size(); ++i) {
      const auto& g = t.adam_.groups_[i];
      state["adam_lr"].push_back(g.lr);
      GAPS_RETURN_IF_ERROR(files.put(absl::StrCat("adam_", i, "_exp_avg"), g.exp_avg));
      GAPS_RETURN_IF_ERROR(files.put(absl::StrCat("adam_", i, "_exp_avg_sq"), g.exp_avg_sq));
    }
    GAPS_RETURN_IF_ERROR(files.put("density_grad_accum", t.density_.grad_accum_));
    GAPS_RETURN_IF_ERROR(files.put("density_denom", t.density_.denom_));
    GAPS_RETURN_IF_ERROR(files.put("density_max_radii", t.density_.max_radii_));
    if (method == nullptr) return absl::OkStatus();
    json& m = state["method"];
    std::ostringstream rng;
    rng << method->rng_;
    m["rng"] = rng.str();
    m["tier"] = method->tier_;
    m["log"] = method->log_;
    m["uncertainty_history"] = json::array();
    for (const auto& [id, per_phase] : method->uncertainty_history_)
      m["uncertainty_history"].push_back({id, per_phase});
    m["admitted"] = json::array();
    m["ever_admitted"] = method->ever_admitted_;
    for (const auto& [id, view] : method->active_) {
      m["admitted"].push_back({{"id", id},
                               {"candidate_id", view.candidate_id},
                               {"generated_in_phase", method->active_phase_.at(id)},
                               {"camera", camera_json(view.camera)}});
      GAPS_RETURN_IF_ERROR(files.put(absl::StrCat("admitted_", id, "_image"), view.image));
      GAPS_RETURN_IF_ERROR(files.put(absl::StrCat("admitted_", id, "_weight"), view.weight));
    }
    return absl::OkStatus();
  }

  static absl::StatusOr<int> load(const fs::path& dir, json& state, Trainer& t, GapsTraining* method) {
    if (state.value("version", 0) != kVersion)
      return absl::FailedPreconditionError(absl::StrCat(dir.string(), ": unsupported checkpoint version"));
    if (method != nullptr && !state.contains("method"))
      return absl::FailedPreconditionError(absl::StrCat(dir.string(), ": checkpoint of a run without the method"));
    TensorFiles files(dir, &state["tensors"]);
    const at::Device device = t.model_.means.device();
    const char* names[] = {"means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest"};
    const auto params = t.model_.parameters();
    if (state.at("adam_lr").size() != params.size())
      return absl::DataLossError(absl::StrCat(dir.string(), ": optimiser state does not match the model"));
    for (size_t i = 0; i < params.size(); ++i) {
      GAPS_ASSIGN_OR_RETURN(at::Tensor p, files.get(absl::StrCat("model_", names[i]), device));
      *params[i] = p.requires_grad_(true);  // the optimiser holds pointers to these members
      auto& g = t.adam_.groups_[i];
      g.lr = state["adam_lr"][i];
      GAPS_ASSIGN_OR_RETURN(g.exp_avg, files.get(absl::StrCat("adam_", i, "_exp_avg"), device));
      GAPS_ASSIGN_OR_RETURN(g.exp_avg_sq, files.get(absl::StrCat("adam_", i, "_exp_avg_sq"), device));
    }
    t.model_.sh_degree = state.at("sh_degree");
    t.iteration_ = state.at("iteration");
    t.view_order_ = state.at("view_order").get<std::vector<size_t>>();
    t.view_cursor_ = state.at("view_cursor");
    t.rng_state_ = state.at("rng_state");
    t.adam_.steps_ = state.at("adam_steps");
    GAPS_ASSIGN_OR_RETURN(t.density_.grad_accum_, files.get("density_grad_accum", device));
    GAPS_ASSIGN_OR_RETURN(t.density_.denom_, files.get("density_denom", device));
    GAPS_ASSIGN_OR_RETURN(t.density_.max_radii_, files.get("density_max_radii", device));
    if (method == nullptr) return t.iteration_;
    const json& m = state["method"];
    std::istringstream rng(m.at("rng").get<std::string>());
    rng >> method->rng_;
    method->tier_ = m.at("tier");
    method->log_ = m.at("log");
    method->adapted_ = false;  // the generator may be another process now: adapt it again
    method->early_adaptation_tried_ = false;
    method->uncertainty_history_.clear();
    for (const auto& e : m.at("uncertainty_history")) {
      // Checkpoints written before the history kept every phase hold one number per view: its last admitted
      // variance, which reads as a history of one phase.
      const json& v = e.at(1);
      method->uncertainty_history_[e.at(0).get<int>()] =
          v.is_number() ? std::vector<double>{v.get<double>()} : v.get<std::vector<double>>();
    }
    method->active_.clear();
    method->active_phase_.clear();
    method->ever_admitted_.clear();
    for (const auto& a : m.at("admitted")) {
      const int id = a.at("id");
      // Checkpoints from before the active set: the views' phases unknown, read as generated in phase 0.
      method->active_phase_[id] = a.value("generated_in_phase", 0);
      method->ever_admitted_.insert(id);
      PseudoView view;
      view.camera = camera_from_json(a.at("camera"));
      view.candidate_id = a.at("candidate_id");
      GAPS_ASSIGN_OR_RETURN(view.image, files.get(absl::StrCat("admitted_", id, "_image"), device));
      GAPS_ASSIGN_OR_RETURN(view.weight, files.get(absl::StrCat("admitted_", id, "_weight"), device));
      method->active_[id] = std::move(view);
    }
    for (int id : m.value("ever_admitted", std::vector<int>{})) method->ever_admitted_.insert(id);
    return t.iteration_;
  }
};

absl::Status save_checkpoint(const fs::path& dir, const Trainer& trainer, const GapsTraining* method, const json& run) {
  const fs::path staging = fs::path(dir.string() + ".partial");
  remove_tree(staging);
  std::error_code ec;
  fs::create_directories(staging, ec);
  if (ec) return absl::PermissionDeniedError(absl::StrCat(staging.string(), ": ", ec.message()));
  json state = {{"version", kVersion}, {"tensors", json::object()}, {"run", run}};
  try {
    GAPS_RETURN_IF_ERROR(CheckpointAccess::save(staging, trainer, method, state));
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("checkpoint: ", e.what()));
  }
  GAPS_RETURN_IF_ERROR(write_file_bytes(staging / "state.json", state.dump()));
  // Swap in: the old checkpoint stays until the new one is complete.
  const fs::path old = fs::path(dir.string() + ".old");
  remove_tree(old);
  if (fs::exists(dir, ec)) fs::rename(dir, old, ec);
  if (ec) return absl::InternalError(absl::StrCat(dir.string(), ": ", ec.message()));
  fs::rename(staging, dir, ec);
  if (ec) return absl::InternalError(absl::StrCat(dir.string(), ": ", ec.message()));
  remove_tree(old);
  return absl::OkStatus();
}

absl::StatusOr<int> load_checkpoint(const fs::path& dir, Trainer& trainer, GapsTraining* method, json* run) {
  std::error_code ec;
  fs::path from = dir;
  // A crash between the two renames of save_checkpoint leaves only the previous checkpoint, as ".old".
  if (!fs::exists(dir / "state.json", ec)) from = fs::path(dir.string() + ".old");
  if (!fs::exists(from / "state.json", ec)) return absl::NotFoundError(absl::StrCat(dir.string(), ": no checkpoint"));
  GAPS_ASSIGN_OR_RETURN(std::string text, read_file_bytes(from / "state.json", "checkpoint state"));
  json state = json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (state.is_discarded()) return absl::DataLossError(absl::StrCat((from / "state.json").string(), ": invalid JSON"));
  if (run != nullptr) *run = state.value("run", json::object());
  try {
    return CheckpointAccess::load(from, state, trainer, method);
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat((from / "state.json").string(), ": ", e.what()));
  }
}

}  // namespace gaps

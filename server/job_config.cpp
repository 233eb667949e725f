#include "server/job_config.h"

#include <c10/core/Device.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "common/limits.h"
#include "common/status_macros.h"
#include "gs_trainer/init/initializer.h"
#include "rpc/config_codec.h"

namespace gaps {

absl::StatusOr<RunOptions> run_options_from_proto(const v1::TrainConfig& c, bool has_points,
                                                  const std::filesystem::path& points_file,
                                                  const std::string& trainer_device) {
  RunOptions o;
  o.views = c.views();
  o.resolution = 1;  // uploads arrive at the resolution to train at
  const std::string init = c.init().empty() ? "auto" : c.init();
  if (init == "points") {
    if (!has_points) return absl::InvalidArgumentError("config: init 'points' needs an uploaded point cloud");
    o.init = "ply";
    o.init_ply = points_file;
  } else if (is_init_method(init)) {
    o.init = init;
  } else {
    return absl::InvalidArgumentError(
        absl::StrCat("config: unknown init '", init, "' (auto, mvs, sweep, sparse, random, points)"));
  }
  if (c.random_points() < 0) return absl::InvalidArgumentError("config: random_points must not be negative");
  if (c.random_points() > 0) {
    GAPS_RETURN_IF_ERROR(check_gaussian_count("config: random_points", c.random_points()));
    o.random_points = c.random_points();
  }
  o.eval_every = c.has_eval_every() ? c.eval_every() : kDefaultEvalEvery;
  if (o.eval_every < 0) return absl::InvalidArgumentError("config: eval_every must be 0 or positive");
  GAPS_ASSIGN_OR_RETURN(o.variant, parse_variant(c.variant().empty() ? "full" : c.variant()));
  try {
    o.config = rpc::present_fields(c.training()).get<TrainConfig>();
    o.gaps = rpc::present_fields(c.gaps()).get<GapsConfig>();
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat("config: ", json_error_message(e)));
  }
  if (absl::Status s = read_mvs_settings(rpc::present_fields(c.init_settings()), o); !s.ok())
    return absl::InvalidArgumentError(absl::StrCat("config: ", s.message()));
  if (absl::Status s = validate_mvs_settings(o); !s.ok())
    return absl::InvalidArgumentError(absl::StrCat("config: ", s.message()));
  if (trainer_device.empty()) return o;
  // A job may name the device type its trainer trains on; the trainer decides which card.
  if (c.training().has_device() && at::Device(o.config.device).type() != at::Device(trainer_device).type())
    return absl::InvalidArgumentError(
        absl::StrCat("config: the job asks for device ", o.config.device, "; this trainer trains on ", trainer_device));
  o.config.device = trainer_device;
  return o;
}

}  // namespace gaps

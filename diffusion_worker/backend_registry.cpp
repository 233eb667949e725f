#include "diffusion_worker/backend_registry.h"

#include <utility>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "diffusion_worker/reproject_generator.h"
#include "diffusion_worker/restore_generator.h"
#include "diffusion_worker/sdxl_generator.h"

namespace gaps {

std::vector<std::string> known_generator_backends() { return {"reproject", "restore", "sdxl"}; }

bool generator_backend_uses_device(const std::string& backend) { return backend == "sdxl" || backend == "restore"; }

absl::StatusOr<std::unique_ptr<Generator>> make_generator(const std::string& backend,
                                                          const std::string& options_json_or_empty) {
  if (backend == "reproject") {
    absl::StatusOr<ReprojectOptions> options = parse_reproject_options(options_json_or_empty);
    if (!options.ok()) return options.status();
    return std::unique_ptr<Generator>(std::make_unique<ReprojectGenerator>(*std::move(options)));
  }
  if (backend == "restore") {
    absl::StatusOr<RestoreOptions> options = parse_restore_options(options_json_or_empty);
    if (!options.ok()) return options.status();
    absl::StatusOr<std::unique_ptr<RestoreGenerator>> generator = RestoreGenerator::create(*options);
    if (!generator.ok()) return generator.status();
    return std::unique_ptr<Generator>(*std::move(generator));
  }
  if (backend == "sdxl") {
    absl::StatusOr<SdxlOptions> options = parse_sdxl_options(options_json_or_empty);
    if (!options.ok()) return options.status();
    absl::StatusOr<std::unique_ptr<SdxlGenerator>> generator = SdxlGenerator::create(*options);
    if (!generator.ok()) return generator.status();
    return std::unique_ptr<Generator>(*std::move(generator));
  }
  return absl::InvalidArgumentError(absl::StrCat("unknown generator backend '", backend,
                                                 "'; known: ", absl::StrJoin(known_generator_backends(), ", ")));
}

}  // namespace gaps

#include "diffusion_worker/backend_registry.h"

#include <utility>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "diffusion_worker/reproject_generator.h"

namespace gaps {

std::vector<std::string> known_generator_backends() { return {"reproject"}; }

absl::StatusOr<std::unique_ptr<Generator>> make_generator(const std::string& backend,
                                                          const std::string& options_json_or_empty) {
  if (backend == "reproject") {
    absl::StatusOr<ReprojectOptions> options = parse_reproject_options(options_json_or_empty);
    if (!options.ok()) return options.status();
    return std::unique_ptr<Generator>(std::make_unique<ReprojectGenerator>(*std::move(options)));
  }
  return absl::InvalidArgumentError(absl::StrCat("unknown generator backend '", backend,
                                                 "'; known: ", absl::StrJoin(known_generator_backends(), ", ")));
}

}  // namespace gaps

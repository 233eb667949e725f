#pragma once
// Builds an in-process pseudo-view generator by backend name, so the trainer and tools pick a backend
// from configuration without knowing the concrete classes.
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "gs_trainer/gaps/generator.h"

namespace gaps {

// Backend names make_generator accepts: {"reproject", "restore", "sdxl"}.
std::vector<std::string> known_generator_backends();

// Whether the backend computes on a device it is given (its "device" option): sdxl and restore do; reproject is a CPU
// algorithm (OpenCV warping and inpainting) and runs on the CPU whatever the worker's device.
bool generator_backend_uses_device(const std::string& backend);

// options_json_or_empty: the backend's options as a JSON object (see e.g. parse_reproject_options), or
// empty for its defaults. An unknown backend name is an error listing the known ones.
absl::StatusOr<std::unique_ptr<Generator>> make_generator(const std::string& backend,
                                                          const std::string& options_json_or_empty);

}  // namespace gaps

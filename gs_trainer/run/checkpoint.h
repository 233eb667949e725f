#pragma once
// Training state at a diffusion-phase boundary or where a run was stopped, so an interrupted run resumes where
// it was: the model, the optimiser's moments and step count, the densification statistics, the view order
// and seeds, and the method's state (tier, admitted pseudo-views with their weights, uncertainty history, phase log,
// RNG). A checkpoint is written to a fresh folder and renamed into place, so a crash while writing leaves the previous
// one intact. Not saved: LibTorch's global RNG (DropGaussian masks), so a resumed run is the uninterrupted one in
// distribution, not bit for bit.
#include <filesystem>

#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "gs_trainer/gaps/training.h"
#include "gs_trainer/train/trainer.h"

namespace gaps {

// Befriended by the classes whose private state a checkpoint holds; defined in checkpoint.cpp only.
struct CheckpointAccess;

// `method` may be null (vanilla runs). `run`: what the caller keeps with the training state (the pipeline: its
// evaluation curve and training time so far).
absl::Status save_checkpoint(const std::filesystem::path& dir, const Trainer& trainer, const GapsTraining* method,
                             const nlohmann::json& run = nlohmann::json::object());
// Restores into a trainer (and method) built for the same run, and the caller's `run` state into *run when
// given; returns the checkpoint's iteration. NotFound when `dir` holds no checkpoint; other errors name the file
// at fault.
absl::StatusOr<int> load_checkpoint(const std::filesystem::path& dir, Trainer& trainer, GapsTraining* method,
                                    nlohmann::json* run = nullptr);

}  // namespace gaps

#pragma once
// What a run is asked to do (RunOptions), and the rules by which "auto" settles what the user left open.
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include "gs_trainer/gaps/training.h"
#include "gs_trainer/init/fusion.h"
#include "gs_trainer/init/patchmatch.h"
#include "gs_trainer/init/sparse.h"
#include "gs_trainer/scene/camera.h"
#include "gs_trainer/train/trainer.h"

namespace gaps {

// Where a run says what it is doing, one line at a time.
using RunLog = std::function<void(const std::string&)>;
// Where a run reports its training progress.
using ProgressCallback = std::function<void(const TrainProgress&)>;

// The evaluation interval of `gaps train` and of submitted jobs when none is given.
inline constexpr int kDefaultEvalEvery = 1000;

struct RunOptions {
  std::filesystem::path scene_dir;
  int views = 3;       // training views (<= 0: every non-test view)
  int resolution = 8;  // downscale factor
  std::filesystem::path out_dir;
  // "auto" ("mvs", or "sparse" when its depth maps cover under a quarter of the pixels; on larger views where the
  // training views face one way: kAutoLargerViewsMaxSide),
  // "mvs" (sparse triangulation + PatchMatch stereo and fusion from the training views only; falls back to
  // "sparse", then "random", saying why), "sweep" (the same with the older plane sweep), "sparse", "random"
  // (uniform in the training cameras' frusta), "scene" (points shipped with the scene, e.g. a COLMAP model:
  // only honest when made without the test views) or "ply".
  std::string init = "auto";
  std::filesystem::path init_ply;
  // Initial point clouds are cached here per scene, views, resolution and method (empty: no cache).
  std::filesystem::path init_cache_dir;
  int64_t random_points = 20000;
  // Downscale factor of the images the initialisation (sparse, mvs, sweep) reads; 0: the training resolution.
  int init_resolution = 0;
  // The training views at twice their size, one image per view under the view's name (what a service job's upload
  // carries): read by "auto" where it reads larger views (kAutoLargerViewsMaxSide), instead of the scene at half
  // the resolution. Empty: the scene's.
  std::filesystem::path larger_views_dir;
  // PatchMatch and fusion settings of "mvs" (and of "auto" where it picks "mvs"). fusion.max_points is not
  // the user's: the run's Gaussian budget replaces it (FusionOptions::max_points says why).
  PatchMatchOptions patchmatch;
  FusionOptions fusion;
  // The sparse stage's settings; only max_image_side is the user's (it is read by "sparse" and "sweep" too).
  SparseOptions sparse;
  // LPIPS-VGG weights: the safetensors file of scripts/lpips_weights.py (default_lpips_weights_path()), or,
  // with lpips_backbone (a torchvision VGG16 pickle), lpips' v0.1 linear layers (vgg.pth). Empty: no LPIPS,
  // reported as null.
  std::filesystem::path lpips_weights;
  std::filesystem::path lpips_backbone;
  bool save_renders = true;
  TrainConfig config;
  // The paper's method: anything but vanilla needs a generator (not owned; see diffusion_worker/).
  Variant variant = Variant::kVanilla;
  GapsConfig gaps;
  Generator* generator = nullptr;
  // Every this many iterations the test views are evaluated into the run's curve (0: only at the end).
  int eval_every = 0;
  // A self-contained report.html in out_dir (metrics, curve, renders next to ground truth, pseudo-views).
  bool html_report = true;
  // Polled before every iteration, and during the initialisation between its stages and PatchMatch's
  // sweeps; returning true stops the run with CANCELLED (once training began, the model so far is saved).
  std::function<bool()> should_stop;
  // Called once, just before training's first iteration (after a resume: its first one): from then on a stop
  // has a state to save.
  std::function<void()> on_training_started;
  // Told about each diffusion phase (see GapsTraining::set_phase_observer).
  GapsTraining::PhaseObserver on_phase;
  // When set, the training state is saved there at the start of every diffusion phase and when the run is
  // stopped through `should_stop` (gs_trainer/run/checkpoint.h), and a run finding a checkpoint there resumes
  // from it; `on_checkpoint` hears the saved iteration.
  std::filesystem::path checkpoint_dir;
  std::function<void(int iteration)> on_checkpoint;
  // Every this many iterations the training state is saved to checkpoint_dir as well (0: never).
  int checkpoint_every = 0;
  // ... and once this many seconds of wall time have passed since the last save (0: never): a service job
  // whose trainer is stopped without warning loses at most that much work, whatever the device's speed.
  double checkpoint_every_seconds = 0;
};

// "auto" on a forward-facing capture gives PatchMatch the training views at twice their size (the scene read at
// half the training resolution, e.g. fern's 1008x756 for -r 8, or a service job's uploaded larger views) when
// that is at most this many pixels on the longest side, and keeps SIFT at the training size; only where the user
// left --init-resolution, --patchmatch-max-image-side and --sparse-max-image-side at their defaults, and only when
// such views exist (otherwise it says so and reads the training views). On fern it gains 0.3–0.5 dB at 3, 6 and 9
// views; around bonsai (12 views) the larger views cost 0.4–0.75 dB, so captures whose views surround the scene
// keep the training views (docs/benchmarks.md, "Larger views for PatchMatch alone").
inline constexpr int kAutoLargerViewsMaxSide = 1024;

// Whether "auto" asks for the training views (their cameras `train`) at twice their size: the rule above.
bool auto_reads_larger_views(const RunOptions& options, const std::vector<Camera>& train);

// Where auto_reads_larger_views holds (whether or not the larger views exist), the automatic Gaussian budget
// (TrainConfig::gaussians_per_variation < 0, the default) is this many per unit of the training views' total
// variation instead of kDefaultGaussiansPerVariation (3.5), unless --max-gaussians is given. On fern at 3, 6 and 9
// views (3 seeds each) vanilla gains 0.24–0.33 dB and the full method −0.12 to +0.10 dB with 57 % of the Gaussians;
// around bonsai k = 2 costs up to 0.34 dB, and there the rule does not hold (docs/benchmarks.md, "The Gaussian budget
// on the PatchMatch clouds").
inline constexpr double kAutoLargerViewsGaussiansPerVariation = 2.0;

// `options` with an automatic budget density (< 0) resolved for the training cameras `train`: the value above
// where it holds, else kDefaultGaussiansPerVariation. What a run initialises and trains with.
RunOptions with_auto_budget(const RunOptions& options, const std::vector<Camera>& train);

// The longest side of any of these cameras' images, in pixels (0 for none): what the larger-views rule measures.
int longest_side(const std::vector<Camera>& cameras);

}  // namespace gaps

// The admission gate on the real fern scene (3 views, -r 8, a model after 1,000 vanilla iterations from the
// sparse points, as at the first diffusion phase): the `reproject` backend's views at interpolated poses are
// admitted; noise, another scene's photograph, a view generated for a wrong pose and the output of a
// random-weight SDXL are rejected. The gate's numbers of every case are printed for docs/fidelity.md.
#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "common/image_io.h"
#include "diffusion_worker/backend_registry.h"
#include "gs_trainer/gaps/admission.h"
#include "gs_trainer/gaps/pose.h"
#include "gs_trainer/gaps/training.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/run/inputs.h"
#include "tests/sdxl_test_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

// One candidate pose with its render and the request the method would send for it.
struct Probe {
  Candidate candidate;
  RenderOutput render;
  GenerationRequest request;
};

std::vector<GenerationRequest> requests_of(const std::vector<Probe>& ps) {
  std::vector<GenerationRequest> out;
  for (const Probe& p : ps) out.push_back(p.request);
  return out;
}

class FernGate : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    const fs::path fern = fs::path(GAPS_DATA_DIR) / "llff" / "fern";
    if (!fs::exists(fern)) return;
    out_ = new fs::path(fs::path(::testing::TempDir()) / "gaps_gate_fern");
    test::remove_tree(*out_);
    RunOptions o;
    o.scene_dir = fern;
    o.out_dir = *out_;
    o.views = 3;
    o.resolution = 8;
    o.init = "sparse";
    o.config.iterations = 1000;
    o.variant = Variant::kVanilla;
    auto run = run_pipeline(
        o, [](const TrainProgress&) {}, [](const std::string&) {});
    ASSERT_TRUE(run.ok()) << run.status();
    auto model = load_gaussians_ply(*out_ / "point_cloud.ply");
    ASSERT_TRUE(model.ok()) << model.status();
    auto scene = load_scene_and_training_views(o, at::kCPU, [](const std::string&) {});
    ASSERT_TRUE(scene.ok()) << scene.status();
    model_ = new GaussianModel(std::move(*model));
    train_ = new std::vector<TrainingView>(std::move(scene->train));
  }
  static void TearDownTestSuite() {
    if (out_ != nullptr) test::remove_tree(*out_);
    delete out_;
    delete model_;
    delete train_;
    out_ = nullptr;
    model_ = nullptr;
    train_ = nullptr;
  }
  void SetUp() override {
    if (model_ == nullptr) GTEST_SKIP() << "benchmark data not found under " << GAPS_DATA_DIR;
  }

  // The model's renders at the training views, as the method's references carry them.
  static std::vector<ReferenceView> references() { return reference_views(*model_, *train_); }

  // Interpolated candidates at α = 0.25, 0.5, 0.75 of every pair, rendered, with their requests.
  static std::vector<Probe> probes(const std::vector<double>& alphas = {0.25, 0.5, 0.75}) {
    const GapsConfig c;
    std::vector<Candidate> chosen;
    for (const Candidate& cand : build_candidate_pool(cameras_of(*train_), c, 0))
      for (double a : alphas)
        if (std::abs(cand.alpha - a) < 1e-9) chosen.push_back(cand);
    std::vector<Camera> poses;
    for (const Candidate& cand : chosen) poses.push_back(cand.camera);
    const std::vector<RenderOutput> renders = render_views(*model_, poses);
    const std::vector<ReferenceView> refs = references();
    std::vector<Probe> out;
    for (size_t k = 0; k < chosen.size(); ++k)
      out.push_back({chosen[k], renders[k], generation_request(chosen[k].camera, renders[k], refs, c, 7 + k)});
    return out;
  }

  static std::vector<at::Tensor> generate(const std::string& backend, const std::string& options,
                                          const std::vector<GenerationRequest>& requests) {
    auto generator = make_generator(backend, options);
    EXPECT_TRUE(generator.ok()) << generator.status();
    if (!generator.ok()) return {};
    EXPECT_TRUE((*generator)->adapt(references(), std::nullopt).ok());
    auto images = (*generator)->generate(requests);
    EXPECT_TRUE(images.ok()) << images.status();
    return images.ok() ? *images : std::vector<at::Tensor>{};
  }

  // Judges `images[k]` as the pseudo-view of probes[k]; prints and returns how many were admitted.
  static int admitted(const std::string& what, const std::vector<Probe>& ps, const std::vector<at::Tensor>& images) {
    const GapsConfig c;
    int count = 0;
    EXPECT_EQ(images.size(), ps.size()) << what;
    for (size_t k = 0; k < std::min(images.size(), ps.size()); ++k) {
      const AdmissionDecision d = admit_pseudo_view(images[k].to(at::kFloat), ps[k].render.rgb.clamp(0, 1),
                                                    ps[k].render.alpha, c, ps[k].request.strength);
      std::printf("%-14s candidate %3d alpha %.3f strength %.3f: residual %.4f SSIM %.4f u2 %.5f -> %s\n", what.c_str(),
                  ps[k].candidate.id, ps[k].candidate.alpha, ps[k].request.strength, d.mean_residual,
                  d.structure.value_or(-9), uncertainty_variance(d.uncertainty), d.admitted ? "admitted" : "rejected");
      count += d.admitted;
    }
    return count;
  }

  static fs::path* out_;
  static GaussianModel* model_;
  static std::vector<TrainingView>* train_;
};

fs::path* FernGate::out_ = nullptr;
GaussianModel* FernGate::model_ = nullptr;
std::vector<TrainingView>* FernGate::train_ = nullptr;

// One test, so that the model is trained once (ctest runs every test of a suite in a process of its own).
TEST_F(FernGate, ReprojectViewsAreAdmittedAndNoiseOtherScenesWrongPosesAndRandomSdxlRejected) {
  const std::vector<Probe> ps = probes();
  ASSERT_EQ(ps.size(), 9u);  // 3 pairs x 3 positions
  {
    SCOPED_TRACE("reproject views at interpolated poses");
    EXPECT_EQ(admitted("reproject", ps, generate("reproject", "", requests_of(ps))), static_cast<int>(ps.size()));
  }
  {
    SCOPED_TRACE("noise");
    at::manual_seed(5);
    std::vector<at::Tensor> noise;
    for (const Probe& p : ps) noise.push_back(at::rand_like(p.request.render_rgb));
    EXPECT_EQ(admitted("noise", ps, noise), 0);
  }
  {
    SCOPED_TRACE("another scene's photograph");
    const fs::path bonsai = fs::path(GAPS_DATA_DIR) / "mipnerf360" / "bonsai" / "images_800x533";
    ASSERT_TRUE(fs::exists(bonsai)) << "bonsai not found at " << bonsai;
    std::vector<fs::path> files;
    for (const auto& e : fs::directory_iterator(bonsai)) files.push_back(e.path());
    std::sort(files.begin(), files.end());
    std::vector<at::Tensor> others;
    for (size_t k = 0; k < ps.size(); ++k) {
      auto image = read_image(files[(k * 17) % files.size()]);
      ASSERT_TRUE(image.ok()) << image.status();
      others.push_back(resize_image(*image, ps[k].request.render_rgb.size(1), ps[k].request.render_rgb.size(0)));
    }
    EXPECT_EQ(admitted("other scene", ps, others), 0);
  }
  {
    SCOPED_TRACE("a view generated for a pose half a baseline away along the same pair");
    const std::vector<Probe> right = probes({0.25, 0.375});
    const std::vector<Probe> wrong = probes({0.75, 0.875});
    ASSERT_EQ(right.size(), wrong.size());
    EXPECT_EQ(admitted("wrong pose", right, generate("reproject", "", requests_of(wrong))), 0);
  }
  {
    SCOPED_TRACE("the sdxl backend on the tiny random-weight model: a generator without a learned prior");
    const std::vector<Probe> mid = probes({0.5});
    const std::string options = "{\"weights\": \"" + test::sdxl_model_dir() + "\", \"steps\": 4}";
    EXPECT_EQ(admitted("random sdxl", mid, generate("sdxl", options, requests_of(mid))), 0);
  }
}

}  // namespace
}  // namespace gaps

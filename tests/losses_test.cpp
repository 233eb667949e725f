// Training losses: values against closed forms, the original 3DGS Python SSIM, and autograd
// gradients against finite differences (float64, tiny images). On CUDA: gpu/losses_cuda_test.cpp.
#include "gs_trainer/raster/losses.h"

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <string>
#include <utility>
#include <vector>

#include "common/io_util.h"
#include "tests/losses_test_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

constexpr double kC1 = 0.01 * 0.01;
constexpr double kC2 = 0.03 * 0.03;
const at::TensorOptions kDouble = at::TensorOptions().dtype(at::kDouble);

using test::random_image;
using test::run_command;

// The normalised 11-tap Gaussian (sigma 1.5), computed independently of losses.cpp.
std::vector<double> gaussian_taps() {
  std::vector<double> g(11);
  double sum = 0;
  for (int i = 0; i < 11; ++i) sum += g[i] = std::exp(-(i - 5) * (i - 5) / (2 * 1.5 * 1.5));
  for (double& v : g) v /= sum;
  return g;
}

// Weight of the window that falls inside [0, n) when centred on i (zero padding drops the rest).
double inside_weight(int i, int n) {
  const std::vector<double> g = gaussian_taps();
  double s = 0;
  for (int k = -5; k <= 5; ++k) {
    if (i + k >= 0 && i + k < n) s += g[k + 5];
  }
  return s;
}

// Gaussian-weighted local mean at (y, x) of channel c, by brute force.
double local_mean(const at::Tensor& image, int y, int x, int c) {
  const std::vector<double> g = gaussian_taps();
  auto a = image.accessor<double, 3>();
  double sum = 0;
  for (int dy = -5; dy <= 5; ++dy) {
    for (int dx = -5; dx <= 5; ++dx) {
      const int yy = y + dy, xx = x + dx;
      if (yy >= 0 && yy < image.size(0) && xx >= 0 && xx < image.size(1)) {
        sum += g[dy + 5] * g[dx + 5] * a[yy][xx][c];
      }
    }
  }
  return sum;
}

TEST(L1Loss, IsMeanAbsoluteDifference) {
  at::Tensor pred = random_image(7, 9, 1);
  at::Tensor gt = random_image(7, 9, 2);
  double expected = 0;
  auto p = pred.accessor<double, 3>();
  auto g = gt.accessor<double, 3>();
  for (int y = 0; y < 7; ++y)
    for (int x = 0; x < 9; ++x)
      for (int c = 0; c < 3; ++c) expected += std::abs(p[y][x][c] - g[y][x][c]);
  expected /= 7 * 9 * 3;
  EXPECT_NEAR(gaps::l1_loss(pred, gt).item<double>(), expected, 1e-14);
}

TEST(Ssim, IdenticalImagesGiveOne) {
  at::Tensor image = random_image(20, 17, 3);
  at::Tensor map = gaps::ssim_map(image, image);
  ASSERT_EQ(map.sizes(), image.sizes());
  EXPECT_NEAR((map - 1).abs().max().item<double>(), 0.0, 1e-12);
  EXPECT_NEAR(gaps::ssim(image, image).item<double>(), 1.0, 1e-12);
}

// Constant images a and b: with window mass s inside the image (s < 1 near borders because of the
// zero padding) mu = a s, sigma_a^2 = a^2 s (1 - s), sigma_ab = a b s (1 - s); the whole map
// follows.
TEST(Ssim, ConstantImagesMatchClosedFormIncludingBorders) {
  const int h = 14, w = 19;
  const double a = 0.7, b = 0.2;
  at::Tensor map = gaps::ssim_map(at::full({h, w, 3}, a, kDouble), at::full({h, w, 3}, b, kDouble));
  auto m = map.accessor<double, 3>();
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const double s = inside_weight(y, h) * inside_weight(x, w);
      const double v = s * (1 - s);
      const double expected = (2 * a * b * s * s + kC1) * (2 * a * b * v + kC2) /
                              (((a * a + b * b) * s * s + kC1) * ((a * a + b * b) * v + kC2));
      for (int c = 0; c < 3; ++c) ASSERT_NEAR(m[y][x][c], expected, 1e-12) << y << "," << x;
    }
  }
  // Away from the border only the luminance term remains.
  EXPECT_NEAR(m[7][9][0], (2 * a * b + kC1) / (a * a + b * b + kC1), 1e-12);
}

// gt = pred + c leaves variances and covariance unchanged, so away from the borders SSIM reduces to
// the luminance term of the local means.
TEST(Ssim, ConstantShiftLeavesOnlyLuminanceTermInInterior) {
  const int h = 16, w = 18;
  const double shift = 0.3;
  at::Tensor pred = random_image(h, w, 4, 0.0, 0.6);
  at::Tensor map = gaps::ssim_map(pred, pred + shift);
  auto m = map.accessor<double, 3>();
  for (int y = 5; y < h - 5; ++y) {
    for (int x = 5; x < w - 5; ++x) {
      for (int c = 0; c < 3; ++c) {
        const double mu = local_mean(pred, y, x, c);
        const double expected = (2 * mu * (mu + shift) + kC1) / (mu * mu + (mu + shift) * (mu + shift) + kC1);
        ASSERT_NEAR(m[y][x][c], expected, 1e-12) << y << "," << x << "," << c;
      }
    }
  }
}

// ---- comparison with the original 3DGS Python code ----

void write_raw(const std::filesystem::path& path, const at::Tensor& t) {
  at::Tensor c = t.contiguous();
  std::ofstream(path, std::ios::binary).write(static_cast<const char*>(c.data_ptr()), c.numel() * c.element_size());
}

at::Tensor read_raw_double(const std::filesystem::path& path, at::IntArrayRef shape) {
  at::Tensor t = at::empty(shape, kDouble);
  std::ifstream in(path, std::ios::binary);
  in.read(static_cast<char*>(t.data_ptr()), t.numel() * sizeof(double));
  EXPECT_EQ(in.gcount(), static_cast<std::streamsize>(t.numel() * sizeof(double))) << path;
  return t;
}

TEST(Ssim, MatchesOriginal3dgsPythonImplementation) {
  ASSERT_TRUE(std::filesystem::exists(GAPS_PYTHON))
      << "GAPS_PYTHON (" << GAPS_PYTHON << ") does not exist; run scripts/setup.sh";
  char pattern[] = "/tmp/gaps_losses_test_XXXXXX";
  ASSERT_NE(mkdtemp(pattern), nullptr);
  const std::filesystem::path dir = pattern;
  const int h = 21, w = 26;
  at::Tensor pred = random_image(h, w, 5);
  at::Tensor gt = 0.6 * pred + 0.4 * random_image(h, w, 6);
  write_raw(dir / "pred.f64", pred);
  write_raw(dir / "gt.f64", gt);
  const std::string command = std::string(GAPS_PYTHON) + " " + GAPS_TEST_SCRIPTS_DIR +
                              "/scripts/ssim_reference.py --pred " + (dir / "pred.f64").string() + " --gt " +
                              (dir / "gt.f64").string() + " --shape " + std::to_string(h) + " " + std::to_string(w) +
                              " 3 --out " + (dir / "map.f64").string();
  auto [rc, output] = run_command(command);
  ASSERT_EQ(rc, 0) << command << "\n" << output;
  at::Tensor expected = read_raw_double(dir / "map.f64", {h, w, 3});
  remove_tree(dir);
  at::Tensor map = gaps::ssim_map(pred, gt);
  EXPECT_LT((map - expected).abs().max().item<double>(), 1e-12);
  // The images differ enough for the check to mean something.
  EXPECT_LT(map.mean().item<double>(), 0.9);
}

// ---- photometric losses ----

TEST(PhotometricLoss, CombinesL1AndDssim) {
  at::Tensor pred = random_image(12, 15, 7);
  at::Tensor gt = random_image(12, 15, 8);
  const double l1 = gaps::l1_loss(pred, gt).item<double>();
  const double s = gaps::ssim(pred, gt).item<double>();
  EXPECT_NEAR(gaps::photometric_loss(pred, gt).item<double>(), 0.8 * l1 + 0.2 * (1 - s), 1e-14);
  EXPECT_NEAR(gaps::photometric_loss(pred, gt, 0.0).item<double>(), l1, 1e-14);
  EXPECT_NEAR(gaps::photometric_loss(pred, gt, 1.0).item<double>(), 1 - s, 1e-14);
}

TEST(WeightedPhotometricLoss, UnitWeightEqualsUnweighted) {
  at::Tensor pred = random_image(12, 15, 9);
  at::Tensor gt = random_image(12, 15, 10);
  at::Tensor ones = at::ones({12, 15}, kDouble);
  EXPECT_NEAR(gaps::weighted_photometric_loss(pred, gt, ones, 0.3).item<double>(),
              gaps::photometric_loss(pred, gt, 0.3).item<double>(), 1e-14);
}

TEST(WeightedPhotometricLoss, WeightsEachPixel) {
  const int h = 12, w = 15;
  at::Tensor pred = random_image(h, w, 11);
  at::Tensor gt = random_image(h, w, 12);
  at::Tensor weight = at::rand({h, w}, kDouble);
  auto p = pred.accessor<double, 3>();
  auto g = gt.accessor<double, 3>();
  auto wt = weight.accessor<double, 2>();
  at::Tensor map = gaps::ssim_map(pred, gt);
  auto m = map.accessor<double, 3>();
  double l1 = 0, dssim = 0;
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x)
      for (int c = 0; c < 3; ++c) {
        l1 += wt[y][x] * std::abs(p[y][x][c] - g[y][x][c]);
        dssim += wt[y][x] * (1 - m[y][x][c]);
      }
  const double n = h * w * 3;
  EXPECT_NEAR(gaps::weighted_photometric_loss(pred, gt, weight, 0.25).item<double>(), 0.75 * l1 / n + 0.25 * dssim / n,
              1e-14);
}

// ---- gradients ----

// d loss / d pred by autograd and by central differences, on every 5th element (5 is coprime to
// the 3 channels and the image widths, so rows, columns and channels are all sampled; float64
// convolutions on the CPU are slow enough that all elements would take seconds per test).
void expect_gradient_matches_finite_differences(const std::function<at::Tensor(const at::Tensor&)>& loss,
                                                const at::Tensor& pred0) {
  at::Tensor pred = pred0.clone().requires_grad_(true);
  loss(pred).backward();
  at::Tensor analytic = pred.grad();
  ASSERT_TRUE(analytic.defined());
  const double eps = 1e-6;
  at::Tensor probe = pred0.clone();
  double* data = probe.data_ptr<double>();
  auto a = analytic.contiguous();
  const double* grad = a.data_ptr<double>();
  double max_abs = 0;
  for (int64_t i = 0; i < probe.numel(); i += 5) {
    const double original = data[i];
    data[i] = original + eps;
    const double up = loss(probe).item<double>();
    data[i] = original - eps;
    const double down = loss(probe).item<double>();
    data[i] = original;
    const double numeric = (up - down) / (2 * eps);
    ASSERT_NEAR(grad[i], numeric, 1e-8 + 1e-5 * std::abs(numeric)) << "element " << i;
    max_abs = std::max(max_abs, std::abs(numeric));
  }
  EXPECT_GT(max_abs, 1e-5);  // the gradient is not trivially zero
}

TEST(Gradients, SsimMatchesFiniteDifferences) {
  at::Tensor gt = random_image(12, 13, 13);
  expect_gradient_matches_finite_differences([&](const at::Tensor& p) { return gaps::ssim(p, gt); },
                                             random_image(12, 13, 14));
}

TEST(Gradients, PhotometricLossMatchesFiniteDifferences) {
  at::Tensor gt = random_image(12, 13, 15);
  expect_gradient_matches_finite_differences([&](const at::Tensor& p) { return gaps::photometric_loss(p, gt, 0.2); },
                                             random_image(12, 13, 16));
}

TEST(Gradients, WeightedPhotometricLossMatchesFiniteDifferences) {
  at::Tensor gt = random_image(12, 13, 17);
  at::Tensor weight = at::rand({12, 13}, kDouble) + 0.1;
  expect_gradient_matches_finite_differences(
      [&](const at::Tensor& p) { return gaps::weighted_photometric_loss(p, gt, weight, 0.4); },
      random_image(12, 13, 18));
}

// The training loss is one autograd node; its gradient must be the one the composed ops give, bit for bit, so
// that fusing it changed no training result.
at::Tensor gradient_of(const std::function<at::Tensor(const at::Tensor&)>& loss, const at::Tensor& pred0) {
  at::Tensor pred = pred0.clone().requires_grad_(true);
  loss(pred).backward();
  return pred.grad();
}

TEST(Gradients, FusedLossesEqualTheComposedOpsBitForBit) {
  const at::Tensor pred = random_image(21, 17, 25).to(at::kFloat), gt = random_image(21, 17, 26).to(at::kFloat);
  const at::Tensor weight = at::rand({21, 17}, at::kFloat) + 0.1f;
  const double lambda = 0.2;
  const at::Tensor fused =
      gradient_of([&](const at::Tensor& p) { return gaps::photometric_loss(p, gt, lambda); }, pred);
  const at::Tensor composed = gradient_of(
      [&](const at::Tensor& p) { return (1.0 - lambda) * gaps::l1_loss(p, gt) + lambda * (1.0 - gaps::ssim(p, gt)); },
      pred);
  EXPECT_TRUE(at::equal(fused, composed)) << (fused - composed).abs().max().item<double>();

  const at::Tensor fused_w =
      gradient_of([&](const at::Tensor& p) { return gaps::weighted_photometric_loss(p, gt, weight, lambda); }, pred);
  const at::Tensor composed_w = gradient_of(
      [&](const at::Tensor& p) {
        const at::Tensor w = weight.unsqueeze(2);
        return (1.0 - lambda) * (w * (p - gt).abs()).mean() + lambda * (w * (1.0 - gaps::ssim_map(p, gt))).mean();
      },
      pred);
  EXPECT_TRUE(at::equal(fused_w, composed_w)) << (fused_w - composed_w).abs().max().item<double>();
  EXPECT_FALSE(at::equal(fused, fused_w));  // the weight reached the gradient
}

// ---- types and misuse ----

TEST(Losses, Float32AgreesWithFloat64) {
  at::Tensor pred = random_image(30, 41, 19);
  at::Tensor gt = random_image(30, 41, 20);
  const double reference = gaps::photometric_loss(pred, gt).item<double>();
  at::Tensor single = gaps::photometric_loss(pred.to(at::kFloat), gt.to(at::kFloat));
  EXPECT_EQ(single.scalar_type(), at::kFloat);
  EXPECT_NEAR(single.item<double>(), reference, 1e-6);
}

TEST(Losses, RejectsMismatchedShapes) {
  at::Tensor a = random_image(8, 8, 23);
  at::Tensor b = random_image(8, 9, 24);
  EXPECT_THROW(gaps::l1_loss(a, b), c10::Error);
  EXPECT_THROW(gaps::ssim_map(a, b), c10::Error);
  EXPECT_THROW(gaps::ssim_map(a[0], a[0]), c10::Error);  // not HxWxC
  EXPECT_THROW(gaps::weighted_photometric_loss(a, a, at::ones({8, 9}, kDouble)), c10::Error);
}

}  // namespace
}  // namespace gaps

#pragma once
// The per-run HTML report: one self-contained page (no network: charts are inline SVG, images base64-embedded
// PNG thumbnails) with the metrics, the web viewer of the model (gs_trainer/viewer, in an iframe, when its
// packed model is at most 16 MiB), the evaluation curve, the test renders next to ground truth and, for the
// method variants, every phase's pseudo-views with their admission decision.
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "gs_trainer/train/trainer.h"

namespace gaps {

// One line of a chart: (x, y) points in drawing order.
struct ChartSeries {
  std::string label;
  std::vector<std::pair<double, double>> points;
};

// An SVG line chart (axes with rounded ticks, one polyline and its markers per series, a legend).
std::string svg_line_chart(const std::string& title, const std::string& x_label, const std::string& y_label,
                           const std::vector<ChartSeries>& series);

// Writes out_dir/report.html from what the run wrote there (metrics.json, renders/, phases.json,
// pseudo_views/) and the test views' ground truth (matched to renders/<image stem>.png).
absl::Status write_run_report(const std::filesystem::path& out_dir, const std::vector<TrainingView>& test_views);

}  // namespace gaps

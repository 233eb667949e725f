#include "gs_trainer/report.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <map>
#include <set>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_replace.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/status_macros.h"
#include "gs_trainer/scene/run_files.h"
#include "gs_trainer/viewer/site.h"
#include "gs_trainer/viewer/viewer_scene.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// Test views at a comparable size; pseudo-views smaller, as a run has hundreds of them (18 phases of up to 24).
constexpr int kThumbnailWidth = 240;
constexpr int kPseudoThumbnailWidth = 160;
// The report embeds the viewer up to this size of packed model (146 bytes per Gaussian of SH degree 3, 56 of
// degree 0: about 115,000 or 300,000 Gaussians); base64 makes the page a third larger than that.
constexpr size_t kViewerEmbedLimitBytes = 16 << 20;
constexpr const char* kSeriesColours[] = {"#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b"};

std::string escape(const std::string& s) {
  return absl::StrReplaceAll(s, {{"&", "&amp;"}, {"<", "&lt;"}, {">", "&gt;"}, {"\"", "&quot;"}});
}

// An <img> of the image shrunk to the thumbnail width (never enlarged).
absl::StatusOr<std::string> thumbnail_img(const at::Tensor& image, const std::string& alt,
                                          int width = kThumbnailWidth) {
  const int h = static_cast<int>(image.size(0)), w = static_cast<int>(image.size(1));
  const int tw = std::min(w, width), th = std::max(1, static_cast<int>(std::lround(double(h) * tw / w)));
  GAPS_ASSIGN_OR_RETURN(const std::string png, encode_png(resize_image(image, tw, th), alt));
  return absl::StrCat("<img alt=\"", escape(alt), "\" width=\"", tw, "\" height=\"", th,
                      "\" src=\"data:image/png;base64,", viewer::base64_encode(png), "\">");
}

absl::StatusOr<std::string> thumbnail_file(const fs::path& path, int width = kThumbnailWidth) {
  GAPS_ASSIGN_OR_RETURN(const at::Tensor image, read_image(path));
  return thumbnail_img(image, path.filename().string(), width);
}

// thumbnail_file of each path that exists, "(image not saved)" for the others; decoded, shrunk and re-encoded in
// parallel, since a run of the method leaves hundreds of pseudo-views to show.
absl::StatusOr<std::vector<std::string>> thumbnail_files(const std::vector<fs::path>& paths, int width) {
  std::vector<absl::StatusOr<std::string>> made(paths.size(), std::string("(image not saved)"));
  at::parallel_for(0, static_cast<int64_t>(paths.size()), 1, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i)
      if (fs::exists(paths[i])) made[i] = thumbnail_file(paths[i], width);
  });
  std::vector<std::string> html;
  for (absl::StatusOr<std::string>& m : made) {
    if (!m.ok()) return m.status();
    html.push_back(*std::move(m));
  }
  return html;
}

// Ticks at 1, 2 or 5 times a power of ten, about `target` of them over [lo, hi].
std::vector<double> nice_ticks(double lo, double hi, int target = 5) {
  const double raw = (hi - lo) / target;
  const double magnitude = std::pow(10.0, std::floor(std::log10(raw)));
  double step = magnitude;
  for (double m : {1.0, 2.0, 5.0, 10.0})
    if (m * magnitude >= raw) {
      step = m * magnitude;
      break;
    }
  std::vector<double> ticks;
  for (double t = std::ceil(lo / step) * step; t <= hi + 1e-9 * step; t += step) ticks.push_back(t);
  return ticks;
}

std::string format_number(double v) {
  if (v != 0 && (std::fabs(v) >= 1e5 || std::fabs(v) < 1e-2)) return absl::StrFormat("%.3g", v);
  return absl::StrFormat("%g", std::round(v * 1000) / 1000);
}

std::string json_number(const json& v, int decimals) {
  return v.is_number() ? absl::StrFormat("%.*f", decimals, v.get<double>()) : std::string("n/a");
}

// "mvs, 55287 points in 4.0 s" ("from the cache" when read from it); the method alone for older metrics.
std::string initial_points_text(const json& m) {
  const std::string method = m.value("init_method", m.value("init", ""));
  if (!m.contains("init_points")) return method;
  return absl::StrCat(method, ", ", m.value("init_points", int64_t{0}), " points in ",
                      json_number(m.value("init_seconds", json()), 1), " s",
                      m.value("init_from_cache", false) ? " (from the cache)" : "");
}

std::string metrics_table(const json& m) {
  const json peak = m.value("peak_memory", json::object());
  const std::vector<std::pair<std::string, std::string>> rows = {
      {"status", m.value("status", "ok")},
      {"scene", m.value("scene", "")},
      {"variant", m.value("variant", "")},
      {"training views", std::to_string(m.value("views", 0))},
      {"iterations", std::to_string(m.value("iterations", 0))},
      {"seed", std::to_string(m.value("seed", 0))},
      {"initial points", initial_points_text(m)},
      {"device", m.value("device", "")},
      {"diffusion phases", m.contains("phases")
                               ? absl::StrCat(m.value("phases", 0), " run, ", m.value("phases_skipped", 0), " skipped")
                               : "none (vanilla)"},
      {"test PSNR (dB)", json_number(m.value("psnr", json()), 2)},
      {"test SSIM", json_number(m.value("ssim", json()), 4)},
      {"test LPIPS", json_number(m.value("lpips", json()), 4)},
      {"Gaussians", std::to_string(m.value("num_gaussians", int64_t{0}))},
      {"training seconds", json_number(m.value("train_seconds", json()), 1)},
      {"generator seconds", json_number(m.value("generator_seconds", json()), 1)},
      {absl::StrCat("peak memory (", peak.value("kind", "n/a"), ", MiB)"),
       peak.contains("bytes") ? absl::StrFormat("%.0f", peak["bytes"].get<double>() / (1 << 20)) : "n/a"},
  };
  std::string html = "<table class=\"metrics\">\n";
  for (const auto& [k, v] : rows) absl::StrAppend(&html, "<tr><th>", escape(k), "</th><td>", escape(v), "</td></tr>\n");
  if (m.contains("error"))
    absl::StrAppend(&html, "<tr><th>error</th><td>", escape(m["error"].get<std::string>()), "</td></tr>\n");
  return html + "</table>\n";
}

std::string curve_section(const json& metrics) {
  const json curve = metrics.value("curve", json::array());
  if (curve.empty()) return "<p>No evaluation curve (the run was made with evaluation only at the end).</p>\n";
  ChartSeries psnr{"test PSNR", {}}, gaussians{"Gaussians", {}};
  for (const auto& p : curve) {
    psnr.points.push_back({p["train_seconds"].get<double>(), p["psnr"].get<double>()});
    gaussians.points.push_back({p["iteration"].get<double>(), p["num_gaussians"].get<double>()});
  }
  std::string html = "<div class=\"charts\">\n";
  absl::StrAppend(&html, svg_line_chart("Test PSNR over training time", "training seconds (evaluation excluded)",
                                        "PSNR (dB)", {psnr}));
  absl::StrAppend(&html, svg_line_chart("Gaussians over iterations", "iteration", "Gaussians", {gaussians}));
  html +=
      "</div>\n<table><tr><th>iteration</th><th>training "
      "s</th><th>PSNR</th><th>SSIM</th><th>LPIPS</th><th>Gaussians</th></tr>\n";
  for (const auto& p : curve)
    absl::StrAppend(&html, "<tr><td>", p["iteration"].get<int>(), "</td><td>", json_number(p["train_seconds"], 1),
                    "</td><td>", json_number(p["psnr"], 2), "</td><td>", json_number(p["ssim"], 4), "</td><td>",
                    json_number(p["lpips"], 4), "</td><td>", p["num_gaussians"].get<int64_t>(), "</td></tr>\n");
  return html + "</table>\n";
}

absl::StatusOr<std::string> renders_section(const fs::path& out_dir, const std::vector<TrainingView>& test,
                                            const json& metrics) {
  std::string html =
      "<table class=\"renders\"><tr><th>view</th><th>ground truth</th><th>render</th><th>PSNR / SSIM</th></tr>\n";
  const json per_view = metrics.value("per_view", json::array());
  for (size_t i = 0; i < test.size(); ++i) {
    const std::string stem = fs::path(test[i].camera.name).stem().string();
    const fs::path render_path = out_dir / "renders" / (stem + ".png");
    GAPS_ASSIGN_OR_RETURN(const std::string gt, thumbnail_img(test[i].image, stem + " ground truth"));
    std::string render = "(not saved)";
    if (fs::exists(render_path)) {
      GAPS_ASSIGN_OR_RETURN(render, thumbnail_file(render_path));
    }
    const std::string scores = i < per_view.size() ? absl::StrCat(json_number(per_view[i]["psnr"], 2), " dB / ",
                                                                  json_number(per_view[i]["ssim"], 4))
                                                   : "";
    absl::StrAppend(&html, "<tr><td>", escape(stem), "</td><td>", gt, "</td><td>", render, "</td><td>", scores,
                    "</td></tr>\n");
  }
  return html + "</table>\n";
}

// The phase's selection diagnostic: every candidate scored (I_recon, C_gen, score, best first), which were
// picked and admitted, and how the active set changed.
std::string selection_diagnostic(const json& phase) {
  std::map<int, bool> picked;  // id -> admitted
  for (const auto& s : phase.value("selection", json::array())) picked[s.value("id", -1)] = s.value("admitted", false);
  std::set<int> refreshed;
  for (const auto& id : phase.value("refreshed", json::array())) refreshed.insert(id.get<int>());
  const json scored = phase.value("candidates", json::array());
  std::vector<json> candidates(scored.begin(), scored.end());
  std::stable_sort(candidates.begin(), candidates.end(),
                   [](const json& a, const json& b) { return a.value("score", 0.0) > b.value("score", 0.0); });
  const json pool = phase.value("pool", json::object());
  std::string html = absl::StrCat("<details><summary>Selection: ", candidates.size(), " candidates scored (",
                                  pool.value("never_generated", 0), " never generated before), ", picked.size(),
                                  " picked; active set ", phase.value("active", json::array()).size(), " views (",
                                  phase.value("entered", json::array()).size(), " entered, ",
                                  phase.value("retired", json::array()).size(), " retired)</summary>\n");
  html +=
      "<table><tr><th>candidate</th><th>pair</th><th>&alpha;</th><th>I_recon</th><th>C_gen</th><th>score</th>"
      "<th>decision</th></tr>\n";
  for (const json& c : candidates) {
    const int id = c.value("id", -1);
    const auto p = picked.find(id);
    const std::string decision =
        p == picked.end() ? ""
                          : absl::StrCat(p->second ? "admitted" : "rejected", refreshed.count(id) ? ", refreshed" : "");
    const json pair = c.value("pair", json::array());
    absl::StrAppend(&html, "<tr><td>", id, "</td><td>", pair.dump(), "</td><td>",
                    json_number(c.value("alpha", json()), 3), "</td><td>", json_number(c.value("i_recon", json()), 4),
                    "</td><td>", json_number(c.value("c_gen", json()), 4), "</td><td>",
                    json_number(c.value("score", json()), 4), "</td><td>", p == picked.end() ? "" : "<b>picked</b>, ",
                    decision, "</td></tr>\n");
  }
  html += "</table>\n";
  for (const auto& r : phase.value("retired", json::array()))
    absl::StrAppend(&html, "<div>retired candidate ", r.value("id", -1), ": ", escape(r.value("reason", "")),
                    "</div>\n");
  return html + "</details>\n";
}

absl::StatusOr<std::string> phases_section(const fs::path& out_dir) {
  const fs::path phases_path = out_dir / "phases.json";
  if (!fs::exists(phases_path)) return std::string("<p>No pseudo-view phases (vanilla training).</p>\n");
  GAPS_ASSIGN_OR_RETURN(const std::string text, read_file_bytes(phases_path, "phases file"));
  const json phases = json::parse(text, nullptr, false);
  if (phases.is_discarded()) return absl::DataLossError(absl::StrCat(phases_path.string(), ": not valid JSON"));
  std::vector<fs::path> images;
  for (const auto& phase : phases)
    for (const auto& s : phase.value("selection", json::array()))
      images.push_back(out_dir / kPseudoViewsFolder /
                       pseudo_view_file(phase.value("phase", 0), s.value("id", -1), s.value("admitted", false)));
  GAPS_ASSIGN_OR_RETURN(const std::vector<std::string> thumbnails, thumbnail_files(images, kPseudoThumbnailWidth));
  std::string html;
  size_t next = 0;
  for (const auto& phase : phases) {
    absl::StrAppend(&html, "<h3>Phase ", phase.value("phase", 0), " (iteration ", phase.value("iteration", 0),
                    ", tier ", phase.value("tier", 0), ", ", phase.value("gaussians", int64_t{0}),
                    " Gaussians): ", phase.value("admitted", 0), " of ", phase.value("selection", json::array()).size(),
                    " admitted</h3>\n<div class=\"grid\">\n");
    for (const auto& s : phase.value("selection", json::array())) {
      const bool admitted = s.value("admitted", false);
      absl::StrAppend(&html, "<figure class=\"", admitted ? "admitted" : "rejected", "\">", thumbnails[next++],
                      "<figcaption>candidate ", s.value("id", -1), ", coverage ",
                      json_number(s.value("coverage", json()), 2), "<br><b>", admitted ? "admitted" : "rejected",
                      "</b>: ", escape(s.value("reason", "")), "</figcaption></figure>\n");
    }
    html += "</div>\n";
    if (phase.contains("candidates") || phase.contains("active")) html += selection_diagnostic(phase);
  }
  return html.empty() ? std::string("<p>No phase was run.</p>\n") : html;
}

// The viewer (gs_trainer/viewer) in an iframe of its own, as a self-contained page; above the size limit, or
// when the model cannot be read, a line instead: the report is written either way.
std::string viewer_section(const fs::path& out_dir) {
  const std::string serve = absl::StrCat("<code>gaps view ", escape(out_dir.string()), "</code>");
  const absl::StatusOr<viewer::ViewerScene> scene = viewer::load_viewer_scene(out_dir);
  if (!scene.ok()) return absl::StrCat("<p>No viewer: ", escape(std::string(scene.status().message())), "</p>\n");
  if (scene->model_bytes.size() > kViewerEmbedLimitBytes)
    return absl::StrFormat(
        "<p>The model (%d Gaussians, %.1f MiB packed) is larger than the %d MiB this report embeds: run %s to "
        "look at it.</p>\n",
        scene->gaussians, scene->model_bytes.size() / double(1 << 20), kViewerEmbedLimitBytes >> 20, serve);
  return absl::StrCat(
      "<iframe class=\"viewer\" title=\"viewer\" srcdoc=\"", escape(viewer::standalone_viewer_page(*scene)),
      "\"></iframe>\n<p>Drag to orbit, right-drag to pan, wheel to zoom, F for fly mode; click a camera "
      "to look through it. ",
      serve, " serves the same viewer with the pseudo-view images.</p>\n");
}

constexpr char kStyle[] =
    "body{font-family:sans-serif;margin:2em;max-width:1400px}table{border-collapse:collapse;margin:1em 0}"
    "th,td{border:1px solid #ccc;padding:4px 8px;text-align:left;vertical-align:top}"
    ".charts{display:flex;flex-wrap:wrap;gap:1em}.grid{display:flex;flex-wrap:wrap;gap:8px}"
    "figure{margin:0;padding:4px;width:170px;font-size:12px}figure.admitted{border:3px solid #2ca02c}"
    "figure.rejected{border:3px solid #d62728}"
    "iframe.viewer{width:100%;height:70vh;border:1px solid #ccc}"
    ".degraded{background:#fde0dc;border:2px solid #d62728;padding:8px 12px;font-weight:bold}";

}  // namespace

std::string svg_line_chart(const std::string& title, const std::string& x_label, const std::string& y_label,
                           const std::vector<ChartSeries>& series) {
  constexpr double kWidth = 560, kHeight = 340, kLeft = 70, kRight = 20, kTop = 30, kBottom = 50;
  double x0 = INFINITY, x1 = -INFINITY, y0 = INFINITY, y1 = -INFINITY;
  for (const auto& s : series)
    for (const auto& [x, y] : s.points) {
      if (!std::isfinite(x) || !std::isfinite(y)) continue;
      x0 = std::min(x0, x), x1 = std::max(x1, x), y0 = std::min(y0, y), y1 = std::max(y1, y);
    }
  std::string svg = absl::StrFormat(
      "<svg width=\"%.0f\" height=\"%.0f\" viewBox=\"0 0 %.0f %.0f\" "
      "font-family=\"sans-serif\" font-size=\"11\">\n<text x=\"%.0f\" y=\"18\" text-anchor=\"middle\" "
      "font-size=\"13\">%s</text>\n",
      kWidth, kHeight, kWidth, kHeight, kWidth / 2, escape(title));
  if (!(x0 <= x1)) return svg + "<text x=\"50%\" y=\"50%\" text-anchor=\"middle\">no data</text>\n</svg>\n";
  // A flat range still gets a visible span.
  if (x1 - x0 < 1e-12) x0 -= 0.5, x1 += 0.5;
  if (y1 - y0 < 1e-12) y0 -= 0.5, y1 += 0.5;
  const double pad = 0.05 * (y1 - y0);
  y0 -= pad, y1 += pad;
  const double pw = kWidth - kLeft - kRight, ph = kHeight - kTop - kBottom;
  const auto px = [&](double x) { return kLeft + (x - x0) / (x1 - x0) * pw; };
  const auto py = [&](double y) { return kTop + (1 - (y - y0) / (y1 - y0)) * ph; };
  absl::StrAppendFormat(&svg,
                        "<rect x=\"%.1f\" y=\"%.1f\" width=\"%.1f\" height=\"%.1f\" fill=\"none\" stroke=\"#333\"/>\n",
                        kLeft, kTop, pw, ph);
  for (double t : nice_ticks(x0, x1))
    absl::StrAppendFormat(&svg,
                          "<line x1=\"%.1f\" y1=\"%.1f\" x2=\"%.1f\" y2=\"%.1f\" stroke=\"#ddd\"/><text x=\"%.1f\" "
                          "y=\"%.1f\" text-anchor=\"middle\">%s</text>\n",
                          px(t), kTop, px(t), kTop + ph, px(t), kTop + ph + 15, format_number(t));
  for (double t : nice_ticks(y0, y1))
    absl::StrAppendFormat(&svg,
                          "<line x1=\"%.1f\" y1=\"%.1f\" x2=\"%.1f\" y2=\"%.1f\" stroke=\"#ddd\"/><text x=\"%.1f\" "
                          "y=\"%.1f\" text-anchor=\"end\">%s</text>\n",
                          kLeft, py(t), kLeft + pw, py(t), kLeft - 5, py(t) + 4, format_number(t));
  absl::StrAppendFormat(&svg, "<text x=\"%.1f\" y=\"%.1f\" text-anchor=\"middle\">%s</text>\n", kLeft + pw / 2,
                        kHeight - 10, escape(x_label));
  absl::StrAppendFormat(&svg, "<text transform=\"translate(15 %.1f) rotate(-90)\" text-anchor=\"middle\">%s</text>\n",
                        kTop + ph / 2, escape(y_label));
  for (size_t i = 0; i < series.size(); ++i) {
    const char* colour = kSeriesColours[i % std::size(kSeriesColours)];
    std::string points;
    for (const auto& [x, y] : series[i].points)
      if (std::isfinite(x) && std::isfinite(y)) absl::StrAppendFormat(&points, "%.1f,%.1f ", px(x), py(y));
    absl::StrAppendFormat(&svg, "<polyline fill=\"none\" stroke=\"%s\" stroke-width=\"2\" points=\"%s\"/>\n", colour,
                          points);
    for (const auto& [x, y] : series[i].points)
      if (std::isfinite(x) && std::isfinite(y))
        absl::StrAppendFormat(&svg, "<circle cx=\"%.1f\" cy=\"%.1f\" r=\"3\" fill=\"%s\"/>\n", px(x), py(y), colour);
    absl::StrAppendFormat(&svg, "<text x=\"%.1f\" y=\"%.1f\" fill=\"%s\">%s</text>\n", kLeft + 10,
                          kTop + 15 + 14 * static_cast<double>(i), colour, escape(series[i].label));
  }
  return svg + "</svg>\n";
}

absl::Status write_run_report(const fs::path& out_dir, const std::vector<TrainingView>& test_views) {
  GAPS_ASSIGN_OR_RETURN(const std::string text, read_file_bytes(out_dir / "metrics.json", "metrics file"));
  const json metrics = json::parse(text, nullptr, false);
  if (metrics.is_discarded())
    return absl::DataLossError(absl::StrCat((out_dir / "metrics.json").string(), ": not valid JSON"));
  const std::string title = absl::StrCat("gaps run: ", fs::path(metrics.value("scene", "")).filename().string(), ", ",
                                         metrics.value("views", 0), " views, ", metrics.value("variant", ""));
  std::string html = absl::StrCat("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>", escape(title),
                                  "</title><style>", kStyle, "</style></head><body>\n<h1>", escape(title), "</h1>\n");
  if (metrics.value("degraded", false))
    absl::StrAppend(&html, "<p class=\"degraded\">DEGRADED: ", metrics.value("phases_skipped", 0), " of ",
                    metrics.value("phases", 0),
                    " diffusion phases were skipped (the generator failed or could not be reached), so this is "
                    "not a full run of the method.</p>\n");
  absl::StrAppend(&html, "<h2>Metrics</h2>\n", metrics_table(metrics));
  absl::StrAppend(&html, "<h2>Viewer</h2>\n", viewer_section(out_dir));
  absl::StrAppend(&html, "<h2>Evaluation curve</h2>\n", curve_section(metrics));
  GAPS_ASSIGN_OR_RETURN(const std::string renders, renders_section(out_dir, test_views, metrics));
  absl::StrAppend(&html, "<h2>Test views: ground truth and render</h2>\n", renders);
  GAPS_ASSIGN_OR_RETURN(const std::string phases, phases_section(out_dir));
  absl::StrAppend(&html, "<h2>Pseudo-views per phase</h2>\n", phases, "</body></html>\n");
  return write_file_bytes(out_dir / "report.html", html);
}

}  // namespace gaps

#include "gs_trainer/viewer/site.h"

#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"
#include "gs_trainer/viewer/assets.h"

namespace gaps::viewer {
namespace {

using nlohmann::json;

const std::string& asset_text(const std::string& name) {
  for (const Asset& a : viewer_assets())
    if (a.name == name) return a.text;
  static const std::string* empty = new std::string;
  return *empty;
}

// JSON inside a <script> element: '<' only occurs inside strings, where \u003c means the same, so no
// "</script>" can end the element early.
std::string script_safe_json(const json& j) { return absl::StrReplaceAll(j.dump(), {{"<", "\\u003c"}}); }

std::string model_file_name(const ViewerScene& scene) {
  return scene.model_format == "splat" ? "model.splat" : "model.bin";
}

}  // namespace

std::string content_type_for(const std::filesystem::path& name) {
  const std::string ext = name.extension().string();
  if (ext == ".html") return "text/html; charset=utf-8";
  if (ext == ".js") return "text/javascript; charset=utf-8";
  if (ext == ".css") return "text/css; charset=utf-8";
  if (ext == ".json") return "application/json";
  if (ext == ".png") return "image/png";
  return "application/octet-stream";
}

std::string base64_encode(absl::string_view bytes) {
  static constexpr char kAlphabet[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((bytes.size() + 2) / 3 * 4);
  for (size_t i = 0; i < bytes.size(); i += 3) {
    const size_t n = std::min<size_t>(3, bytes.size() - i);
    uint32_t v = 0;
    for (size_t k = 0; k < 3; ++k) v = (v << 8) | (k < n ? static_cast<uint8_t>(bytes[i + k]) : 0);
    for (size_t k = 0; k < 4; ++k) out += k <= n ? kAlphabet[(v >> (18 - 6 * k)) & 63] : '=';
  }
  return out;
}

WebSite viewer_site(const ViewerScene& scene) {
  WebSite site;
  for (const Asset& a : viewer_assets()) site["/" + a.name] = {content_type_for(a.name), a.text, {}};
  site["/"] = site["/index.html"];
  json description = scene.scene;
  description["model"]["url"] = model_file_name(scene);
  site["/scene.json"] = {content_type_for("scene.json"), description.dump(), {}};
  site["/" + model_file_name(scene)] = {content_type_for(model_file_name(scene)), scene.model_bytes, {}};
  for (const auto& [url, file] : scene.images) site["/" + url] = {content_type_for(file), "", file};
  return site;
}

std::string standalone_viewer_page(const ViewerScene& scene) {
  json description = scene.scene;
  for (json& phase : description["phases"])
    for (json& view : phase["views"]) view["image"] = nullptr;
  std::string page = asset_text("index.html");
  std::vector<std::pair<std::string, std::string>> inline_assets = {
      {"<link rel=\"stylesheet\" href=\"viewer.css\">",
       absl::StrCat("<style>\n", asset_text("viewer.css"), "</style>")}};
  for (const Asset& a : viewer_assets())
    if (std::filesystem::path(a.name).extension() == ".js")
      inline_assets.push_back(
          {absl::StrCat("<script src=\"", a.name, "\"></script>"), absl::StrCat("<script>\n", a.text, "</script>")});
  const std::string data = absl::StrCat(
      "<script type=\"application/json\" id=\"gaps-scene\">", script_safe_json(description), "</script>\n",
      "<script type=\"application/octet-stream\" id=\"gaps-model\">", base64_encode(scene.model_bytes), "</script>\n");
  // The data goes before the first script, which the replacements below then inline.
  const size_t first_script = page.find("<script src=");
  if (first_script != std::string::npos) page.insert(first_script, data);
  return absl::StrReplaceAll(page, inline_assets);
}

}  // namespace gaps::viewer

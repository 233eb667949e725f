#pragma once
// The viewer as web resources: what `gaps view` serves (the page's files, scene.json, the model and the
// pseudo-view images, by URL path) and the self-contained page that report.html embeds.
#include <filesystem>
#include <map>
#include <string>

#include "absl/strings/string_view.h"
#include "gs_trainer/viewer/viewer_scene.h"

namespace gaps::viewer {

struct WebResource {
  std::string content_type;
  std::string body;            // the bytes, unless `file` is set
  std::filesystem::path file;  // read when requested (images of the run, which may be many)
};
// URL path ("/", "/scene.json", "/model.bin", ...) -> resource. Only these paths are served.
using WebSite = std::map<std::string, WebResource>;

WebSite viewer_site(const ViewerScene& scene);

// One HTML page with the styles, scripts, scene and model (base64) inline: it makes no request, so it opens
// from a file or an iframe's srcdoc. Pseudo-view images are left out (the report shows them itself).
std::string standalone_viewer_page(const ViewerScene& scene);

// "text/javascript; charset=utf-8" for "viewer.js", ...; application/octet-stream when unknown.
std::string content_type_for(const std::filesystem::path& name);
std::string base64_encode(absl::string_view bytes);

}  // namespace gaps::viewer

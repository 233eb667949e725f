#include "gs_trainer/init/init_cache.h"

#include <unistd.h>

#include <fstream>
#include <system_error>

#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

fs::path meta_path(const fs::path& ply) { return fs::path(ply).replace_extension(".json"); }

}  // namespace

std::optional<InitResult> read_init_cache(const fs::path& ply) {
  std::error_code ec;
  if (!fs::exists(ply, ec) || !fs::exists(meta_path(ply), ec)) return std::nullopt;
  auto points = read_point_cloud_ply(ply);
  if (!points.ok()) return std::nullopt;
  std::ifstream in(meta_path(ply));
  const nlohmann::json meta = nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
  if (meta.is_discarded() || !meta.contains("method")) return std::nullopt;
  InitResult r;
  r.points = std::move(*points);
  r.method = meta["method"].get<std::string>();
  r.warnings = meta.value("warnings", std::vector<std::string>{});
  r.notes = meta.value("notes", std::vector<std::string>{});
  r.cache_file = ply;
  r.from_cache = true;
  return r;
}

absl::StatusOr<PointCloud> write_init_cache(const fs::path& ply, const InitResult& r) {
  std::error_code ec;
  fs::create_directories(ply.parent_path(), ec);
  // Both files are written under per-process names and renamed into place: a reader opens either the old
  // file or the new one, whole, and two runs filling the same entry do not write into one file.
  const std::string suffix = absl::StrCat(".tmp", getpid());
  const fs::path ply_tmp = fs::path(ply).concat(suffix), meta_tmp = fs::path(meta_path(ply)).concat(suffix);
  const auto fail = [&](const absl::Status& status) {
    fs::remove(ply_tmp, ec);
    fs::remove(meta_tmp, ec);
    return status;
  };
  if (absl::Status s = write_point_cloud_ply(r.points, ply_tmp); !s.ok()) return fail(s);
  std::ofstream out(meta_tmp);
  out << nlohmann::json{{"method", r.method}, {"warnings", r.warnings}, {"notes", r.notes}}.dump(2) << "\n";
  out.close();
  if (!out) return fail(absl::InternalError(absl::StrCat(meta_path(ply).string(), ": cannot write")));
  // The metadata first: a reader needs both files, so a new entry appears only once its points are in place.
  for (const auto& [from, to] : {std::pair{meta_tmp, meta_path(ply)}, std::pair{ply_tmp, ply}}) {
    fs::rename(from, to, ec);
    if (ec) return fail(absl::InternalError(absl::StrCat(to.string(), ": cannot write: ", ec.message())));
  }
  return read_point_cloud_ply(ply);
}

}  // namespace gaps

#include "gs_trainer/gaps/active_set.h"

#include <algorithm>
#include <set>

#include "absl/strings/str_cat.h"

namespace gaps {

int active_capacity(const GapsConfig& c) { return c.active_size > 0 ? c.active_size : c.n_active; }

ActiveSetChange refresh_active_set(const std::map<int, int>& active, const std::vector<int>& admitted,
                                   const std::vector<int>& rejected, int phase, const GapsConfig& c) {
  ActiveSetChange change;
  change.active = active;
  for (int id : admitted) {
    const auto old = change.active.find(id);
    if (old != change.active.end()) {
      change.refreshed.push_back(id);
      change.retired.push_back({id, old->second, absl::StrCat("replaced by its generation of phase ", phase)});
    }
    change.active[id] = phase;
    change.entered.push_back(id);
  }
  if (!c.refresh_active_set) return change;

  const auto retire = [&](int id, const std::string& reason) {
    change.retired.push_back({id, change.active.at(id), reason});
    change.active.erase(id);
  };
  for (int id : rejected)
    if (change.active.count(id) > 0) retire(id, absl::StrCat("its regeneration in phase ", phase, " was rejected"));
  if (c.active_max_age > 0) {
    std::vector<int> aged;
    for (const auto& [id, born] : change.active)
      if (phase - born >= c.active_max_age) aged.push_back(id);
    for (int id : aged)
      retire(id,
             absl::StrCat("generated in phase ", change.active.at(id), ", ", c.active_max_age, " or more phases ago"));
  }
  const int capacity = active_capacity(c);
  if (capacity > 0 && static_cast<int>(change.active.size()) > capacity) {
    std::vector<std::pair<int, int>> by_age;  // (phase generated, -id): oldest first, then the higher id
    for (const auto& [id, born] : change.active) by_age.push_back({born, -id});
    std::sort(by_age.begin(), by_age.end());
    const size_t excess = change.active.size() - capacity;
    for (size_t k = 0; k < excess; ++k)
      retire(-by_age[k].second, absl::StrCat("displaced by newer views (the active set holds ", capacity, ")"));
  }
  return change;
}

}  // namespace gaps

#pragma once
// The active set: which admitted pseudo-views the GS optimisation trains on after a diffusion phase (paper
// sec. 3.2: each phase selects n_active views, generates and admits them; the ablation credits "the scored
// selection together with the per-phase refresh"). The paper does not spell the refresh out; ours:
//   - a view admitted this phase enters, replacing its own older generation if that was active;
//   - an active view whose regeneration this phase was rejected leaves (the model has moved on from it);
//   - a view generated active_max_age phases ago or earlier leaves (when active_max_age > 0);
//   - beyond the capacity, the oldest views leave first (then the higher candidate id, for determinism).
// Without refresh_active_set nothing leaves: every admitted view trains until the end.
#include <map>
#include <string>
#include <vector>

#include "gs_trainer/gaps/config.h"

namespace gaps {

struct RetiredView {
  int id = -1;
  int generated_in_phase = -1;
  std::string reason;
};

struct ActiveSetChange {
  std::vector<int> entered;          // admitted this phase, in the order given
  std::vector<int> refreshed;        // of `entered`, those that replaced an older generation of themselves
  std::vector<RetiredView> retired;  // left the set, with why
  std::map<int, int> active;         // after the phase: candidate id -> phase it was generated in
};

// The capacity of the active set: c.active_size, or n_active when that is 0.
int active_capacity(const GapsConfig& c);

// `active`: candidate id -> phase its active view was generated in, before this phase. `admitted` and
// `rejected`: the candidate ids this phase generated, by the gate's decision.
ActiveSetChange refresh_active_set(const std::map<int, int>& active, const std::vector<int>& admitted,
                                   const std::vector<int>& rejected, int phase, const GapsConfig& c);

}  // namespace gaps

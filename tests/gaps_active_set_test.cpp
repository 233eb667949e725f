// The active set's refresh (gs_trainer/gaps/active_set.h): what enters, what leaves and why.
#include <gtest/gtest.h>

#include <map>
#include <string>
#include <vector>

#include "gs_trainer/gaps/active_set.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

GapsConfig rules(int capacity, int max_age) {
  GapsConfig c;
  c.n_active = capacity;
  c.active_max_age = max_age;
  return c;
}

std::string reason_of(const ActiveSetChange& change, int id) {
  for (const RetiredView& r : change.retired)
    if (r.id == id) return r.reason;
  return "";
}

TEST(ActiveSet, AdmittedViewsEnterAndReplaceTheirOlderGeneration) {
  const ActiveSetChange change = refresh_active_set({{3, 0}, {5, 0}}, {5, 9}, {}, 1, rules(16, 0));
  EXPECT_EQ(change.entered, (std::vector<int>{5, 9}));
  EXPECT_EQ(change.refreshed, (std::vector<int>{5}));
  ASSERT_EQ(change.retired.size(), 1u);
  EXPECT_EQ(change.retired[0].id, 5);
  EXPECT_EQ(change.retired[0].generated_in_phase, 0);
  EXPECT_TRUE(test::contains(change.retired[0].reason, "replaced by its generation of phase 1"));
  EXPECT_EQ(change.active, (std::map<int, int>{{3, 0}, {5, 1}, {9, 1}}));
}

TEST(ActiveSet, AViewWhoseRegenerationIsRejectedLeaves) {
  const ActiveSetChange change = refresh_active_set({{3, 0}, {5, 0}}, {}, {3, 7}, 1, rules(16, 0));
  EXPECT_EQ(change.active, (std::map<int, int>{{5, 0}}));
  ASSERT_EQ(change.retired.size(), 1u);  // 7 was never active
  EXPECT_TRUE(test::contains(reason_of(change, 3), "regeneration in phase 1 was rejected"));
}

TEST(ActiveSet, ViewsAgeOutAfterMaxAgePhases) {
  const ActiveSetChange change = refresh_active_set({{1, 0}, {2, 1}, {3, 2}}, {4}, {}, 3, rules(16, 2));
  EXPECT_EQ(change.active, (std::map<int, int>{{3, 2}, {4, 3}}));
  EXPECT_TRUE(test::contains(reason_of(change, 1), "generated in phase 0, 2 or more phases ago"));
  EXPECT_TRUE(test::contains(reason_of(change, 2), "generated in phase 1"));
}

TEST(ActiveSet, BeyondTheCapacityTheOldestLeaveFirst) {
  const ActiveSetChange change = refresh_active_set({{1, 0}, {2, 1}, {3, 1}}, {4, 5}, {}, 2, rules(3, 0));
  // Oldest first (1, phase 0), then among phase 1 the higher id (3).
  EXPECT_EQ(change.active, (std::map<int, int>{{2, 1}, {4, 2}, {5, 2}}));
  EXPECT_TRUE(test::contains(reason_of(change, 1), "displaced by newer views (the active set holds 3)"));
  EXPECT_TRUE(test::contains(reason_of(change, 3), "displaced"));
  GapsConfig sized = rules(3, 0);
  sized.active_size = 4;  // active_size overrides n_active
  EXPECT_EQ(active_capacity(sized), 4);
  EXPECT_EQ(refresh_active_set({{1, 0}, {2, 1}, {3, 1}}, {4, 5}, {}, 2, sized).active.size(), 4u);
}

TEST(ActiveSet, WithoutRefreshEveryAdmittedViewStays) {
  GapsConfig c = rules(2, 1);
  c.refresh_active_set = false;
  const ActiveSetChange change = refresh_active_set({{1, 0}, {2, 0}}, {2, 3}, {1}, 5, c);
  EXPECT_EQ(change.active, (std::map<int, int>{{1, 0}, {2, 5}, {3, 5}}));
  ASSERT_EQ(change.retired.size(), 1u);  // only 2's older generation, replaced
  EXPECT_EQ(change.retired[0].id, 2);
}

}  // namespace
}  // namespace gaps

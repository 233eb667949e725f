// The backends' option tables (diffusion_worker/option_table.h): every entry sets its own field, errors name
// the key and what it accepts, an unknown key lists the known ones, and the README lists the sdxl and restore
// tables.
#include <fstream>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "diffusion_worker/reproject_generator.h"
#include "diffusion_worker/restore_generator.h"
#include "diffusion_worker/sdxl_generator.h"

namespace gaps {
namespace {

::testing::AssertionResult contains_all(const absl::Status& status, const std::vector<std::string>& parts) {
  const std::string text(status.message());
  for (const std::string& part : parts)
    if (text.find(part) == std::string::npos)
      return ::testing::AssertionFailure() << "'" << part << "' not in: " << text;
  return ::testing::AssertionSuccess();
}

// The first of a few values of every JSON type that the option accepts and that differs from its default.
template <typename Options>
std::optional<nlohmann::json> valid_non_default(const Option<Options>& option) {
  const nlohmann::json fallback = option.get(Options{});
  for (const nlohmann::json& value :
       std::vector<nlohmann::json>{"x", "float16", "reproject", true, false, 2, 3, 5, 0.25, 0.75}) {
    Options options;
    if (option.set(value, options) && value.dump() != fallback.dump()) return value;
  }
  return std::nullopt;
}

// Setting an option's key gives its field that value and leaves every other option's field at its default.
template <typename Options>
void expect_round_trips(const OptionTable<Options>& table) {
  const Options defaults;
  for (const Option<Options>& option : table.options()) {
    const std::optional<nlohmann::json> value = valid_non_default(option);
    ASSERT_TRUE(value) << option.name << ": no valid value besides its default among the candidates";
    Options options;
    ASSERT_TRUE(table.apply({{option.name, *value}}, options).ok()) << option.name;
    EXPECT_EQ(option.get(options), *value) << option.name;
    for (const Option<Options>& other : table.options()) {
      if (other.name == option.name) continue;
      EXPECT_EQ(other.get(options).dump(), other.get(defaults).dump()) << option.name << " also set " << other.name;
    }
  }
}

template <typename Options>
void expect_wrong_types_named(const OptionTable<Options>& table) {
  for (const Option<Options>& option : table.options()) {
    Options options;
    const absl::Status status = table.apply({{option.name, nlohmann::json::array({1})}}, options);
    EXPECT_TRUE(contains_all(status, {"'" + option.name + "'", "must be " + option.accepts}));
  }
}

TEST(SdxlOptionTableTest, EveryOptionRoundTripsAValidValue) { expect_round_trips(sdxl_option_table()); }
TEST(ReprojectOptionTableTest, EveryOptionRoundTripsAValidValue) { expect_round_trips(reproject_option_table()); }
TEST(RestoreOptionTableTest, EveryOptionRoundTripsAValidValue) { expect_round_trips(restore_option_table()); }

TEST(SdxlOptionTableTest, WrongTypesNameTheKeyAndTheExpectedType) {
  expect_wrong_types_named(sdxl_option_table());
  const auto error = [](const std::string& extra) {
    return parse_sdxl_options(R"({"weights": "w", )" + extra + "}").status();
  };
  EXPECT_TRUE(contains_all(error(R"("weights": 3)"), {"'weights'", "a string"}));
  EXPECT_TRUE(contains_all(error(R"("steps": 2.5)"), {"'steps'", "an integer >= 1"}));
  EXPECT_TRUE(contains_all(error(R"("guidance": "5")"), {"'guidance'", "a number >= 0"}));
  EXPECT_TRUE(contains_all(error(R"("cuda_graphs": 1)"), {"'cuda_graphs'", "true or false"}));
  EXPECT_TRUE(contains_all(error(R"("dtype": "int8")"), {"'dtype'", "float32, float16 or bfloat16"}));
}

TEST(ReprojectOptionTableTest, WrongTypesNameTheKeyAndTheExpectedType) {
  expect_wrong_types_named(reproject_option_table());
  EXPECT_TRUE(contains_all(parse_reproject_options(R"({"splat_footprint": 1.5})").status(),
                           {"'splat_footprint'", "an integer in [1, 8]"}));
  EXPECT_TRUE(contains_all(parse_reproject_options(R"({"depth_tolerance": "low"})").status(),
                           {"'depth_tolerance'", "a number in [0, 1)"}));
}

TEST(RestoreOptionTableTest, WrongTypesNameTheKeyAndTheExpectedType) {
  expect_wrong_types_named(restore_option_table());
  EXPECT_TRUE(contains_all(parse_restore_options(R"({"tile": 1.5})").status(), {"'tile'", "an integer >= 0"}));
  EXPECT_TRUE(
      contains_all(parse_restore_options(R"({"compose": "sdxl"})").status(), {"'compose'", "none or reproject"}));
  EXPECT_TRUE(
      contains_all(parse_restore_options(R"({"dtype": "half"})").status(), {"'dtype'", "auto, float32 or float16"}));
}

TEST(RestoreOptionTableTest, UnknownKeysListTheKnownOnes) {
  std::vector<std::string> parts = {"unknown restore option 'tiles'", "did you mean 'tile'"};
  for (const std::string& name : restore_option_table().names()) parts.push_back(name);
  EXPECT_TRUE(contains_all(parse_restore_options(R"({"tiles": 2})").status(), parts));
}

// Open and closed ends, odd sizes, finite numbers, integers beyond int64.
TEST(SdxlOptionTableTest, RangesKeepTheirEnds) {
  const auto accepted = [](const std::string& key, const nlohmann::json& value) {
    SdxlOptions options;
    return sdxl_option_table().apply({{key, value}}, options).ok();
  };
  EXPECT_FALSE(accepted("control_min_alpha", 0));
  EXPECT_TRUE(accepted("control_max_relative_variance", 0));
  EXPECT_FALSE(accepted("control_variance_window", 4));
  EXPECT_TRUE(accepted("control_variance_window", 1));
  EXPECT_TRUE(accepted("lora_steps", 0));
  EXPECT_FALSE(accepted("lora_steps", -1));
  EXPECT_FALSE(accepted("lora_rank", 0));
  EXPECT_FALSE(accepted("lora_lr", 0));
  EXPECT_FALSE(accepted("batch_size", 0));
  EXPECT_TRUE(accepted("inpaint_uncovered_fraction", 0));
  EXPECT_FALSE(accepted("inpaint_uncovered_fraction", 1));
  EXPECT_FALSE(accepted("inpaint_dilation", 14));
  EXPECT_TRUE(accepted("inpaint_depth_threshold", 0));
  EXPECT_FALSE(accepted("inpaint_guidance", std::numeric_limits<double>::infinity()));
  EXPECT_FALSE(accepted("steps", nlohmann::json::parse("18446744073709551615")));
}

TEST(ReprojectOptionTableTest, OptionsBuiltInCodeAreCheckedByTheSameTable) {
  EXPECT_TRUE(validate_reproject_options(ReprojectOptions{}).ok());
  ReprojectOptions options;
  options.splat_footprint = 9;
  EXPECT_TRUE(contains_all(validate_reproject_options(options), {"'splat_footprint' = 9", "an integer in [1, 8]"}));
  options = ReprojectOptions{};
  options.min_reference_alpha = 0;
  EXPECT_TRUE(contains_all(validate_reproject_options(options), {"'min_reference_alpha' = 0", "in (0, 1]"}));
}

TEST(SdxlOptionTableTest, UnknownKeysListTheKnownOnes) {
  const absl::Status status = parse_sdxl_options(R"({"weights": "w", "stepz": 3})").status();
  std::vector<std::string> parts = {"unknown sdxl option 'stepz'", "did you mean 'steps'"};
  for (const std::string& name : sdxl_option_table().names()) parts.push_back(name);
  EXPECT_TRUE(contains_all(status, parts));
  const absl::Status far = parse_sdxl_options(R"({"weights": "w", "colour": 3})").status();
  EXPECT_TRUE(contains_all(far, {"unknown sdxl option 'colour'", "known: weights, "}));
  EXPECT_FALSE(contains_all(far, {"did you mean"}));
}

TEST(ReprojectOptionTableTest, UnknownKeysListTheKnownOnes) {
  const absl::Status status = parse_reproject_options(R"({"footprint": 2})").status();
  std::vector<std::string> parts = {"unknown reproject option 'footprint'", "did you mean 'splat_footprint'"};
  for (const std::string& name : reproject_option_table().names()) parts.push_back(name);
  EXPECT_TRUE(contains_all(status, parts));
}

// The first column of a backend's option table (the first table of its section "## The `<backend>` backend")
// in diffusion_worker/README.md, in order.
std::vector<std::string> readme_keys(const std::string& backend) {
  std::ifstream in(std::string(GAPS_TEST_SCRIPTS_DIR) + "/../diffusion_worker/README.md");
  std::string line;
  while (std::getline(in, line) && line != "## The `" + backend + "` backend") {
  }
  std::vector<std::string> keys;
  bool in_table = false;
  while (std::getline(in, line)) {
    if (line.rfind("| ", 0) != 0) {
      if (in_table) break;
      continue;
    }
    in_table = true;
    if (line.rfind("| `", 0) == 0) keys.push_back(line.substr(3, line.find('`', 3) - 3));
  }
  return keys;
}

TEST(SdxlOptionTableTest, ReadmeListsExactlyTheTablesOptions) {
  EXPECT_EQ(readme_keys("sdxl"), sdxl_option_table().names());
}

TEST(RestoreOptionTableTest, ReadmeListsExactlyTheTablesOptions) {
  EXPECT_EQ(readme_keys("restore"), restore_option_table().names());
}

}  // namespace
}  // namespace gaps

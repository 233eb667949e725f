// The option tables (common/option_table.h) against everything that carries options: JSON files, the
// gaps.v1 proto, the service's RunOptions and metrics.json's record. Every field of TrainConfig and
// GapsConfig is enumerated from the tables, so a field added to a table but not to the proto fails here.
#include <string>

#include <google/protobuf/descriptor.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "gaps/v1/trainer.pb.h"
#include "gs_trainer/gaps/config.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/train/train_config.h"
#include "rpc/config_codec.h"
#include "server/job_config.h"
#include "tests/option_values.h"

namespace gaps {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::FieldDescriptor;

template <typename Config>
std::string error_of(const nlohmann::json& j) {
  try {
    j.get<Config>();
  } catch (const std::exception& e) {
    return json_error_message(e);
  }
  return "";
}

FieldDescriptor::CppType proto_type_of(const std::string& table_type) {
  if (table_type == "int") return FieldDescriptor::CPPTYPE_INT32;
  if (table_type == "int64_t") return FieldDescriptor::CPPTYPE_INT64;
  if (table_type == "uint64_t") return FieldDescriptor::CPPTYPE_UINT64;
  if (table_type == "bool") return FieldDescriptor::CPPTYPE_BOOL;
  if (table_type == "std::string") return FieldDescriptor::CPPTYPE_STRING;
  return FieldDescriptor::CPPTYPE_DOUBLE;  // double and std::vector<double>
}

void expect_proto_matches_table(const Descriptor* message, const std::vector<OptionInfo>& table) {
  for (const OptionInfo& o : table) {
    const FieldDescriptor* f = message->FindFieldByName(o.name);
    ASSERT_NE(f, nullptr) << message->full_name() << " has no field for the option '" << o.name << "'";
    EXPECT_EQ(f->cpp_type(), proto_type_of(o.type)) << o.name;
    EXPECT_EQ(f->is_repeated(), o.type == "std::vector<double>") << o.name;
    EXPECT_TRUE(f->is_repeated() || f->has_presence()) << o.name << ": unset must mean the default";
  }
  for (int i = 0; i < message->field_count(); ++i) {
    const std::string name = message->field(i)->name();
    EXPECT_TRUE(std::any_of(table.begin(), table.end(), [&](const OptionInfo& o) { return o.name == name; }))
        << message->full_name() << "." << name << " is in no option table";
  }
}

TEST(Options, TheProtoCarriesEveryOptionWithItsType) {
  expect_proto_matches_table(v1::TrainHyperparameters::descriptor(), train_config_options());
  expect_proto_matches_table(v1::GapsHyperparameters::descriptor(), gaps_config_options());
}

TEST(Options, NamesAreUniqueAcrossTablesSoEachCanBeAFlag) {
  std::set<std::string> names;
  for (const auto& table : {train_config_options(), gaps_config_options()})
    for (const OptionInfo& o : table) EXPECT_TRUE(names.insert(o.name).second) << o.name;
}

TEST(Options, TheTwoStageDefaultsAreTheGeneratorSeams) {
  const InpaintSettings seam;
  const InpaintSettings from_config = inpaint_settings(GapsConfig{});
  EXPECT_EQ(from_config.depth_threshold, seam.depth_threshold);
  EXPECT_EQ(from_config.uncovered_fraction, seam.uncovered_fraction);
  EXPECT_EQ(from_config.dilation, seam.dilation);
}

// Non-default values for every field: JSON -> structs, and JSON -> proto -> RunOptions (the service's path)
// -> metrics.json's record, all identical.
TEST(Options, EveryOptionRoundTripsThroughJsonProtoRunOptionsAndTheRecord) {
  const nlohmann::json training = test::non_default_options(train_config_options());
  const nlohmann::json gaps = test::non_default_options(gaps_config_options());
  for (const auto& [key, value] : training.items()) EXPECT_NE(value, nlohmann::json(TrainConfig{})[key]) << key;
  for (const auto& [key, value] : gaps.items()) EXPECT_NE(value, nlohmann::json(GapsConfig{})[key]) << key;
  const TrainConfig from_file = training.get<TrainConfig>();
  const GapsConfig gaps_from_file = gaps.get<GapsConfig>();
  EXPECT_EQ(nlohmann::json(from_file), training);
  EXPECT_EQ(nlohmann::json(gaps_from_file), gaps);

  v1::TrainConfig proto;
  proto.set_views(3);
  proto.set_variant("full");
  ASSERT_TRUE(rpc::set_fields(training, proto.mutable_training()).ok());
  ASSERT_TRUE(rpc::set_fields(gaps, proto.mutable_gaps()).ok());
  v1::TrainConfig decoded;
  ASSERT_TRUE(decoded.ParseFromString(proto.SerializeAsString()));
  const auto o = run_options_from_proto(decoded, false, "", from_file.device);
  ASSERT_TRUE(o.ok()) << o.status();
  EXPECT_EQ(nlohmann::json(o->config), training);
  EXPECT_EQ(nlohmann::json(o->gaps), gaps);

  RunResult result;
  result.config = o->config;
  result.gaps = o->gaps;
  const nlohmann::json record = run_configuration_json(*o, result);
  EXPECT_EQ(record.at("config"), training);
  EXPECT_EQ(record.at("gaps"), gaps);
}

TEST(Options, ValuesOutsideTheirRangeAreRefusedNamingTheOption) {
  for (const auto& [table, is_training] : {std::pair{train_config_options(), true}, {gaps_config_options(), false}}) {
    for (const OptionInfo& o : table) {
      if (!o.default_value.is_number()) continue;
      for (const double bad : {o.max * 2 + 1, o.min - 1, std::nan("")}) {
        if ((!std::isfinite(bad) && !std::isnan(bad)) || std::abs(bad) > 9e18) continue;  // the type's own limit
        if (o.default_value.is_number_integer() && std::isnan(bad)) continue;
        nlohmann::json j = {{o.name, bad}};
        if (o.default_value.is_number_integer()) j[o.name] = static_cast<int64_t>(std::max(-9e18, std::min(9e18, bad)));
        if (o.type == "uint64_t" && bad < 0) j[o.name] = -1;
        const std::string error = is_training ? error_of<TrainConfig>(j) : error_of<GapsConfig>(j);
        EXPECT_NE(error.find("'" + o.name + "'"), std::string::npos) << o.name << " = " << j[o.name] << ": " << error;
      }
    }
  }
}

TEST(Options, WrongTypesAndUnknownKeysAreRefusedNamingTheKey) {
  EXPECT_NE(error_of<TrainConfig>({{"iterations", 10}, {"iteration", 10}}).find("unknown training option 'iteration'"),
            std::string::npos);
  EXPECT_NE(error_of<GapsConfig>({{"phase_intervall", 250}}).find("unknown GAPS option 'phase_intervall'"),
            std::string::npos);
  EXPECT_NE(error_of<TrainConfig>({{"iterations", 2.5}}).find("'iterations' must be an integer"), std::string::npos);
  EXPECT_NE(error_of<TrainConfig>({{"iterations", 1e40}}).find("'iterations' must be an integer"), std::string::npos);
  EXPECT_NE(error_of<TrainConfig>({{"iterations", 2147483648LL}}).find("'iterations' is out of the range"),
            std::string::npos);
  EXPECT_NE(error_of<TrainConfig>({{"device", "tpu"}}).find("'device'"), std::string::npos);
  EXPECT_NE(error_of<GapsConfig>({{"tier_alpha_min", {0, "a"}}}).find("'tier_alpha_min'"), std::string::npos);
  EXPECT_NE(error_of<GapsConfig>({{"warmup_iterations", -1}}).find("'warmup_iterations'"), std::string::npos);
  EXPECT_EQ(error_of<TrainConfig>(nlohmann::json::object()), "");
}

TEST(Options, NActiveFollowsTheViewsLayoutUnlessGiven) {
  GapsConfig c;
  EXPECT_EQ(c.n_active, 0);
  EXPECT_EQ(n_active_for(c, /*views_surround_scene=*/false), kNActiveLlff);
  EXPECT_EQ(n_active_for(c, true), kNActiveMip360);
  c.n_active = 5;
  EXPECT_EQ(n_active_for(c, true), 5);
}

}  // namespace
}  // namespace gaps

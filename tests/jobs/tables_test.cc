// Every engine's Validate() refuses each field outside the range its descriptor table states,
// naming the field: the tables that ListMethods, the CLI and the docs show are the rules the
// engines apply.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <iterator>
#include <limits>

#include "worker/front/front_tracking.h"
#include "worker/jobs/method_registry.h"
#include "worker/mls/algebraic_mls.h"
#include "worker/mls/iamls.h"
#include "worker/pu/pu.h"
#include "worker/render/render.h"

namespace lsqsurf {
namespace {

// Values just outside the field's accepted set (none for flags: a bool holds no third value).
std::vector<double> Outside(const core::ParamInfo& info) {
  switch (info.type) {
    case core::ParamType::kReal: {
      const auto beyond = [](double bound, double direction) {
        return bound + direction * std::max(1e-9, 1e-3 * std::abs(bound));
      };
      return {beyond(info.min_value, -1), beyond(info.max_value, 1), std::numeric_limits<double>::quiet_NaN()};
    }
    case core::ParamType::kInteger: {
      std::vector<double> out{info.max_value + 1};
      if (info.min_value >= 1) out.push_back(info.min_value - 1);  // Unsigned fields cannot go below 0.
      return out;
    }
    case core::ParamType::kChoice: {
      int largest = 0;
      for (const auto& c : info.choices) largest = std::max(largest, c.value);
      return {static_cast<double>(largest + 1)};
    }
    case core::ParamType::kFlag:
    case core::ParamType::kText:
    case core::ParamType::kRealList: return {};
  }
  return {};
}

template <class P>
void ExpectValidateEnforcesTheTable(const core::ParamTable<P>& table, absl::Status (*validate)(const P&),
                                    const P& defaults, const char* what) {
  ASSERT_TRUE(validate(defaults).ok()) << what << ": " << validate(defaults);
  int checked = 0;
  for (const auto& field : table.fields()) {
    if (!field.set) continue;
    for (double value : Outside(field.info)) {
      P p = defaults;
      field.set(p, value);
      const absl::Status s = validate(p);
      EXPECT_FALSE(s.ok()) << what << "." << field.info.name << "=" << value << " was accepted";
      EXPECT_NE(s.message().find(field.info.name), std::string_view::npos)
          << what << "." << field.info.name << "=" << value << ": " << s;
      ++checked;
    }
  }
  EXPECT_GT(checked, 0) << what;
}

TEST(DescriptorTables, EveryEngineValidatesWhatItsTableStates) {
  ExpectValidateEnforcesTheTable(pu::PuParamTable(), &pu::Validate, pu::PuParams{}, "pu");
  ExpectValidateEnforcesTheTable(mls::IamlsParamTable(), &mls::Validate, mls::IamlsParams{}, "iamls");
  mls::AlgebraicMlsParams ramls, apss;
  ramls.fit = mls::AlgebraicFit::kRamls;
  apss.fit = mls::AlgebraicFit::kApss;
  ExpectValidateEnforcesTheTable(mls::AlgebraicMlsParamTable(ramls.fit), &mls::Validate, ramls, "ramls");
  ExpectValidateEnforcesTheTable(mls::AlgebraicMlsParamTable(apss.fit), &mls::Validate, apss, "apss");
  ExpectValidateEnforcesTheTable(front::TrackingParamTable(), &front::Validate, front::TrackingParams{}, "track");
  ExpectValidateEnforcesTheTable(render::ViewParamTable(), &render::Validate, render::RenderParams{}, "view");
}

// The cross-field rules are the engines' too: a combination each field allows alone is refused.
// The spec format a job is stored with (JobRecord::spec_format) is raised with every change to
// the methods' tables: the last format listed is this build's tables.
TEST(SpecFormats, TheLastFormatListedHasThisBuildsTables) {
  const auto& formats = jobs::kSpecFormats;
  for (size_t i = 1; i < std::size(formats); ++i) EXPECT_EQ(formats[i].format, formats[i - 1].format + 1);
  char fingerprint[24];
  std::snprintf(fingerprint, sizeof(fingerprint), "0x%016llx",
                static_cast<unsigned long long>(jobs::SpecFingerprint()));
  EXPECT_EQ(formats[std::size(formats) - 1].fingerprint, jobs::SpecFingerprint())
      << "a method, parameter or view option changed: append {" << jobs::kSpecFormat + 1 << ", " << fingerprint
      << "} to kSpecFormats in worker/jobs/method_registry.h";
  EXPECT_EQ(jobs::RegistrySpecTables().format, jobs::kSpecFormat);
}

TEST(DescriptorTables, CrossFieldRulesNameWhatToChange) {
  front::TrackingParams p;
  p.marker_spacing = 0.6;
  p.marker_gap = 0.5;  // Both in range, but gaps would be filled and thinned again at once.
  const absl::Status s = front::Validate(p);
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("marker_gap"), std::string_view::npos) << s;
  pu::PuParams noisy;
  noisy.noise_level = -0.5;  // In the table's [-1, 0.1], but only -1 means "estimate".
  EXPECT_NE(pu::Validate(noisy).message().find("noise_level"), std::string_view::npos);
}

}  // namespace
}  // namespace lsqsurf

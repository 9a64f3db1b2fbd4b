// Descriptor tables: per-field checks, cross-field rules, text parsing and the stored form.
#include "worker/core/params.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <vector>

namespace lsqsurf::core {
namespace {

enum class Shape { kBall = 0, kCube = 4 };

struct Example {
  double radius = 1.5;
  int count = 3;
  bool smooth = true;
  Shape shape = Shape::kCube;
  std::string label = "a;b=c";  // Characters the stored form must escape.
  double low = 0.1, high = 0.2;
};

const ParamTable<Example>& ExampleTable() {
  static const auto* table = [] {
    auto* t = new ParamTable<Example>();
    t->Real<&Example::radius>("radius", 0.5, 10, "mm", "ball radius")
        .Integer<&Example::count>("count", 1, 20, "", "how many")
        .Flag<&Example::smooth>("smooth", "smooth shading")
        .Choice<&Example::shape>("shape", {{"ball", 0, "round"}, {"cube", 4, "square"}}, "the shape")
        .Text<&Example::label>("label", "a name")
        .Real<&Example::low>("low", 0, 1, "", "lower bound")
        .Real<&Example::high>("high", 0, 1, "", "upper bound")
        .AddRule([](const Example& e) {
          return e.low < e.high ? absl::OkStatus() : absl::InvalidArgumentError("low must be below high");
        });
    return t;
  }();
  return *table;
}

TEST(Params, DescribeReportsTheStructsDefaults) {
  const auto infos = ExampleTable().Describe();
  ASSERT_EQ(infos.size(), 7u);
  EXPECT_EQ(infos[0].name, "radius");
  EXPECT_EQ(infos[0].default_value, Example{}.radius);
  EXPECT_EQ(infos[0].unit, "mm");
  EXPECT_EQ(infos[3].default_value, 4);  // The choice's value, not its position.
  EXPECT_EQ(infos[4].default_text, Example{}.label);
}

TEST(Params, EachFieldIsCheckedAgainstItsOwnRange) {
  ParamSet set(ExampleTable());
  EXPECT_TRUE(set.Set("radius", 0.5).ok());
  EXPECT_TRUE(set.Set("radius", 10).ok());
  const absl::Status low = set.Set("radius", 0.4);
  EXPECT_EQ(low.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(low.message().find("radius=0.4 is out of range"), std::string_view::npos) << low;
  EXPECT_NE(set.Set("count", 2.5).message().find("not a whole number"), std::string_view::npos);
  EXPECT_FALSE(set.Set("count", std::nan("")).ok());
  EXPECT_FALSE(set.Set("smooth", 2).ok());
  EXPECT_FALSE(set.Set("shape", 1).ok());  // Between the choices' values.
  EXPECT_FALSE(set.Set("label", 1).ok());  // Text, not a number.
  const absl::Status unknown = set.Set("radios", 1);
  EXPECT_NE(unknown.message().find("valid parameters: radius, count"), std::string_view::npos) << unknown;
  EXPECT_EQ(set.Get("radius"), 10);  // Refused values left the last good one.
}

TEST(Params, CrossFieldRulesRunInValidate) {
  ParamSet set(ExampleTable());
  ASSERT_TRUE(set.Validate().ok());
  ASSERT_TRUE(set.Set("low", 0.5).ok());  // In range alone, but not below high.
  const absl::Status s = set.Validate();
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(s.message(), "low must be below high");
  // Direct edits skip the per-field checks; Validate still catches them.
  set.Mutable<Example>()->low = 0.1;
  set.Mutable<Example>()->radius = 99;
  EXPECT_NE(set.Validate().message().find("radius=99"), std::string_view::npos);
}

TEST(Params, ParseTakesTheTextFormsUsersType) {
  ParamSet set(ExampleTable());
  EXPECT_TRUE(set.Parse("radius", "2.25").ok());
  EXPECT_EQ(set.Get("radius"), 2.25);
  EXPECT_TRUE(set.Parse("smooth", "false").ok());
  EXPECT_EQ(set.Get("smooth"), 0);
  EXPECT_TRUE(set.Parse("smooth", "1").ok());
  EXPECT_EQ(set.Get("smooth"), 1);
  EXPECT_TRUE(set.Parse("shape", "ball").ok());
  EXPECT_EQ(set.As<Example>()->shape, Shape::kBall);
  const absl::Status bad_choice = set.Parse("shape", "cone");
  EXPECT_NE(bad_choice.message().find("ball"), std::string_view::npos) << bad_choice;  // Lists the choices.
  EXPECT_FALSE(set.Parse("radius", "2mm").ok());
  EXPECT_FALSE(set.Parse("count", "").ok());
  EXPECT_TRUE(set.Parse("label", "x y").ok());
  EXPECT_EQ(set.GetText("label"), "x y");
}

TEST(Params, TheStoredFormRoundTrips) {
  ParamSet set(ExampleTable());
  ASSERT_TRUE(set.Set("radius", 0.1 + 0.2 + 5).ok());  // Needs every digit to survive.
  ASSERT_TRUE(set.Parse("shape", "ball").ok());
  ASSERT_TRUE(set.SetText("label", "semi;colon=equals\\slash").ok());
  ParamSet back(ExampleTable());
  ASSERT_TRUE(back.Decode(set.Encode()).ok()) << set.Encode();
  EXPECT_EQ(back.Get("radius"), set.Get("radius"));
  EXPECT_EQ(back.GetText("label"), "semi;colon=equals\\slash");
  EXPECT_EQ(back.As<Example>()->shape, Shape::kBall);
  EXPECT_EQ(back.Encode(), set.Encode());
  // Names a table no longer has are skipped; values that no longer fit are refused.
  EXPECT_TRUE(back.Decode("retired=3;count=5;").ok());
  EXPECT_EQ(back.Get("count"), 5);
  EXPECT_FALSE(back.Decode("count=500;").ok());
}

struct Levels {
  std::vector<double> any;           // Any finite numbers.
  std::vector<double> unit = {0.5};  // Each within [0, 1].
};

const ParamTable<Levels>& LevelsTable() {
  static const auto* table = [] {
    auto* t = new ParamTable<Levels>();
    const double inf = std::numeric_limits<double>::infinity();
    t->RealList<&Levels::any>("any", 3, -inf, inf, "", "levels").RealList<&Levels::unit>("unit", 2, 0, 1, "", "shares");
    return t;
  }();
  return *table;
}

TEST(Params, ListsAreCountedCheckedParsedAndStored) {
  const auto infos = LevelsTable().Describe();
  EXPECT_EQ(infos[0].RangeText(), "up to 3 values, each any number");
  EXPECT_EQ(infos[1].RangeText(), "up to 2 values, each [0, 1]");
  EXPECT_EQ(infos[1].default_list, std::vector<double>{0.5});
  ParamSet set(LevelsTable());
  ASSERT_TRUE(set.Parse("any", "-1e300, 0.1,2").ok());
  EXPECT_EQ(set.GetList("any"), (std::vector<double>{-1e300, 0.1, 2}));
  const absl::Status too_many = set.SetList("any", {1, 2, 3, 4});
  EXPECT_EQ(too_many.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(too_many.message().find("4 values; it takes at most 3"), std::string_view::npos) << too_many;
  EXPECT_NE(set.SetList("any", {1, std::nan("")}).message().find("value 2 of any=nan is not a finite number"),
            std::string_view::npos)
      << set.SetList("any", {1, std::nan("")});
  EXPECT_NE(set.Parse("unit", "0.2,1.5").message().find("unit=1.5 is out of range"), std::string_view::npos);
  EXPECT_NE(set.Parse("any", "0.5;0.7").message().find("'0.5;0.7' is not a number"), std::string_view::npos);
  EXPECT_EQ(set.GetList("any"), (std::vector<double>{-1e300, 0.1, 2}));  // Refused lists left the last good one.
  ASSERT_TRUE(set.Set("unit", 0.25).ok());                               // One number is a list of one.
  ParamSet back(LevelsTable());
  ASSERT_TRUE(back.Decode(set.Encode()).ok()) << set.Encode();
  EXPECT_EQ(back.GetList("any"), set.GetList("any"));
  EXPECT_EQ(back.GetList("unit"), std::vector<double>{0.25});
  ASSERT_TRUE(back.Parse("any", "").ok());  // An empty list is one.
  EXPECT_TRUE(back.GetList("any")->empty());
  EXPECT_FALSE(back.Decode("unit=0.1,0.2,0.3;").ok());
}

TEST(Params, CopiesAreIndependentAndTypesAreKept) {
  ParamSet a(ExampleTable());
  ParamSet b = a;
  ASSERT_TRUE(b.Set("count", 7).ok());
  EXPECT_EQ(a.Get("count"), 3);
  EXPECT_TRUE(a.SameType(b));
  EXPECT_EQ(a.As<int>(), nullptr);
  EXPECT_TRUE(ParamSet().empty());
}

TEST(Params, TheReferenceListsEveryField) {
  const std::string md = ParamReferenceMarkdown(ExampleTable().Describe());
  for (const char* name : {"radius", "count", "smooth", "shape", "label", "low", "high"}) {
    EXPECT_NE(md.find(std::string("`") + name + "`"), std::string::npos) << name << "\n" << md;
  }
  EXPECT_NE(md.find("mm"), std::string::npos);
  EXPECT_NE(md.find("ball"), std::string::npos);
}

}  // namespace
}  // namespace lsqsurf::core

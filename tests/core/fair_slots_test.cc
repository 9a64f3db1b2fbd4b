// Slots shared fairly: the limit in all, a named owner's share, the unnamed held only to the limit.
#include "worker/core/fair_slots.h"

#include <gtest/gtest.h>

namespace lsqsurf::core {
namespace {

using Refusal = FairSlots::Refusal;

TEST(FairSlots, NoOwnerHoldsMoreThanItsShareAndNoneMoreThanTheLimit) {
  FairSlots slots(5);  // Share: 3 (half of 5, rounded up).
  EXPECT_EQ(slots.owner_share(), 3);
  for (int i = 0; i < 3; ++i) EXPECT_EQ(slots.TryTake("alice"), Refusal::kNone);
  EXPECT_EQ(slots.TryTake("alice"), Refusal::kOwnerFull);
  EXPECT_EQ(slots.TryTake("bob"), Refusal::kNone);
  EXPECT_EQ(slots.TryTake(""), Refusal::kNone);  // Unnamed: only the limit.
  EXPECT_EQ(slots.held(), 5);
  EXPECT_EQ(slots.TryTake("carol"), Refusal::kFull);
  EXPECT_EQ(slots.TryTake(""), Refusal::kFull);
  EXPECT_EQ(slots.HeldBy("carol"), 0);  // A refusal holds nothing.
  slots.Release("alice");
  EXPECT_EQ(slots.HeldBy("alice"), 2);
  EXPECT_EQ(slots.TryTake("carol"), Refusal::kNone);
  slots.Release("");
  EXPECT_EQ(slots.TryTake("alice"), Refusal::kNone);  // Back to its share.
  EXPECT_EQ(slots.held(), 5);
}

TEST(FairSlots, EveryOwnerGetsAtLeastOneAndAReleasedOwnerIsForgotten) {
  FairSlots one(1, 0.1);
  EXPECT_EQ(one.owner_share(), 1);
  EXPECT_EQ(one.TryTake("alice"), Refusal::kNone);
  one.Release("alice");
  EXPECT_EQ(one.HeldBy("alice"), 0);
  EXPECT_EQ(one.held(), 0);
  EXPECT_EQ(one.TryTake("bob"), Refusal::kNone);
}

}  // namespace
}  // namespace lsqsurf::core

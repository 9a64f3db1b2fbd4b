#include "worker/core/fair_slots.h"

#include <algorithm>
#include <cmath>

namespace lsqsurf::core {

FairSlots::FairSlots(int limit, double owner_share)
    : limit_(limit), owner_share_(std::max(1, static_cast<int>(std::ceil(limit * owner_share)))) {}

FairSlots::Refusal FairSlots::TryTake(const std::string& owner) {
  if (held_ >= limit_) return Refusal::kFull;
  if (!owner.empty()) {
    int& mine = by_owner_[owner];
    if (mine >= owner_share_) return Refusal::kOwnerFull;  // Held at least one: the entry stays.
    ++mine;
  }
  ++held_;
  return Refusal::kNone;
}

void FairSlots::Release(const std::string& owner) {
  --held_;
  if (auto it = by_owner_.find(owner); it != by_owner_.end() && --it->second == 0) by_owner_.erase(it);
}

int FairSlots::HeldBy(const std::string& owner) const {
  auto it = by_owner_.find(owner);
  return it == by_owner_.end() ? 0 : it->second;
}

}  // namespace lsqsurf::core

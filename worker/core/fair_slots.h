// worker/core/fair_slots.h — a bounded number of slots shared fairly among owners.
//
// At most `limit` slots are held in all, and a named owner holds at most its share of them
// (`limit` × `owner_share`, rounded up, at least one), so that no one user holds every slot and
// the others wait on them. An unnamed owner ("") is held only to the limit. Used for the server's
// open streams of each kind and for the pictures drawn at once. Not synchronized: the caller
// holds its own lock around every call.
#pragma once

#include <map>
#include <string>

namespace lsqsurf::core {

class FairSlots {
 public:
  enum class Refusal {
    kNone,      // Taken.
    kFull,      // Every slot is held.
    kOwnerFull  // The owner holds its share.
  };
  explicit FairSlots(int limit, double owner_share = 0.5);

  Refusal TryTake(const std::string& owner);
  // Gives back a slot that TryTake gave `owner`.
  void Release(const std::string& owner);

  int limit() const { return limit_; }
  int owner_share() const { return owner_share_; }
  int held() const { return held_; }
  int HeldBy(const std::string& owner) const;

 private:
  int limit_;
  int owner_share_;
  int held_ = 0;
  std::map<std::string, int> by_owner_;  // Named owners holding at least one.
};

}  // namespace lsqsurf::core

// Which listen addresses count as loopback (plaintext allowed without --plaintext).
#include "worker/core/address.h"

#include <gtest/gtest.h>

namespace lsqsurf::core {
namespace {

TEST(Address, OnlyLoopbackAddressesCountAsLoopback) {
  for (const char* loopback :
       {"127.0.0.1:50051", "127.1.2.3:0", "localhost:1", "[::1]:50051", "ipv4:127.0.0.1:5", "unix:/tmp/lsqsurf.sock"}) {
    EXPECT_TRUE(IsLoopback(loopback)) << loopback;
  }
  // A host name that merely starts like a loopback address leads wherever its DNS says.
  for (const char* elsewhere : {"127.evil.example:50051", "127.0.0.1.nip.io:1", "0.0.0.0:50051", "[::]:1",
                                "10.0.0.1:50051", "example.org:443", "128.0.0.1:1"}) {
    EXPECT_FALSE(IsLoopback(elsewhere)) << elsewhere;
  }
}

}  // namespace
}  // namespace lsqsurf::core

// worker/core/address.h — what a HOST:PORT address says about where it leads.
#pragma once

#include <string_view>

namespace lsqsurf::core {

// The host of "HOST:PORT" ("[::1]:50051" gives "[::1]"); the whole text when it has no port.
inline std::string_view HostOf(std::string_view address) {
  const size_t colon = address.rfind(':');
  if (colon == std::string_view::npos || address.find(']', colon) != std::string_view::npos) return address;
  return address.substr(0, colon);
}

// Whether the address's host is this machine's loopback, where traffic stays on the machine
// (the only place plaintext is used without being asked for). "unix:" sockets count as well.
inline bool IsLoopback(std::string_view address) {
  if (address.rfind("unix:", 0) == 0) return true;
  std::string_view host = HostOf(address);
  if (host.rfind("ipv4:", 0) == 0) host.remove_prefix(5);
  return host == "localhost" || host == "[::1]" || host == "::1" || host.rfind("127.", 0) == 0;
}

}  // namespace lsqsurf::core

// worker/core/address.h — what a HOST:PORT address says about where it leads.
#pragma once

#include <arpa/inet.h>
#include <netinet/in.h>

#include <string>
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
// The host must be an address in 127.0.0.0/8 or ::1 (or "localhost"): a name that merely starts
// with "127." may lead anywhere.
inline bool IsLoopback(std::string_view address) {
  if (address.rfind("unix:", 0) == 0) return true;
  std::string_view host = HostOf(address);
  if (host.rfind("ipv4:", 0) == 0 || host.rfind("ipv6:", 0) == 0) host.remove_prefix(5);
  if (host == "localhost") return true;
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') host = host.substr(1, host.size() - 2);
  const std::string text(host);
  in_addr v4{};
  if (inet_pton(AF_INET, text.c_str(), &v4) == 1) return (ntohl(v4.s_addr) >> 24) == 127;
  in6_addr v6{};
  return inet_pton(AF_INET6, text.c_str(), &v6) == 1 && IN6_IS_ADDR_LOOPBACK(&v6);
}

}  // namespace lsqsurf::core

// server/web_assets.h — the job page's files, embedded in lsqsurfd at build time (web/CMakeLists.txt
// writes the table: the page's own files and the libraries npm fetched), so that the running
// server needs neither the network nor files beside it.
#pragma once

#include <span>
#include <string_view>

namespace lsqsurf::server {

struct WebAsset {
  std::string_view path;          // As requested, e.g. "/static/app.js"; "/" for the page.
  std::string_view content_type;  // e.g. "text/javascript" (text is UTF-8).
  std::string_view bytes;
};

// Empty when lsqsurfd was built without the page (LSQSURF_WITH_WEB=OFF).
std::span<const WebAsset> WebAssets();

}  // namespace lsqsurf::server

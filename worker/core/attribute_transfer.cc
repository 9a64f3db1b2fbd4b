#include "worker/core/attribute_transfer.h"

#include <algorithm>
#include <cmath>

#include "worker/core/kd_tree.h"
#include "worker/core/parallel.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"

namespace lsqsurf::core {
namespace {

constexpr size_t kNeighbours = 4;

const ScalarAttribute* Find(const PointCloud& cloud, std::string_view name) {
  for (const ScalarAttribute& a : cloud.attributes) {
    if (a.name == name && a.values.size() == cloud.size()) return &a;
  }
  return nullptr;
}

}  // namespace

std::vector<std::string> DefaultCarriedAttributes(const PointCloud& cloud) {
  std::vector<std::string> names;
  if (ColourChannels(cloud.attributes, cloud.size())[0] != nullptr)
    names.assign(kColourChannels.begin(), kColourChannels.end());
  if (Find(cloud, "intensity")) names.push_back("intensity");
  return names;
}

absl::Status CarryAttributes(const PointCloud& cloud, const std::vector<std::string>& names, TriangleMesh& mesh,
                             JobContext& ctx) {
  std::vector<const ScalarAttribute*> sources;
  for (const std::string& name : names) {
    const ScalarAttribute* a = Find(cloud, name);
    if (a == nullptr) {
      std::string known;
      for (const ScalarAttribute& b : cloud.attributes) StrAppend(&known, known.empty() ? "" : ", ", b.name);
      return absl::InvalidArgumentError(StrCat("the cloud has no per-point attribute '", name,
                                               "' to carry to the mesh; it has: ", known.empty() ? "none" : known));
    }
    sources.push_back(a);
  }
  if (sources.empty() || cloud.empty()) return absl::OkStatus();
  const KdTree tree(cloud.positions);
  const size_t n = mesh.vertices.size(), k = std::min(kNeighbours, cloud.size());
  std::vector<std::vector<float>> values(sources.size(), std::vector<float>(n));
  LSQSURF_RETURN_IF_ERROR(ParallelFor(
      n, 2048,
      [&](size_t begin, size_t end) {
        std::vector<Neighbor> nn;
        std::vector<double> sum(sources.size());
        for (size_t v = begin; v < end; ++v) {
          tree.Knn(mesh.vertices[v], k, nn);
          // σ = half the k-th distance: the nearest points weigh most, the k-th e^-4 of a coincident one.
          const double sigma2 = std::max<double>(nn.back().distance2, 1e-30) / 4;
          double total = 0;
          std::fill(sum.begin(), sum.end(), 0.0);
          for (const Neighbor& q : nn) {
            const double w = std::exp(-q.distance2 / sigma2);
            total += w;
            for (size_t a = 0; a < sources.size(); ++a) sum[a] += w * sources[a]->values[q.index];
          }
          for (size_t a = 0; a < sources.size(); ++a) values[a][v] = static_cast<float>(sum[a] / total);
        }
      },
      &ctx));
  for (size_t a = 0; a < sources.size(); ++a)
    mesh.vertex_attributes.push_back({sources[a]->name, std::move(values[a])});
  return absl::OkStatus();
}

}  // namespace lsqsurf::core

#include <chrono>
#include <cstdio>

#include "client/cli.h"
#include "worker/core/sampling.h"
#include "worker/core/surface_distance.h"
#include "worker/io/files.h"

namespace lsqsurf::cli {

int PrintMethods(const Globals& g) {
  auto response = Connect(g).ListMethods();
  if (!response.ok()) return FailStatus("methods", response.status());
  for (const auto& m : response->methods()) {
    std::printf("%s: %s\n", m.name().c_str(), m.description().c_str());
    for (const auto& p : m.parameters()) {
      std::string range;
      if (p.type() == v1::Parameter::TYPE_CHOICE) {
        for (const auto& c : p.choices()) range += (range.empty() ? "" : " | ") + c.name();
      } else if (p.type() == v1::Parameter::TYPE_FLAG) {
        range = "true | false";
      } else {
        for (const auto& s : p.special_values()) range += StrCat(s.value(), " (", s.meaning(), "), ");
        if (!range.empty()) range.replace(range.size() - 2, 2, " or ");
        range += StrCat("[", p.min_value(), ", ", p.max_value(), "]", p.unit().empty() ? "" : " ", p.unit());
      }
      const std::string def = p.type() == v1::Parameter::TYPE_CHOICE ? p.default_choice()
                              : p.type() == v1::Parameter::TYPE_FLAG ? (p.default_value() != 0 ? "true" : "false")
                                                                     : StrCat(p.default_value());
      std::printf("  %-18s default %-9s %s  %s\n", p.name().c_str(), def.c_str(), range.c_str(), p.help().c_str());
    }
    std::string attributes;
    for (const auto& a : m.attributes()) attributes += (attributes.empty() ? "" : ", ") + a;
    if (!attributes.empty()) std::printf("  mesh attributes (--color): %s\n", attributes.c_str());
  }
  return 0;
}

CLI::App* HealthCommand::AddTo(CLI::App& app) {
  CLI::App* health = app.add_subcommand("health", "exit 0 when the server answers SERVING to a gRPC health check");
  health->add_option("--service", service, "service to ask about (default: the whole server)");
  health->add_option("--timeout", timeout_seconds, "seconds to wait for an answer")->capture_default_str();
  return health;
}

int HealthCommand::Run(const Globals& g) const {
  const auto timeout = std::chrono::milliseconds(static_cast<int64_t>(timeout_seconds * 1000));
  auto serving = Connect(g).Serving(service, timeout);
  if (!serving.ok()) return FailStatus("health", serving.status());
  std::printf("%s\n", *serving ? "SERVING" : "NOT_SERVING");
  return *serving ? 0 : 1;
}

int PrintServerInfo(const Globals& g) {
  auto info = Connect(g).GetServerInfo();
  if (!info.ok()) return FailStatus("info", info.status());
  std::printf(
      "version          %s\nmax_points       %lld\nmin_points       %lld\nmax_upload_bytes %lld\n"
      "max_queue        %d\nworkers          %d\nmax_renders      %d\ncan_render       %s\n"
      "max_job_memory   %lld\n",
      info->version().c_str(), static_cast<long long>(info->max_points()), static_cast<long long>(info->min_points()),
      static_cast<long long>(info->max_upload_bytes()), info->max_queue(), info->workers(), info->max_renders(),
      info->can_render() ? "yes" : "no", static_cast<long long>(info->max_job_memory_bytes()));
  if (!info->requires_token()) return 0;
  const v1::Account& a = info->account();
  const auto limit = [](int64_t value) { return value > 0 ? std::to_string(value) : std::string("none"); };
  std::printf(
      "account          %s (%s)\njobs             %d of %s\nstored_bytes     %lld of %s\n"
      "max_upload_bytes %s\n",
      a.name().c_str(), a.admin() ? "admin" : "user", a.active_jobs(), limit(a.max_jobs()).c_str(),
      static_cast<long long>(a.stored_bytes()), limit(a.max_stored_bytes()).c_str(),
      limit(a.max_upload_bytes()).c_str());
  return 0;
}

int Compare(const std::string& reference, const std::string& candidate, size_t samples) {
  auto ref = lsqsurf::io::ReadMeshFile(reference);
  if (!ref.ok()) return Fail(std::string(ref.status().message()));
  auto cand = lsqsurf::io::ReadMeshFile(candidate);
  if (!cand.ok()) return Fail(std::string(cand.status().message()));
  lsqsurf::core::LocalJobContext local;
  lsqsurf::core::CompareParams params;
  params.samples = samples;
  auto r = lsqsurf::core::CompareMeshes(*ref, *cand, params, local);
  if (!r.ok()) return Fail(std::string(r.status().message()));
  std::printf(
      "chamfer            %.4e\nhausdorff          %.4e\nhausdorff_corners  %.4e\nnormal_consistency %.5f\n"
      "far_fraction       %.4e\nmean_ref_to_cand   %.4e\nmean_cand_to_ref   %.4e\ndiagonal           %.6g\n",
      r->chamfer, r->hausdorff, r->hausdorff_with_vertices, r->normal_consistency, r->far_fraction, r->mean_ref_to_cand,
      r->mean_cand_to_ref, r->diagonal);
  return 0;
}

CLI::App* SampleCommand::AddTo(CLI::App& app) {
  CLI::App* sample =
      app.add_subcommand("sample", "sample a cloud with normals from a mesh (test input with a known truth)");
  sample->add_option("mesh", mesh_path, "mesh to sample (PLY, OBJ, DRC)")->required();
  sample->add_option("-o,--output", output, "cloud to write (PLY, XYZ, DRC)")->required();
  sample->add_option("--points", points, "number of points")->capture_default_str();
  sample->add_option("--noise", noise, "Gaussian noise along the normal, share of the diagonal")->capture_default_str();
  sample->add_option("--seed", seed, "random seed")->capture_default_str();
  return sample;
}

int SampleCommand::Run() const {
  auto mesh = lsqsurf::io::ReadMeshFile(mesh_path);
  if (!mesh.ok()) return Fail(std::string(mesh.status().message()));
  if (mesh->faces.empty()) return Fail(mesh_path + " has no triangles to sample");
  if (!(noise >= 0 && noise <= 0.1)) return Fail("--noise must be within [0, 0.1] (a share of the diagonal)");
  const double diagonal = lsqsurf::core::Diagonal(lsqsurf::core::BoundingBox(mesh->vertices));
  const lsqsurf::core::PointCloud cloud = lsqsurf::core::SampleCloud(*mesh, points, seed, noise * diagonal);
  if (absl::Status s = lsqsurf::io::WritePointCloudFile(output, cloud); !s.ok()) return Fail(std::string(s.message()));
  return 0;
}

// The commands that take a job id and print little.
int JobCommand(const Globals& g, const std::string& command, const std::string& id) {
  client::Client c = Connect(g);
  if (command == "status") {
    auto job = c.Get(id);
    if (!job.ok()) return FailStatus("status", job.status());
    PrintJob(*job);
    return 0;
  }
  if (command == "cancel") {
    auto job = c.Cancel(id);
    if (!job.ok()) return FailStatus("cancel", job.status());
    std::printf("%s %s\n", job->id().c_str(), client::StateName(job->state()));
    return 0;
  }
  if (command == "delete") {
    if (absl::Status s = c.Delete(id); !s.ok()) return FailStatus("delete", s);
    return 0;
  }
  v1::Job job;
  return Watch(g, id, &job);
}

int List(const Globals& g, int limit) {
  auto response = Connect(g).List(limit);
  if (!response.ok()) return FailStatus("list", response.status());
  for (const auto& job : response->jobs()) {
    std::printf("%s  %-9s  %-7s  %3.0f%%  %s\n", job.id().c_str(), client::StateName(job.state()),
                client::MethodOf(job.spec()).c_str(), job.progress() * 100,
                job.error().empty() ? job.stage().c_str() : job.error().c_str());
  }
  return 0;
}

}  // namespace lsqsurf::cli

// Writes the seed corpus of every fuzz target: small valid inputs of each format, made with the
// project's own writers (tests/fuzz/seeds/TARGET/NAME). Run by scripts/fuzz.sh --seeds; the
// output is committed, so that the replay tests run it in every build.
#include <filesystem>
#include <fstream>
#include <string>

#include "lsqsurf/v1/reconstruction.pb.h"
#include "tests/test_shapes.h"
#include "worker/core/sphere_mesh.h"
#include "worker/io/draco_codec.h"
#include "worker/io/files.h"
#include "worker/io/las.h"
#include "worker/io/obj_xyz.h"
#include "worker/io/pcd.h"
#include "worker/io/ply.h"
#include "worker/io/pts_ptx.h"
#include "worker/io/volume_codec.h"
#include "worker/io/volume_formats.h"
#include "worker/io/vtk_grid.h"
#include "worker/volume/synthetic.h"

namespace {

namespace fs = std::filesystem;
using namespace lsqsurf;

fs::path root;

void Write(const std::string& target, const std::string& name, const std::string& bytes) {
  fs::create_directories(root / target);
  std::ofstream(root / target / name, std::ios::binary) << bytes;
}

// Two uploads as fuzz_uploads splits them: the method byte, the first one's length, both.
std::string TwoUploads(char method, const std::string& first, const std::string& second) {
  std::string out(1, method);
  const auto length = static_cast<uint32_t>(first.size());
  out.append(reinterpret_cast<const char*>(&length), 4);
  return out + first + second;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: make_seeds OUTPUT_DIR\n");
    return 2;
  }
  root = argv[1];
  const core::TriangleMesh mesh = core::SphereMesh(4, 6);
  const core::PointCloud cloud = lsqsurf::testing::SphereCloud(40);
  core::TriangleMesh cloud_mesh;
  cloud_mesh.vertices = cloud.positions;
  cloud_mesh.normals = cloud.normals;
  Write("ply", "mesh_ascii.ply", io::EncodePly(mesh, io::PlyFormat::kAscii));
  Write("ply", "mesh_binary.ply", io::EncodePly(mesh, io::PlyFormat::kBinaryLittleEndian));
  Write("ply", "cloud_ascii.ply", io::EncodePly(cloud_mesh, io::PlyFormat::kAscii));
  core::PointCloud coloured = cloud;
  for (const char* channel : {"red", "green", "blue", "intensity"}) {
    coloured.attributes.push_back({channel, std::vector<float>(cloud.size())});
    for (size_t i = 0; i < cloud.size(); ++i) coloured.attributes.back().values[i] = static_cast<float>((i * 37) % 256);
  }
  Write("pcd", "cloud_ascii.pcd", io::EncodePcd(coloured, io::PcdEncoding::kAscii));
  Write("pcd", "cloud_binary.pcd", io::EncodePcd(coloured, io::PcdEncoding::kBinary));
  Write("pcd", "cloud_compressed.pcd", io::EncodePcd(coloured, io::PcdEncoding::kBinaryCompressed));
  coloured.attributes.push_back({"classification", std::vector<float>(cloud.size(), 2.0f)});
  Write("las", "cloud_1_2_format3.las", io::EncodeLas(coloured, {.version_minor = 2, .point_format = 3}));
  Write("las", "cloud_1_4_format10.las", io::EncodeLas(coloured, {.version_minor = 4, .point_format = 10}));
  core::PointCloud half = coloured;
  half.positions.resize(cloud.size() / 2);
  for (auto& a : half.attributes) a.values.resize(half.positions.size());
  Write("ptx", "two_stations.ptx",
        io::EncodePtx({{core::Vec3d(0, 0, 3), &half, half.size(), 1}, {core::Vec3d(2, 1, 0), &coloured}}));
  Write("ptx", "cloud.pts", "3\n1 2 3 -5 10 20 30\n4 5 6 0 1 2 3\n7 8 9 100 4 5 6\n");
  Write("obj", "mesh.obj", io::EncodeObj(mesh));
  Write("xyz", "cloud.xyzn", io::EncodeXyz(cloud));
  core::PointCloud bare = cloud;
  bare.normals.clear();
  Write("xyz", "cloud.xyz", io::EncodeXyz(bare));

  const std::string draco_cloud = *io::EncodeDracoPointCloud(cloud, {});
  Write("draco", "cloud.drc", draco_cloud);
  Write("draco", "mesh.drc", *io::EncodeDracoMesh(mesh, {}));

  volume::VolumeMesh tets = volume::JitteredTetMesh(core::Box3(core::Vec3d::Zero(), core::Vec3d::Ones()), 3, 0.2, 1);
  volume::SampleField(tets, volume::Franke3d());
  Write("vtk_volume", "tets_ascii.vtk", io::EncodeLegacyVtk(tets, false));
  Write("vtk_volume", "tets_binary.vtk", io::EncodeLegacyVtk(tets, true));
  Write("vtk_volume", "mixed-binary.vtk",
        io::ReadFileBytes(LSQSURF_SOURCE_DIR "/tests/data/volume/mixed-binary.vtk").value_or(""));
  for (const char* vtu : {"mixed-ascii.vtu", "mixed-binary.vtu", "mixed-binary-zlib.vtu", "mixed-appended-base64.vtu",
                          "mixed-appended-zlib.vtu"}) {
    Write("vtu", vtu, io::ReadFileBytes(std::string(LSQSURF_SOURCE_DIR "/tests/data/volume/") + vtu).value_or(""));
  }

  io::VectorGrid grid;
  grid.dims = {3, 3, 2};
  grid.spacing = core::Vec3d(0.5, 0.5, 1.0);
  for (int i = 0; i < 18; ++i) grid.values.emplace_back(i * 0.1, 1.0 - i * 0.05, 0.25);
  const std::string velocity = io::EncodeVtkVectorGrid(grid, false);
  Write("velocity_grid", "grid_ascii.vtk", velocity);
  Write("velocity_grid", "grid_binary.vtk", io::EncodeVtkVectorGrid(grid, true));

  const std::string fields[] = {"franke"};
  Write("uploads", "iamls", std::string(1, '\0') + draco_cloud);
  Write("uploads", "track", TwoUploads(2, draco_cloud, velocity));
  Write("uploads", "volume", TwoUploads(3, *io::EncodeVolumeVertices(tets, fields, {}), io::EncodeCellStream(tets)));

  v1::JobSpec spec;
  spec.mutable_iamls()->set_iterations(2);
  spec.mutable_preview()->mutable_options()->set_width(64);
  Write("job_spec", "iamls", spec.SerializeAsString());
  spec.Clear();
  spec.mutable_pu()->set_max_depth(9);
  Write("job_spec", "pu", spec.SerializeAsString());
  spec.Clear();
  spec.mutable_track()->set_steps(10);
  Write("job_spec", "track", spec.SerializeAsString());
  spec.Clear();
  spec.mutable_volume();
  Write("job_spec", "volume", spec.SerializeAsString());
  v1::RenderOptions view;
  view.set_azimuth_deg(30);
  view.set_width(64);
  Write("job_spec", "view", view.SerializeAsString());
  std::printf("seeds written under %s\n", root.c_str());
  return 0;
}

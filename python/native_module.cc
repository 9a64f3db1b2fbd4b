// python/native_module.cc — lsqsurf._native: the C++ client library (client/client.h) for the
// Python package in python/lsqsurf. It stays thin: messages cross as JSON text (the Python side
// turns them into objects), arrays as NumPy arrays, and every call that waits on the network or
// codes Draco releases the GIL. Parameter values arrive as text and are set by the client
// library's own rules, so the package and the CLI read them alike.
#include <google/protobuf/util/json_util.h>
#include <pybind11/functional.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <array>
#include <cmath>
#include <cstring>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "client/client.h"
#include "worker/core/address.h"
#include "worker/io/draco_codec.h"
#include "worker/io/mesh_part.h"
#include "worker/io/point_stream.h"

namespace lsqsurf::python {
namespace {

namespace py = pybind11;
using Points = py::array_t<double, py::array::c_style | py::array::forcecast>;

// A failed call to the server; becomes lsqsurf.RpcError with the code.
struct RpcFailure : std::runtime_error {
  RpcFailure(const absl::Status& status) : std::runtime_error(std::string(status.message())), code(status.code()) {}
  absl::StatusCode code;
};

void ThrowIfFailed(const absl::Status& status) {
  if (!status.ok()) throw RpcFailure(status);
}
template <class T>
T ValueOrThrow(absl::StatusOr<T> value) {
  ThrowIfFailed(value.status());
  return *std::move(value);
}
// A local check that failed (a parameter's text, an array's shape): the caller's mistake.
void ThrowIfInvalid(const absl::Status& status) {
  if (!status.ok()) throw py::value_error(std::string(status.message()));
}

std::string ToJson(const google::protobuf::Message& message) {
  google::protobuf::util::JsonPrintOptions options;
  options.preserve_proto_field_names = true;
  options.always_print_primitive_fields = true;
  std::string json;
  if (!google::protobuf::util::MessageToJsonString(message, &json, options).ok()) {
    throw std::runtime_error("a message of the server could not be shown as JSON");
  }
  return json;
}

// N×3 float positions from a NumPy array, refused when not N×3 or not finite.
std::vector<core::Vec3f> ToVectors(const Points& array, const char* what) {
  if (array.ndim() != 2 || array.shape(1) != 3) {
    throw py::value_error(std::string(what) + " must be an N×3 array");
  }
  std::vector<core::Vec3f> out(static_cast<size_t>(array.shape(0)));
  const double* data = array.data();
  for (size_t i = 0; i < out.size(); ++i) {
    for (int k = 0; k < 3; ++k) {
      const double v = data[3 * i + static_cast<size_t>(k)];
      if (!std::isfinite(v)) {
        throw py::value_error(std::string(what) + " row " + std::to_string(i) + " is not finite");
      }
      out[i][k] = static_cast<float>(v);
    }
  }
  return out;
}

core::PointCloud ToCloud(const Points& points, const std::optional<Points>& normals,
                         const py::dict& attributes = py::dict()) {
  core::PointCloud cloud;
  cloud.positions = ToVectors(points, "points");
  if (normals) {
    cloud.normals = ToVectors(*normals, "normals");
    if (cloud.normals.size() != cloud.positions.size()) throw py::value_error("normals must have one row per point");
    for (size_t i = 0; i < cloud.normals.size(); ++i) {
      const float length = cloud.normals[i].norm();
      if (!(length > 0)) throw py::value_error("normals row " + std::to_string(i) + " is zero");
      cloud.normals[i] /= length;  // The server takes unit normals.
    }
  }
  for (const auto& [name, values] : attributes) {
    const auto array = py::array_t<float, py::array::c_style | py::array::forcecast>::ensure(values);
    const std::string key = py::str(name);
    if (!array || array.ndim() != 1 || static_cast<size_t>(array.shape(0)) != cloud.size()) {
      throw py::value_error("attribute " + key + " must have one value per point");
    }
    cloud.attributes.push_back({key, std::vector<float>(array.data(), array.data() + array.shape(0))});
  }
  return cloud;
}

py::array_t<float> VectorArray(const std::vector<core::Vec3f>& vectors) {
  py::array_t<float> out({static_cast<py::ssize_t>(vectors.size()), py::ssize_t{3}});
  float* data = out.mutable_data();
  for (size_t i = 0; i < vectors.size(); ++i) std::memcpy(data + 3 * i, vectors[i].data(), 3 * sizeof(float));
  return out;
}

py::dict AttributeArrays(const std::vector<core::ScalarAttribute>& attributes) {
  py::dict out;
  for (const auto& a : attributes)
    out[py::str(a.name)] = py::array_t<float>(py::ssize_t(a.values.size()), a.values.data());
  return out;
}

// A Draco result mesh as NumPy arrays.
py::dict DecodeMesh(const py::bytes& bytes) {
  const std::string_view view(bytes);
  absl::StatusOr<core::TriangleMesh> mesh;
  {
    py::gil_scoped_release unlocked;
    mesh = io::DecodeDracoMesh(view);
  }
  ThrowIfInvalid(mesh.status());
  py::array_t<int64_t> faces({static_cast<py::ssize_t>(mesh->faces.size()), py::ssize_t{3}});
  int64_t* f = faces.mutable_data();
  for (size_t i = 0; i < mesh->faces.size(); ++i) {
    for (size_t k = 0; k < 3; ++k) f[3 * i + k] = mesh->faces[i][k];
  }
  py::dict out;
  out["vertices"] = VectorArray(mesh->vertices);
  out["faces"] = faces;
  out["normals"] = VectorArray(mesh->normals);
  out["attributes"] = AttributeArrays(mesh->vertex_attributes);
  return out;
}

// One part of a mesh delivered in parts (LQM1); its faces use the whole mesh's vertex numbers.
py::dict DecodeMeshPart(const py::bytes& bytes) {
  auto part = io::DecodeMeshPart(std::string_view(bytes));
  ThrowIfInvalid(part.status());
  py::array_t<int64_t> faces({static_cast<py::ssize_t>(part->faces.size()), py::ssize_t{3}});
  if (!part->faces.empty())
    std::memcpy(faces.mutable_data(), part->faces.data(), part->faces.size() * 3 * sizeof(int64_t));
  py::dict out;
  out["first_vertex"] = part->first_vertex;
  out["vertices"] = VectorArray(part->vertices);
  out["faces"] = faces;
  out["normals"] = VectorArray(part->normals);
  out["attributes"] = AttributeArrays(part->attributes);
  return out;
}

// A point cloud file (any format the CLI reads) as NumPy arrays, with what the file says of its
// sensors and of a shift of its coordinates.
py::dict ReadCloud(const std::string& path) {
  core::PointCloud cloud;
  std::vector<core::Vec3d> sensors;
  std::array<double, 3> shift{};
  absl::Status read = [&]() -> absl::Status {
    py::gil_scoped_release unlocked;
    auto stream = io::OpenPointStream(path);
    if (!stream.ok()) return stream.status();
    sensors = (*stream)->sensor_positions();
    shift = (*stream)->coordinate_shift();
    for (;;) {
      auto chunk = (*stream)->Next(size_t{1} << 20);
      if (!chunk.ok()) return chunk.status();
      if (chunk->size() == 0) return absl::OkStatus();
      if (cloud.size() == 0) {
        cloud = *std::move(chunk);
      } else {
        core::AppendCloud(cloud, *chunk);
      }
    }
  }();
  ThrowIfInvalid(read);
  py::array_t<double> stations({static_cast<py::ssize_t>(sensors.size()), py::ssize_t{3}});
  for (size_t i = 0; i < sensors.size(); ++i) std::memcpy(stations.mutable_data() + 3 * i, sensors[i].data(), 24);
  py::dict out;
  out["points"] = VectorArray(cloud.positions);
  out["normals"] = VectorArray(cloud.normals);
  out["attributes"] = AttributeArrays(cloud.attributes);
  out["sensors"] = stations;
  out["shift"] = py::make_tuple(shift[0], shift[1], shift[2]);
  return out;
}

// A cloud as one Draco upload. `exact`: unquantized and in order (probe points, whose answer's
// rows follow them); otherwise the client library's default coding.
py::bytes EncodeCloud(const Points& points, const std::optional<Points>& normals, bool exact) {
  const core::PointCloud cloud = ToCloud(points, normals);
  io::DracoOptions options;
  if (exact) {
    options.position_bits = 0;
    options.speed = 10;
  }
  absl::StatusOr<std::string> bytes;
  {
    py::gil_scoped_release unlocked;
    bytes = io::EncodeDracoPointCloud(cloud, options);
  }
  ThrowIfInvalid(bytes.status());
  return py::bytes(*bytes);
}

// A volume's two uploads from its arrays: cells as flat corner indices with offsets (cells + 1
// entries) and one VTK type per cell; fields one value per vertex (NaN = missing).
py::tuple EncodeVolume(const Points& points, py::array_t<int64_t, py::array::c_style | py::array::forcecast> corners,
                       py::array_t<int64_t, py::array::c_style | py::array::forcecast> offsets,
                       py::array_t<int64_t, py::array::c_style | py::array::forcecast> types, const py::dict& fields) {
  core::VolumeMesh mesh;
  mesh.positions = ToVectors(points, "points");
  const int64_t cells = types.size();
  if (offsets.size() != (cells ? cells + 1 : 0))
    throw py::value_error("offsets must have one entry per cell and one more");
  for (int64_t c = 0; c < cells; ++c) {
    const int64_t type = types.data()[c];
    const int64_t begin = offsets.data()[c], end = offsets.data()[c + 1];
    if (type < 0 || type > 255 || begin < 0 || end < begin || end > corners.size()) {
      throw py::value_error("cell " + std::to_string(c) + ": its type or offsets are out of range");
    }
    mesh.cell_types.push_back(static_cast<uint8_t>(type));
    mesh.cell_offsets.push_back(static_cast<uint32_t>(begin));
  }
  if (cells) mesh.cell_offsets.push_back(static_cast<uint32_t>(offsets.data()[cells]));
  for (int64_t i = 0; i < corners.size(); ++i) {
    const int64_t v = corners.data()[i];
    if (v < 0 || v >= static_cast<int64_t>(mesh.positions.size())) {
      throw py::value_error("cell corner " + std::to_string(i) + " names vertex " + std::to_string(v) +
                            ", not one of the " + std::to_string(mesh.positions.size()) + " points");
    }
    mesh.cell_vertices.push_back(static_cast<uint32_t>(v));
  }
  std::vector<std::string> names;
  for (const auto& [key, value] : fields) {
    auto values = py::array_t<float, py::array::c_style | py::array::forcecast>::ensure(value);
    if (!values || values.ndim() != 1 || values.size() != static_cast<py::ssize_t>(mesh.positions.size())) {
      throw py::value_error("field '" + py::str(key).cast<std::string>() + "' must hold one number per point");
    }
    names.push_back(py::str(key));
    mesh.fields.push_back({names.back(), 1, std::vector<float>(values.data(), values.data() + values.size())});
  }
  absl::StatusOr<client::VolumeUpload> upload;
  {
    py::gil_scoped_release unlocked;
    upload = client::EncodeVolume(std::move(mesh), names, "the volume");
  }
  ThrowIfInvalid(upload.status());
  return py::make_tuple(py::bytes(upload->vertices), py::bytes(upload->cells), upload->missing_vertices);
}

// A job's spec under construction: the method and its parameters set from text.
class Spec {
 public:
  explicit Spec(const std::string& method) { ThrowIfInvalid(client::SetMethod(&spec_, method)); }
  void Set(const std::string& name, const std::string& value) { ThrowIfInvalid(client::SetParam(&spec_, name, value)); }
  void SetPreview(const std::string& name, const std::string& value) {
    ThrowIfInvalid(client::SetMessageField(spec_.mutable_preview()->mutable_options(), name, value));
  }
  void SetMeshBits(int bits) { spec_.set_mesh_position_bits(bits); }
  std::string Json() const { return ToJson(spec_); }
  const v1::JobSpec& spec() const { return spec_; }

 private:
  v1::JobSpec spec_;
};

class Connection {
 public:
  Connection(const std::string& address, const client::ConnectOptions& options) : client_(address, options) {}

  std::string ListMethods() {
    return Unary([&] { return client_.ListMethods(); });
  }
  std::string ServerInfo() {
    return Unary([&] { return client_.GetServerInfo(); });
  }
  std::string Get(const std::string& id) {
    return Unary([&] { return client_.Get(id); });
  }
  std::string List(int limit) {
    return Unary([&] { return client_.List(limit); });
  }
  std::string Cancel(const std::string& id) {
    return Unary([&] { return client_.Cancel(id); });
  }
  void Delete(const std::string& id) {
    absl::Status status;
    {
      py::gil_scoped_release unlocked;
      status = client_.Delete(id);
    }
    ThrowIfFailed(status);
  }

  // A cloud in parts of `part_points` points, each coded as it is sent.
  std::string SubmitCloud(const Spec& spec, const Points& points, const std::optional<Points>& normals,
                          const py::dict& attributes, int64_t part_points) {
    auto cloud = std::make_shared<const core::PointCloud>(ToCloud(points, normals, attributes));
    return Unary([&] { return client_.SubmitParts(spec.spec(), client::CloudParts(cloud, {}, part_points)); });
  }
  std::string Submit(const Spec& spec, const py::bytes& input, const py::bytes& velocity, const py::bytes& cells) {
    const std::string_view in(input), vel(velocity), cel(cells);
    return Unary([&] { return client_.Submit(spec.spec(), in, vel, cel); });
  }

  // Follows the job until it ends; `on_event` (may be None) gets each state as JSON, with the GIL.
  std::string Watch(const std::string& id, const std::function<void(const std::string&)>& on_event) {
    std::exception_ptr raised;  // An exception of the callback, raised again once the watch is over.
    auto forward = [&](const v1::Job& job) {
      if (!on_event || raised) return;
      py::gil_scoped_acquire locked;
      try {
        on_event(ToJson(job));
      } catch (...) {
        raised = std::current_exception();
      }
    };
    absl::StatusOr<v1::Job> done;
    {
      py::gil_scoped_release unlocked;
      done = client_.Watch(id, forward);
    }
    if (raised) std::rethrow_exception(raised);
    return ToJson(ValueOrThrow(std::move(done)));
  }

  py::bytes Fetch(const std::string& id, const std::string& name) {
    absl::StatusOr<std::string> bytes;
    {
      py::gil_scoped_release unlocked;
      bytes = client_.Fetch(id, name);
    }
    return py::bytes(ValueOrThrow(std::move(bytes)));
  }

  // The picture and the response's other fields (JSON); `options` as (name, text) pairs.
  py::tuple Render(const std::string& id, const std::string& name,
                   const std::vector<std::pair<std::string, std::string>>& options) {
    v1::RenderOptions parsed;
    for (const auto& [field, value] : options) ThrowIfInvalid(client::SetMessageField(&parsed, field, value));
    absl::StatusOr<v1::RenderResponse> response;
    {
      py::gil_scoped_release unlocked;
      response = client_.Render(id, name, parsed);
    }
    v1::RenderResponse r = ValueOrThrow(std::move(response));
    py::bytes png(r.png());
    r.clear_png();
    return py::make_tuple(png, ToJson(r));
  }

 private:
  template <class Call>
  std::string Unary(const Call& call) {
    decltype(call()) response = absl::UnknownError("");
    {
      py::gil_scoped_release unlocked;
      response = call();
    }
    return ToJson(ValueOrThrow(std::move(response)));
  }

  client::Client client_;
};

Connection Connect(const std::string& address, const std::string& token, bool tls, const std::string& ca_pem,
                   const std::string& cert_pem, const std::string& key_pem, const std::string& server_name) {
  client::ConnectOptions options;
  options.tls = tls;
  options.ca_pem = ca_pem;
  options.cert_pem = cert_pem;
  options.key_pem = key_pem;
  options.server_name = server_name;
  if (!token.empty()) {
    ThrowIfInvalid(client::CheckToken(token));
    options.token = token;
  }
  return Connection(address, options);
}

}  // namespace
}  // namespace lsqsurf::python

PYBIND11_MODULE(_native, m) {
  using namespace lsqsurf::python;  // NOLINT: the module's definitions read shorter.
  m.doc() = "lsqsurf's C++ client library; use the lsqsurf package, not this module.";
  py::register_exception_translator([](std::exception_ptr raised) {
    try {
      if (raised) std::rethrow_exception(raised);
    } catch (const RpcFailure& e) {
      const py::object error = py::module_::import("lsqsurf._errors").attr("RpcError");
      const py::object instance =
          error(static_cast<int>(e.code), absl::StatusCodeToString(e.code), std::string(e.what()));
      PyErr_SetObject(error.ptr(), instance.ptr());
    }
  });
  py::class_<Spec>(m, "Spec")
      .def(py::init<const std::string&>(), py::arg("method"))
      .def("set", &Spec::Set, py::arg("name"), py::arg("value"))
      .def("set_preview", &Spec::SetPreview, py::arg("name"), py::arg("value"))
      .def("set_mesh_bits", &Spec::SetMeshBits, py::arg("bits"))
      .def("json", &Spec::Json);
  py::class_<Connection>(m, "Connection")
      .def(py::init(&Connect), py::arg("address"), py::arg("token"), py::arg("tls"), py::arg("ca_pem"),
           py::arg("cert_pem"), py::arg("key_pem"), py::arg("server_name"))
      .def("list_methods", &Connection::ListMethods)
      .def("server_info", &Connection::ServerInfo)
      .def("get", &Connection::Get, py::arg("id"))
      .def("list", &Connection::List, py::arg("limit"))
      .def("cancel", &Connection::Cancel, py::arg("id"))
      .def("delete", &Connection::Delete, py::arg("id"))
      .def("submit_cloud", &Connection::SubmitCloud, py::arg("spec"), py::arg("points"), py::arg("normals"),
           py::arg("attributes"), py::arg("part_points"))
      .def("submit", &Connection::Submit, py::arg("spec"), py::arg("input"), py::arg("velocity"), py::arg("cells"))
      .def("watch", &Connection::Watch, py::arg("id"), py::arg("on_event"))
      .def("fetch", &Connection::Fetch, py::arg("id"), py::arg("name"))
      .def("render", &Connection::Render, py::arg("id"), py::arg("name"), py::arg("options"));
  m.def("decode_mesh", &DecodeMesh, py::arg("data"));
  m.def("read_cloud", &ReadCloud, py::arg("path"));
  m.def("decode_mesh_part", &DecodeMeshPart, py::arg("data"));
  m.def("encode_cloud", &EncodeCloud, py::arg("points"), py::arg("normals"), py::arg("exact"));
  m.def("encode_volume", &EncodeVolume, py::arg("points"), py::arg("corners"), py::arg("offsets"), py::arg("types"),
        py::arg("fields"));
  m.def(
      "is_loopback", [](const std::string& address) { return lsqsurf::core::IsLoopback(address); }, py::arg("address"));
  m.attr("points_per_part") = lsqsurf::client::kPointsPerPart;
}

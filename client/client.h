// client/client.h — a small library over the lsqsurf.v1 API: each call returns a StatusOr, so
// the CLI (and other programs) need not handle gRPC streams themselves.
//
// Thread safety: a Client may be used from one thread at a time per call; calls open their
// own contexts on a shared channel.
#pragma once

#include <chrono>
#include <functional>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "lsqsurf/v1/reconstruction.grpc.pb.h"
#include "worker/core/geometry.h"
#include "worker/core/volume_mesh.h"
#include "worker/io/draco_codec.h"
#include "worker/io/point_stream.h"

namespace lsqsurf::client {

// The gRPC status as an absl::Status (the codes are the same numbers).
absl::Status FromGrpc(const grpc::Status& status);

// The method a spec names ("" when none), and setting one (an empty parameter message).
// Errors: kInvalidArgument for an unknown method, listing the known ones.
std::string MethodOf(const v1::JobSpec& spec);
absl::Status SetMethod(v1::JobSpec* spec, const std::string& method);
// Sets the parameter `name` of the spec's method from its text form: a number, true/false/1/0
// for flags, a choice's name (e.g. "gridlines") for enums. Ranges are the server's to check.
// Errors: kInvalidArgument naming the field (unknown, or a value of the wrong type).
absl::Status SetParam(v1::JobSpec* spec, std::string_view name, std::string_view value);
// Sets the field `name` of any parameter message (a method's, or RenderOptions) the same way.
absl::Status SetMessageField(google::protobuf::Message* message, std::string_view name, std::string_view value);
// "name=value" as given to --param.
absl::Status SetParamAssignment(v1::JobSpec* spec, std::string_view assignment);

// A volume file as the two uploads of a volume job (VolumeParams): the vertices with the named
// fields as Draco, the cells as a stream. `raw_layout` non-empty reads `path` as a raw volume
// ("NXxNYxNZ:TYPE[:SPACING]", its field named `fields[0]`). Errors: kInvalidArgument naming the
// file and the problem (a missing field lists those present). Values that are NaN or infinite
// cannot travel in Draco's quantized attributes: they are filled in from the neighbouring
// vertices first (core::FillMissingValues), or the file is refused when too many are missing.
struct VolumeUpload {
  std::string vertices;
  std::string cells;
  int64_t missing_vertices = 0;  // Vertices whose values were filled in.
};
absl::StatusOr<VolumeUpload> EncodeVolumeFile(const std::string& path, const std::string& raw_layout,
                                              const std::vector<std::string>& fields);
// The same for a volume held in memory; `name` (a file's path, or what the volume is) begins each
// error's message.
absl::StatusOr<VolumeUpload> EncodeVolume(core::VolumeMesh mesh, const std::vector<std::string>& fields,
                                          std::string_view name);

// A cloud's upload one Draco part at a time (SubmitJobRequest.input_part_end): each call returns
// the next part's bytes, and an empty string after the last. An error ends the upload.
using PartSource = std::function<absl::StatusOr<std::string>()>;
// Points per part that CloudParts uses: small enough that neither side holds much at once, large
// enough that the parts cost nothing next to the points.
inline constexpr int64_t kPointsPerPart = int64_t{1} << 20;
// The parts of `cloud`, at most `points_per_part` points each, encoded (with `options`) only when
// asked for, so that one part's Draco bytes are held at a time. A cloud within one part gives
// one part: what any server accepts.
PartSource CloudParts(std::shared_ptr<const core::PointCloud> cloud, const io::DracoOptions& options = {},
                      int64_t points_per_part = kPointsPerPart);
// The parts of a cloud read from `points` as they are asked for (a file streamed holds one part
// at a time). Normals are scaled to unit length, as the server takes them.
PartSource StreamParts(std::shared_ptr<io::PointStream> points, const io::DracoOptions& options = {},
                       int64_t points_per_part = kPointsPerPart);

// A result mesh delivered in parts (a PU job streamed from an input in parts; see
// FetchResultRequest): the names of its parts, in order; empty for any other job.
std::vector<std::string> MeshParts(const v1::Job& job);
// Writes a mesh from its `parts` parts, `fetch` giving part i's bytes: .ply (binary) and .obj are
// written as the parts come (the vertices and faces go to files beside `path` until the counts
// are known), so that the mesh is never whole in memory; .drc and other formats take it whole.
// Errors: those of `fetch`, kInvalidArgument (an unknown extension, a corrupt part), kDataLoss
// (parts that do not follow on), kResourceExhausted (a full disk).
absl::Status WriteMeshParts(size_t parts, const std::function<absl::StatusOr<std::string>(size_t part)>& fetch,
                            const std::string& path);

// Writes each of the `parts` parts of a mesh delivered in parts as a Draco mesh of its own, with
// the vertices of earlier parts its faces name (io::SelfContainedParts), to
// `directory`/mesh-part-NNNNN.drc (made if missing): the tiles, which share the vertices on their
// seams (positions are stored exactly, so they weld by position). Returns the paths written. Errors: those of `fetch`,
// kInvalidArgument (a corrupt part or one that does not follow on), kPermissionDenied / kResourceExhausted (cannot
// write).
absl::StatusOr<std::vector<std::string>> WriteMeshPartFiles(
    size_t parts, const std::function<absl::StatusOr<std::string>(size_t part)>& fetch, const std::string& directory);

// Display names: "queued", "running", ...
const char* StateName(v1::JobState state);
bool IsTerminal(v1::JobState state);

// How a Client reaches the server.
struct ConnectOptions {
  // TLS is used when `tls` is set or any PEM below is given; plaintext otherwise.
  bool tls = false;
  std::string ca_pem;       // Certificates to trust; empty: the system's roots.
  std::string cert_pem;     // The client's certificate chain (mutual TLS), with...
  std::string key_pem;      // ...its private key.
  std::string server_name;  // The name the server's certificate must carry; empty: the address's host.
  std::string token;        // Sent as "authorization: Bearer TOKEN" on every call; empty: none.
  // Deadline of each unary call (Get, List, Cancel, Delete, ListMethods, GetServerInfo); 0: none.
  // A call past it fails with kDeadlineExceeded.
  std::chrono::milliseconds unary_deadline{0};
  bool uses_tls() const { return tls || !ca_pem.empty() || !cert_pem.empty() || !key_pem.empty(); }
};

// A token can be sent: printable ASCII without spaces. Errors: kInvalidArgument saying what is
// wrong with it (never repeating it). A Client sends no invalid token.
absl::Status CheckToken(std::string_view token);

class Client {
 public:
  explicit Client(const std::string& address, const ConnectOptions& options = {});

  // Uploads `input` (Draco bytes; may be empty for jobs that need none) and `velocity` (legacy
  // VTK; empty when not used) in 1 MiB chunks. Returns the accepted job.
  // `cells`: a volume's cell stream (VolumeParams).
  absl::StatusOr<v1::Job> Submit(const v1::JobSpec& spec, std::string_view input, std::string_view velocity = {},
                                 std::string_view cells = {});
  // The same with the input in parts, each asked for when the previous one is sent.
  absl::StatusOr<v1::Job> SubmitParts(const v1::JobSpec& spec, const PartSource& input, std::string_view velocity = {},
                                      std::string_view cells = {});
  // Follows the job until it ends, calling `on_event` with every state; returns the final job.
  // Errors: the RPC's, or kAborted when the stream ended before the job did.
  absl::StatusOr<v1::Job> Watch(const std::string& id, const std::function<void(const v1::Job&)>& on_event = {});
  absl::StatusOr<std::string> Fetch(const std::string& id, const std::string& name);
  absl::StatusOr<v1::RenderResponse> Render(const std::string& id, const std::string& name,
                                            const v1::RenderOptions& options);
  absl::StatusOr<v1::Job> Get(const std::string& id);
  // Newest first: up to `limit` jobs (0: all), following the server's pages.
  absl::StatusOr<v1::ListJobsResponse> List(int limit);
  // One page: at most `limit` jobs (0: the server's default) after `page_token` (empty: the newest).
  absl::StatusOr<v1::ListJobsResponse> ListPage(int limit, const std::string& page_token);
  absl::StatusOr<v1::Job> Cancel(const std::string& id);
  absl::Status Delete(const std::string& id);
  absl::StatusOr<v1::ListMethodsResponse> ListMethods();
  absl::StatusOr<v1::ServerInfo> GetServerInfo();
  // The standard gRPC health check (grpc.health.v1) of `service` ("" = the server as a whole):
  // true when SERVING, false when NOT_SERVING (a server that is stopping). Errors: the RPC's,
  // kUnavailable or kDeadlineExceeded when nothing answers within `timeout`.
  absl::StatusOr<bool> Serving(const std::string& service, std::chrono::milliseconds timeout);

 private:
  // A context for one call, carrying the token.
  std::unique_ptr<grpc::ClientContext> NewContext() const;
  template <class Request, class Response>
  absl::StatusOr<Response> Unary(grpc::Status (v1::Reconstruction::Stub::*call)(grpc::ClientContext*, const Request&,
                                                                                Response*),
                                 const Request& request);

  std::string token_;
  std::chrono::milliseconds unary_deadline_{0};
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::Reconstruction::Stub> stub_;
};

}  // namespace lsqsurf::client

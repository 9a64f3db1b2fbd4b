// worker/jobs/job_kind.h — the interface every kind of work implements (a surface, a moving
// front, next a volume).
//
// A kind names its methods and their parameter tables, checks a spec's uploads before the job
// is accepted, and runs the job with a cancel/progress context, writing its artifacts through a
// sink. The job service knows queues, states and recovery, never a kind's details.
#pragma once

#include <algorithm>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <string>
#include <string_view>
#include <type_traits>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/job_context.h"
#include "worker/core/params.h"
#include "worker/io/draco_codec.h"
#include "worker/jobs/job.h"

namespace lsqsurf::render {
class SharedRenderer;
}

namespace lsqsurf::jobs {

// One method a kind offers: what ListMethods shows and what a spec's parameters start from.
struct MethodInfo {
  std::string name;
  std::string description;
  core::ParamSet defaults;              // The method's parameter struct with its defaults.
  std::vector<std::string> attributes;  // Per-vertex scalars on its result meshes (to colour by).
  std::vector<std::string> uploads;     // Upload slots it accepts (kInputUpload, kVelocityUpload).
  bool input_in_parts = false;          // Takes the input in parts (InputPartSlot).
};

// Server limits a kind checks uploads against.
struct InputLimits {
  int64_t max_points = 20'000'000;
  int64_t min_points = 16;
  int64_t max_cells = 100'000'000;  // Volume meshes.
  int64_t max_job_memory = 0;       // Bytes one job may take (0: no limit); see LeavesWithin.
  // Bytes a compressed stream (a volume's cells) may inflate to: the most its submitter may
  // upload, so that compression buys no more than an upload could hold (0: no limit).
  int64_t max_inflated_bytes = 0;
};

// Memory of the extraction per visited J1a leaf, the tree, the corner values, the tetrahedra
// and the output vertices together (measured on iaMLS and PU runs: 1.6 to 2 KiB), by which a
// run's memory limit becomes the leaves its extraction may visit.
inline constexpr int64_t kBytesPerExtractionLeaf = 2048;

// The leaves an extraction may visit: the engine's own bound, lowered to what `memory_bytes`
// holds (0: no memory limit).
inline int64_t LeavesWithin(int64_t memory_bytes, int64_t engine_bound) {
  if (memory_bytes <= 0) return engine_bound;
  return std::max<int64_t>(1, std::min(engine_bound, memory_bytes / kBytesPerExtractionLeaf));
}

// Stores a job's artifacts; each write is atomic and the name is recorded in order.
class ArtifactSink {
 public:
  virtual ~ArtifactSink() = default;
  // Errors: kUnavailable (storage failed).
  virtual absl::Status Write(std::string_view name, std::string_view bytes) = 0;
  // An artifact this run wrote (a picture of a mesh delivered in parts reads them back).
  // Errors: kNotFound (not written), kUnavailable.
  virtual absl::StatusOr<std::string> Read(std::string_view name) const = 0;
};

// The memory a run is expected to take at its peak (0: not estimated), and what to change when
// that is more than a job may take.
struct MemoryEstimate {
  int64_t bytes = 0;
  std::string hint;
};

// A job's decoded uploads, of its kind's own type (see TypedJobKind): the job service holds them
// from submission to the run while memory allows, so that an upload is decoded once.
class DecodedInput {
 public:
  virtual ~DecodedInput() = default;
};

// What checking a job's uploads found: the input's size and, where the kind keeps it, the decoded
// uploads standing in for all of them.
struct CheckedInput {
  int64_t points = 0;
  std::shared_ptr<DecodedInput> decoded;  // Null when nothing is kept.
  MemoryEstimate memory;                  // The job service refuses a job estimated past its memory limit.
};

class TileExchange;  // tile_exchange.h

struct RunEnvironment {
  ArtifactSink& sink;
  core::JobContext& context;
  render::SharedRenderer* renderer = nullptr;  // For previews; nullptr: none can be drawn.
  // CheckUploads' `decoded` of this job when the service still holds it (not after a restart);
  // the kind may move from it.
  std::shared_ptr<DecodedInput> decoded;
  // A result of another, succeeded job (a kept precomputation). Errors: kNotFound (no such job
  // or result), kFailedPrecondition (the job has not succeeded), kUnavailable.
  std::function<absl::StatusOr<std::string>(const std::string& job_id, const std::string& name)> read_result;
  // The memory a job may take (0: no limit); extractions visit at most LeavesWithin(it) leaves.
  int64_t memory_bytes = 0;
  // Where a run keeps large temporary files (a tiled build's points): the server's own scratch
  // directory, emptied of what crashed runs left when it starts; "": the system's temporary one.
  std::string scratch_dir;
  // Where a tiled build may spread its tiles over the servers sharing the store; nullptr: this
  // run makes every tile itself.
  TileExchange* tiles = nullptr;
};

class JobKind {
 public:
  virtual ~JobKind() = default;
  virtual std::string_view name() const = 0;  // "surface", "track".
  virtual std::vector<MethodInfo> Methods() const = 0;
  // Checks a validated spec's uploads (decoding them). Errors: kInvalidArgument (a missing,
  // undecodable or unsuitable upload, with what to fix), kResourceExhausted (over the limits).
  virtual absl::StatusOr<CheckedInput> CheckUploads(const JobSpec& spec, const Uploads& uploads,
                                                    const InputLimits& limits) const = 0;
  // The other jobs a validated spec reads results of (RunEnvironment::read_result reads no
  // others): the job service lets a submitter name only jobs it may see.
  virtual std::vector<std::string> ReferencedJobs(const JobSpec&) const { return {}; }
  // Runs an accepted job; the artifacts go through `env.sink`. Returns the final statistics.
  // Errors: kCancelled, or the engine's own (kInvalidArgument, kResourceExhausted, ...).
  virtual absl::StatusOr<Statistics> Run(const JobSpec& spec, const Uploads& uploads, RunEnvironment& env) const = 0;
};

// The limits a job accepted before a restart is decoded under again: it met the server's at
// submission, and a server restarted with lower ones still runs what it accepted.
inline constexpr InputLimits kAcceptedInputLimits{.max_points = io::DracoDecodeLimits{}.max_points,
                                                  .min_points = 0,
                                                  .max_cells = std::numeric_limits<int64_t>::max(),
                                                  .max_job_memory = 0,
                                                  .max_inflated_bytes = 0};

// A kind with nothing to decode from uploads.
struct NoInput {};

// A kind whose parameters are one struct (`Params`; core::ParamSet for a kind whose methods have
// different ones) and whose uploads decode into `Input`, once: at submission, kept by the job
// service, or at run time for a job accepted before a restart. Run never sees raw uploads.
template <typename Params, typename Input>
class TypedJobKind : public JobKind {
 public:
  struct Checked {
    int64_t points = 0;
    Input input;
    MemoryEstimate memory;
  };

  absl::StatusOr<CheckedInput> CheckUploads(const JobSpec& spec, const Uploads& uploads,
                                            const InputLimits& limits) const final {
    const Params* params = ParamsOf(spec);
    if (params == nullptr) return MissingParams();
    absl::StatusOr<Checked> checked = Decode(spec, *params, uploads, limits);
    if (!checked.ok()) return checked.status();
    CheckedInput out{checked->points, nullptr, std::move(checked->memory)};
    if constexpr (!std::is_same_v<Input, NoInput>) out.decoded = std::make_shared<Held>(std::move(checked->input));
    return out;
  }

  std::vector<std::string> ReferencedJobs(const JobSpec& spec) const final {
    const Params* params = ParamsOf(spec);
    return params == nullptr ? std::vector<std::string>{} : Referenced(*params);
  }

  absl::StatusOr<Statistics> Run(const JobSpec& spec, const Uploads& uploads, RunEnvironment& env) const final {
    const Params* params = ParamsOf(spec);
    if (params == nullptr) return MissingParams();
    Input input{};
    if constexpr (!std::is_same_v<Input, NoInput>) {
      if (auto* held = dynamic_cast<Held*>(env.decoded.get()); held != nullptr) {
        input = std::move(held->input);
      } else {
        absl::StatusOr<Checked> checked = Decode(spec, *params, uploads, kAcceptedInputLimits);
        if (!checked.ok()) return checked.status();
        input = std::move(checked->input);
      }
    }
    return RunDecoded(spec, *params, std::move(input), env);
  }

 protected:
  // Decodes and checks the uploads against `limits`. Errors: as CheckUploads.
  virtual absl::StatusOr<Checked> Decode(const JobSpec& spec, const Params& params, const Uploads& uploads,
                                         const InputLimits& limits) const = 0;
  virtual std::vector<std::string> Referenced(const Params&) const { return {}; }
  virtual absl::StatusOr<Statistics> RunDecoded(const JobSpec& spec, const Params& params, Input input,
                                                RunEnvironment& env) const = 0;

 private:
  struct Held final : DecodedInput {
    explicit Held(Input decoded) : input(std::move(decoded)) {}
    Input input;
  };
  static const Params* ParamsOf(const JobSpec& spec) {
    if constexpr (std::is_same_v<Params, core::ParamSet>) {
      return &spec.params;
    } else {
      return spec.params.template As<Params>();
    }
  }
  absl::Status MissingParams() const {
    return absl::InternalError(std::string("a ") + std::string(name()) + " job without its parameters");
  }
};

}  // namespace lsqsurf::jobs

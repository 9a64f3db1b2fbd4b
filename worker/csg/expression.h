// worker/csg/expression.h — the text form of a CSG solid: operations, analytic primitives,
// transforms and references to kept results of other jobs.
//
//   difference(job:7f3a, sphere(c=0.1,0.2,0.3 r=0.05))
//   union(box(min=-1,-1,-1 max=1,1,1), rotate(axis=1,0,0 deg=90 cylinder(a=0,0,-2 b=0,0,2 r=0.5)))
//
// A call is NAME(ARGS). ARGS are operands (calls or `job:ID`) and named numbers `key=v` or
// `key=x,y,z`, separated by commas or blanks. Operations take two or more operands: union,
// intersection, difference (the first minus all the others). Primitives, in model units, inside
// negative:
//   sphere(c=x,y,z r=R)                 c defaults to the origin
//   box(min=x,y,z max=x,y,z)            or box(c=x,y,z size=sx,sy,sz), or size=s for a cube
//   cylinder(a=x,y,z b=x,y,z r=R)       capped, axis from a to b
//   torus(c=x,y,z axis=x,y,z R=major r=minor)   axis defaults to z
//   plane(p=x,y,z n=x,y,z)              the half-space behind n (unbounded: intersect it)
// Transforms take one operand: translate(t=x,y,z X), rotate(axis=x,y,z deg=A [c=x,y,z] X)
// (right-handed, about c, default the origin), scale(s=k [c=x,y,z] X) (uniform, k > 0).
// `job:ID` is the kept implicit function of a succeeded PU job.
#pragma once

#include <map>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "worker/core/geometry.h"

namespace lsqsurf::csg {

enum class NodeKind {
  kUnion,
  kIntersection,
  kDifference,
  kSphere,
  kBox,
  kCylinder,
  kTorus,
  kPlane,
  kTranslate,
  kRotate,
  kScale,
  kJob,
};

// One parsed node, with its arguments checked and defaults filled in.
struct CsgNode {
  NodeKind kind = NodeKind::kUnion;
  std::map<std::string, std::vector<double>> args;  // Named numbers, e.g. "c" → {x, y, z}.
  std::string job_id;                               // kJob.
  std::vector<CsgNode> children;                    // Operations and transforms.

  core::Vec3d Vector(const std::string& key) const;  // A three-number argument.
  double Number(const std::string& key) const;       // A one-number argument.
};

// Limits of an expression, so that a request cannot make the server parse or evaluate without end.
inline constexpr size_t kMaxExpressionBytes = 65536;
inline constexpr int kMaxNodes = 1000;
inline constexpr int kMaxNesting = 64;
inline constexpr int kMaxJobReferences = 16;

// Errors: kInvalidArgument naming the column and what was expected there.
absl::StatusOr<CsgNode> ParseCsg(std::string_view text);

// The distinct job ids the expression refers to, in order of first appearance.
std::vector<std::string> ReferencedJobs(const CsgNode& root);

}  // namespace lsqsurf::csg

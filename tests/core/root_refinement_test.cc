// Root refinement on a segment: superlinear on smooth fields, and still exact next to a kink
// where the secant stalls.
#include <gtest/gtest.h>

#include <atomic>
#include <cmath>

#include "worker/core/implicit_function.h"

namespace lsqsurf::core {
namespace {

// F along the x axis only, with a count of evaluations.
class AlongX : public ImplicitFunction {
 public:
  explicit AlongX(double (*f)(double)) : f_(f) {}
  FieldValue Value(const Vec3d& x) const override {
    ++evaluations;
    return {f_(x.x()), true};
  }
  FieldGradient ValueAndGradient(const Vec3d& x) const override { return {Value(x).value, Vec3d::UnitX(), true}; }
  mutable std::atomic<int> evaluations{0};

 private:
  double (*f_)(double);
};

double Refine(const AlongX& field, double a, double b, int steps) {
  const double fa = field.ValueOnly(Vec3d(a, 0, 0)), fb = field.ValueOnly(Vec3d(b, 0, 0));
  field.evaluations = 0;
  return a + RefineRootOnSegment(field, Vec3d(a, 0, 0), Vec3d(b, 0, 0), fa, fb, steps) * (b - a);
}

TEST(RootRefinement, SmoothRootsConvergeInAFewSteps) {
  const AlongX cubic([](double x) { return x * x * x + 2 * x - 1; });  // Root 0.4533976515...
  const double root = Refine(cubic, 0, 1, 3);
  EXPECT_NEAR(root, 0.45339765151640376, 1e-9);
  EXPECT_LE(cubic.evaluations.load(), 8);  // Never the bisection fallback.
}

TEST(RootRefinement, AKinkBesideAPlateauIsBisectedToTheRoot) {
  // max(x − h, s) with s slowly rising and negative: a box face beside a sphere in a CSG
  // difference. The secant keeps landing on the plateau's side and creeps (without the bisection
  // it ends 0.11 short of the root).
  const AlongX kink([](double x) { return std::max(x - 0.797, -0.031 + 0.003 * x); });
  const double root = Refine(kink, 0, 1, 3);
  EXPECT_NEAR(root, 0.797, 1e-4);
  EXPECT_LE(kink.evaluations.load(), 3 + 8 + 12);
}

TEST(RootRefinement, ZeroStepsGiveTheSecantGuess) {
  const AlongX line([](double x) { return 2 * x - 0.5; });
  EXPECT_DOUBLE_EQ(Refine(line, 0, 1, 0), 0.25);
  EXPECT_EQ(line.evaluations.load(), 0);
}

}  // namespace
}  // namespace lsqsurf::core

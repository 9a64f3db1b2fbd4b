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

// Round-off beside the root: past the first secant step the values are specks of one sign that
// differ in their last bits, and Anderson–Björck's rescaling of the kept end by 1 − f/f_kept then
// shrinks it to their size, so the next secant guess may land anywhere in the bracket. The
// answer is the point that met the tolerance, not that guess (in a partition of unity over a
// dodecahedron's faces the guess left 12 of 300k vertices 1e-3 of the diagonal off the faces).
double root_of_speck = 0;
double SpeckBesideRoot(double x) {
  const double d = x - root_of_speck;
  if (std::abs(d) > 1e-9) return d;
  return 5e-18 * (1 + d);  // Positive, and smaller towards the negative end.
}

TEST(RootRefinement, RoundOffBesideTheRootDoesNotThrowTheAnswerAcrossTheBracket) {
  const AlongX speck(SpeckBesideRoot);
  int off = 0;
  for (int k = 1; k < 1000; ++k) {
    root_of_speck = k / 1000.0;
    for (int steps = 1; steps <= 4; ++steps) off += std::abs(Refine(speck, 0, 1, steps) - root_of_speck) > 1e-6;
  }
  EXPECT_EQ(off, 0);
}

TEST(RootRefinement, ZeroStepsGiveTheSecantGuess) {
  const AlongX line([](double x) { return 2 * x - 0.5; });
  EXPECT_DOUBLE_EQ(Refine(line, 0, 1, 0), 0.25);
  EXPECT_EQ(line.evaluations.load(), 0);
}

}  // namespace
}  // namespace lsqsurf::core

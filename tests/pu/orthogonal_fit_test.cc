#include "worker/pu/orthogonal_fit.h"

#include <gtest/gtest.h>

#include <random>

namespace lsqsurf::pu {
namespace {

struct Samples {
  std::vector<double> u, v, w, weight;
};

Samples Random(size_t n, uint64_t seed) {
  Samples s;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> d(-1, 1), wt(0.1, 1);
  for (size_t i = 0; i < n; ++i) {
    s.u.push_back(d(rng));
    s.v.push_back(d(rng));
    s.weight.push_back(wt(rng));
  }
  s.w.resize(n);
  return s;
}

// A polynomial of exactly total degree `degree` with unrelated coefficients.
double Height(int degree, double u, double v) {
  double h = 0.3 - 0.7 * u + 0.2 * v;
  if (degree >= 2) h += 0.5 * u * u - 0.4 * u * v + 0.9 * v * v;
  if (degree >= 3) h += -0.6 * u * u * u + 0.25 * u * v * v + 0.33 * v * v * v;
  if (degree >= 4) h += 0.8 * u * u * u * u - 0.45 * u * u * v * v + 0.15 * u * v * v * v;
  return h;
}

TEST(OrthogonalFit, ReproducesPolynomialHeightFieldsUpToTheirDegree) {
  for (int degree = 1; degree <= kMaxDegree; ++degree) {
    Samples s = Random(200, 7 + static_cast<uint64_t>(degree));
    for (size_t i = 0; i < s.u.size(); ++i) s.w[i] = Height(degree, s.u[i], s.v[i]);
    OrthogonalFitter fitter;
    fitter.Reset(s.u, s.v, s.w, s.weight);
    for (int d = 1; d <= kMaxDegree; ++d) {
      ASSERT_TRUE(fitter.RaiseDegree());
      if (d < degree) {
        EXPECT_GT(fitter.residual_energy(), 1e-8) << "degree " << d << " cannot fit degree " << degree;
        continue;
      }
      EXPECT_LT(fitter.residual_energy(), 1e-20) << d << " " << degree;
      // Off the samples too: the polynomial itself is recovered.
      for (double u : {-0.9, 0.1, 0.7}) {
        for (double v : {-0.5, 0.3, 0.95}) {
          EXPECT_NEAR(fitter.polynomial().Value(u, v), Height(degree, u, v), 1e-10);
        }
      }
    }
  }
}

TEST(OrthogonalFit, BasisIsOrthogonalAndResidualMatchesDirectSum) {
  Samples s = Random(120, 3);
  for (size_t i = 0; i < s.u.size(); ++i) s.w[i] = std::sin(3 * s.u[i]) * std::cos(2 * s.v[i]);
  OrthogonalFitter fitter;
  fitter.Reset(s.u, s.v, s.w, s.weight);
  double previous = fitter.residual_energy();
  for (int d = 1; d <= kMaxDegree; ++d) {
    ASSERT_TRUE(fitter.RaiseDegree());
    double direct = 0;
    for (size_t i = 0; i < s.u.size(); ++i) {
      const double r = s.w[i] - fitter.polynomial().Value(s.u[i], s.v[i]);
      direct += s.weight[i] * r * r;
    }
    EXPECT_NEAR(fitter.residual_energy(), direct, 1e-10 * (1 + direct));
    EXPECT_LT(fitter.residual_energy(), previous);  // Each degree fits strictly better here.
    previous = fitter.residual_energy();
  }
  // Every pair, not just the ones the short recurrence orthogonalized explicitly.
  for (int a = 0; a < kMaxTerms; ++a) {
    for (int b = 0; b < a; ++b) {
      const double scale = std::sqrt(fitter.BasisInnerProduct(a, a) * fitter.BasisInnerProduct(b, b));
      EXPECT_LT(std::abs(fitter.BasisInnerProduct(a, b)), 1e-10 * scale) << a << " " << b;
    }
  }
}

TEST(OrthogonalFit, CollinearDataStopsAtTheDegreeItSupports) {
  // All samples on the line v = 0.5 u: no term in v beyond what u already explains.
  Samples s = Random(50, 11);
  for (size_t i = 0; i < s.u.size(); ++i) {
    s.v[i] = 0.5 * s.u[i];
    s.w[i] = s.u[i] * s.u[i];
  }
  OrthogonalFitter fitter;
  fitter.Reset(s.u, s.v, s.w, s.weight);
  EXPECT_FALSE(fitter.RaiseDegree());
  EXPECT_EQ(fitter.degree(), 0);
}

TEST(OrthogonalFit, TooFewPointsForADegreeAreRejected) {
  Samples s = Random(5, 13);  // Degree 2 has 6 terms.
  for (size_t i = 0; i < s.u.size(); ++i) s.w[i] = s.u[i];
  OrthogonalFitter fitter;
  fitter.Reset(s.u, s.v, s.w, s.weight);
  EXPECT_TRUE(fitter.RaiseDegree());
  EXPECT_FALSE(fitter.RaiseDegree());
  EXPECT_EQ(fitter.degree(), 1);
  EXPECT_NEAR(fitter.polynomial().Value(0.2, -0.4), 0.2, 1e-12);
}

}  // namespace
}  // namespace lsqsurf::pu

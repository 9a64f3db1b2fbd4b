// worker/pu/orthogonal_fit.h — weighted least squares in bivariate orthogonal polynomials.
//
// Bartels & Jezioranski, "Least-squares fitting using orthogonal multinomials", ACM TOMS 11(3),
// 1985: the basis is built for the discrete weighted inner product of the data, one monomial at
// a time in graded order. Each new element is a variable times an element of one degree less,
// orthogonalized against the elements of degree d−2, d−1 and d (it is orthogonal to the lower
// ones already, in exact arithmetic), with one re-orthogonalization pass. Because the basis is
// orthogonal, raising the degree adds coefficients and leaves the old ones untouched, each new
// coefficient is the projection of the current residual (updated in O(n) per term), and a new element that vanishes on
// the data reveals that the data cannot support that degree.
#pragma once

#include <array>
#include <span>
#include <vector>

namespace lsqsurf::pu {

inline constexpr int kMaxDegree = 4;
inline constexpr int kMaxTerms = 15;

// Coefficients of a polynomial of total degree `degree` ≤ 4.
constexpr int TermCount(int degree) { return (degree + 1) * (degree + 2) / 2; }

// p(u, v) in monomial form, graded order: 1 | u v | u² uv v² | u³ u²v uv² v³ | u⁴ … v⁴.
// Safe to evaluate in this form because fits are made in coordinates scaled into [−1, 1].
struct BivariatePolynomial {
  std::array<double, kMaxTerms> coefficients{};
  int degree = 0;

  double Value(double u, double v) const;
  // Value and first partial derivatives.
  void Evaluate(double u, double v, double& value, double& du, double& dv) const;
};

// Fits w ≈ p(u, v) by weighted least squares, degree by degree, starting at degree 0.
// Not thread-safe; reuse one per thread (its buffers are kept between fits).
class OrthogonalFitter {
 public:
  // Starts a fit at degree 0 (the weighted mean of w). Spans must have equal sizes; weights
  // must be >= 0 with a positive sum. `rank_tolerance` is the relative size below which an
  // orthogonalized element counts as zero on the data.
  void Reset(std::span<const double> u, std::span<const double> v, std::span<const double> w,
             std::span<const double> weights, double rank_tolerance = 1e-9);

  // Adds the terms of the next degree. Returns false, and stays at the current degree, when the
  // degree is already 4 or the data cannot determine one of the new terms (rank deficiency).
  bool RaiseDegree();

  int degree() const { return polynomial_.degree; }
  // The current least-squares polynomial.
  const BivariatePolynomial& polynomial() const { return polynomial_; }
  // Weighted residual energy Σ weight·(w − p)².
  double residual_energy() const { return residual_energy_; }
  // ⟨φ_a, φ_b⟩ of two basis elements built so far (for checks of orthogonality).
  double BasisInnerProduct(int a, int b) const;

 private:
  double Inner(const double* a, const double* b) const;
  bool AddTerm(int index, int variable, int parent);

  size_t n_ = 0;
  double tolerance_ = 1e-9;
  std::span<const double> u_, v_, weights_;
  std::vector<double> values_;    // kMaxTerms × n: the basis elements at the data points.
  std::vector<double> residual_;  // w − p at the data points.
  std::vector<double> saved_residual_values_;
  std::array<std::array<double, kMaxTerms>, kMaxTerms> monomials_{};  // Basis in monomial form.
  std::array<double, kMaxTerms> norms_{};                             // ⟨φ_k, φ_k⟩.
  int terms_ = 0;
  BivariatePolynomial polynomial_;
  double residual_energy_ = 0;
};

}  // namespace lsqsurf::pu

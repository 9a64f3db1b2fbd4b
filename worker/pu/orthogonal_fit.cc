#include "worker/pu/orthogonal_fit.h"

#include <algorithm>
#include <cassert>

namespace lsqsurf::pu {
namespace {

constexpr int MonomialIndex(int a, int b) { return TermCount(a + b - 1) + b; }

// The monomial coefficients of `p` multiplied by u (variable 0) or v (variable 1).
std::array<double, kMaxTerms> MultiplyByVariable(const std::array<double, kMaxTerms>& p, int variable) {
  std::array<double, kMaxTerms> out{};
  for (int d = 0; d < kMaxDegree; ++d) {
    for (int b = 0; b <= d; ++b) {
      const double c = p[static_cast<size_t>(MonomialIndex(d - b, b))];
      if (c == 0) continue;
      const int target = variable == 0 ? MonomialIndex(d - b + 1, b) : MonomialIndex(d - b, b + 1);
      out[static_cast<size_t>(target)] += c;
    }
  }
  return out;
}

}  // namespace

double BivariatePolynomial::Value(double u, double v) const {
  double value, du, dv;
  Evaluate(u, v, value, du, dv);
  return value;
}

void BivariatePolynomial::Evaluate(double u, double v, double& value, double& du, double& dv) const {
  // Powers u^a v^b with their derivatives, term by term; at most 15 terms.
  std::array<double, kMaxDegree + 1> pu{1, u, u * u, u * u * u, u * u * u * u};
  std::array<double, kMaxDegree + 1> pv{1, v, v * v, v * v * v, v * v * v * v};
  value = du = dv = 0;
  for (int d = 0; d <= degree; ++d) {
    for (int b = 0; b <= d; ++b) {
      const int a = d - b;
      const double c = coefficients[static_cast<size_t>(MonomialIndex(a, b))];
      value += c * pu[static_cast<size_t>(a)] * pv[static_cast<size_t>(b)];
      if (a > 0) du += c * a * pu[static_cast<size_t>(a - 1)] * pv[static_cast<size_t>(b)];
      if (b > 0) dv += c * b * pu[static_cast<size_t>(a)] * pv[static_cast<size_t>(b - 1)];
    }
  }
}

double OrthogonalFitter::Inner(const double* a, const double* b) const {
  double sum = 0;
  for (size_t j = 0; j < n_; ++j) sum += weights_[j] * a[j] * b[j];
  return sum;
}

double OrthogonalFitter::BasisInnerProduct(int a, int b) const {
  assert(a < terms_ && b < terms_);
  return Inner(&values_[static_cast<size_t>(a) * n_], &values_[static_cast<size_t>(b) * n_]);
}

void OrthogonalFitter::Reset(std::span<const double> u, std::span<const double> v, std::span<const double> w,
                             std::span<const double> weights, double rank_tolerance) {
  assert(u.size() == v.size() && u.size() == w.size() && u.size() == weights.size());
  n_ = u.size();
  u_ = u, v_ = v, weights_ = weights;
  tolerance_ = rank_tolerance;
  values_.resize(static_cast<size_t>(kMaxTerms) * n_);
  std::fill_n(values_.begin(), n_, 1.0);
  monomials_ = {};
  monomials_[0][0] = 1;
  double weight_sum = 0, w_moment = 0;
  for (size_t j = 0; j < n_; ++j) {
    weight_sum += weights[j];
    w_moment += weights[j] * w[j];
  }
  norms_[0] = weight_sum;
  terms_ = 1;
  polynomial_ = {};
  polynomial_.coefficients[0] = weight_sum > 0 ? w_moment / weight_sum : 0;
  residual_.resize(n_);
  for (size_t j = 0; j < n_; ++j) residual_[j] = w[j] - polynomial_.coefficients[0];
  residual_energy_ = Inner(residual_.data(), residual_.data());
}

bool OrthogonalFitter::AddTerm(int index, int variable, int parent) {
  double* phi = &values_[static_cast<size_t>(index) * n_];
  const double* parent_values = &values_[static_cast<size_t>(parent) * n_];
  const std::span<const double> x = variable == 0 ? u_ : v_;
  for (size_t j = 0; j < n_; ++j) phi[j] = x[j] * parent_values[j];
  auto& mono = monomials_[static_cast<size_t>(index)];
  mono = MultiplyByVariable(monomials_[static_cast<size_t>(parent)], variable);
  const double initial_norm = Inner(phi, phi);
  if (!(initial_norm > 0)) return false;
  // Elements of degree below d−2 are orthogonal to x·φ_parent already (see the header).
  const int degree = polynomial_.degree + 1;
  const int first = degree >= 3 ? TermCount(degree - 3) : 0;
  for (int pass = 0; pass < 2; ++pass) {
    for (int q = first; q < index; ++q) {
      const double* phi_q = &values_[static_cast<size_t>(q) * n_];
      const double beta = Inner(phi, phi_q) / norms_[static_cast<size_t>(q)];
      for (size_t j = 0; j < n_; ++j) phi[j] -= beta * phi_q[j];
      for (int m = 0; m < kMaxTerms; ++m) {
        mono[static_cast<size_t>(m)] -= beta * monomials_[static_cast<size_t>(q)][static_cast<size_t>(m)];
      }
    }
  }
  const double norm = Inner(phi, phi);
  if (!(norm > tolerance_ * initial_norm)) return false;  // The data cannot see this term.
  norms_[static_cast<size_t>(index)] = norm;
  // Projecting the residual rather than w is the same in exact arithmetic and stabler.
  const double coefficient = Inner(residual_.data(), phi) / norm;
  for (int m = 0; m < kMaxTerms; ++m)
    polynomial_.coefficients[static_cast<size_t>(m)] += coefficient * mono[static_cast<size_t>(m)];
  for (size_t j = 0; j < n_; ++j) residual_[j] -= coefficient * phi[j];
  residual_energy_ = Inner(residual_.data(), residual_.data());
  return true;
}

bool OrthogonalFitter::RaiseDegree() {
  const int degree = polynomial_.degree + 1;
  if (degree > kMaxDegree) return false;
  const BivariatePolynomial saved = polynomial_;
  const double saved_residual = residual_energy_;
  saved_residual_values_.assign(residual_.begin(), residual_.end());
  for (int b = 0; b <= degree; ++b) {
    const int a = degree - b;
    const int index = MonomialIndex(a, b);
    const bool ok = a > 0 ? AddTerm(index, 0, MonomialIndex(a - 1, b)) : AddTerm(index, 1, MonomialIndex(0, b - 1));
    if (!ok) {
      polynomial_ = saved;
      residual_energy_ = saved_residual;
      residual_.swap(saved_residual_values_);
      return false;
    }
  }
  polynomial_.degree = degree;
  terms_ = TermCount(degree);
  return true;
}

}  // namespace lsqsurf::pu

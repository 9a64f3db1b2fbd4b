// worker/core/noise.h — the scan noise of an oriented cloud, estimated from the data alone.
#pragma once

#include <span>

#include "worker/core/geometry.h"
#include "worker/core/kd_tree.h"

namespace lsqsurf::core {

struct NoiseEstimate {
  double sigma = 0;           // Noise σ along the normal, model units.
  double points_in_ball = 0;  // Median number of points within 4σ of a point.
};

// The noise σ along the normal: the median, over an even sample of about 2048 points, of the
// residual RMS of a quadratic height fit to each one's neighbourhood. A quadratic follows the
// shape at that scale, so on clean data what remains is small (third-order terms: about 0.07 of
// the nearest-neighbour distance on the bunny and spot, 0.006 on fandisk's flat faces) and on
// noisy data it is the noise. The neighbourhood is the 48 nearest points, widened to a ball of
// 4σ: a neighbourhood thinner than the noise holds mostly points displaced alike and
// underestimates it, so the estimate is repeated on the wider ball until it settles.
// `normals[i]` belongs to tree.points()[i]. With `known_sigma` >= 0 only the ball is counted.
// Cost: about 2048 neighbourhood queries and fits per pass, at most 4 passes.
NoiseEstimate EstimateNoise(const KdTree& tree, std::span<const Vec3f> normals, double known_sigma = -1);

}  // namespace lsqsurf::core

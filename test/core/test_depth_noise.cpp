// The renderer's stereo depth model, measured on the clouds it makes: range-squared disparity
// noise with the camera presets' numbers, its spatial correlation, holes, edge fattening, seeds.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>

#include <opencv2/imgproc.hpp>

#include "scene.hpp"

namespace arucotag {
namespace {

const sim::Camera kCamera = test::RoverCamera();  // 1280x720, f ~ 1005 px

cv::Mat Wall(double z) { return cv::Mat(kCamera.size, CV_32F, cv::Scalar(z)); }

cv::Mat Cloud(const cv::Mat& depth, const sim::DepthNoise& stereo, unsigned seed = 5,
              double nan_fraction = 0.0, const cv::Mat& image = cv::Mat()) {
  sim::CloudOptions options;
  options.stereo = stereo;
  options.seed = seed;
  options.nan_fraction = nan_fraction;
  return sim::MakeOrganizedCloud(kCamera, depth, options, image);
}

cv::Mat ZOf(const cv::Mat& cloud) {
  cv::Mat z;
  cv::extractChannel(cloud, z, 2);
  return z;
}

struct Stats {
  double mean = 0, sigma = 0;
  int valid = 0;
};

Stats Measure(const cv::Mat& z) {
  Stats s;
  double sum = 0, sum2 = 0;
  for (auto it = z.begin<float>(); it != z.end<float>(); ++it) {
    if (!std::isfinite(*it)) continue;
    sum += *it;
    sum2 += double(*it) * *it;
    ++s.valid;
  }
  s.mean = sum / s.valid;
  s.sigma = std::sqrt(sum2 / s.valid - s.mean * s.mean);
  return s;
}

// Pearson correlation of the depth error between pixels `lag` columns apart.
double LagCorrelation(const cv::Mat& z, double truth, int lag) {
  double sa = 0, sb = 0, saa = 0, sbb = 0, sab = 0;
  int n = 0;
  for (int v = 0; v < z.rows; ++v) {
    const float* row = z.ptr<float>(v);
    for (int u = 0; u + lag < z.cols; ++u) {
      if (!std::isfinite(row[u]) || !std::isfinite(row[u + lag])) continue;
      const double a = row[u] - truth, b = row[u + lag] - truth;
      sa += a, sb += b, saa += a * a, sbb += b * b, sab += a * b;
      ++n;
    }
  }
  const double cov = sab / n - (sa / n) * (sb / n);
  return cov / std::sqrt((saa / n - sa * sa / n / n) * (sbb / n - sb * sb / n / n));
}

double HoleFraction(const cv::Mat& cloud) {
  const cv::Mat z = ZOf(cloud);
  return 1.0 - double(cv::countNonZero(z == z)) / z.total();  // NaN != NaN
}

TEST(DepthNoise, PresetsCarryTheirBaselineAndSubpixel) {
  const sim::DepthNoise zed = sim::DepthNoise::Zed2(), d435 = sim::DepthNoise::D435();
  EXPECT_DOUBLE_EQ(zed.baseline, 0.12);
  EXPECT_DOUBLE_EQ(d435.baseline, 0.050);
  EXPECT_GE(zed.disparity_sigma, 0.1);
  EXPECT_LE(zed.disparity_sigma, 0.3);
  EXPECT_GE(d435.disparity_sigma, 0.1);
  EXPECT_LE(d435.disparity_sigma, 0.3);
  // z^2 sigma_d / (f B): 25 * 0.15 / (1000 * 0.12).
  EXPECT_NEAR(zed.SigmaZ(5.0, 1000.0), 0.03125, 1e-12);
  EXPECT_EQ(sim::DepthNoise().SigmaZ(5.0, 1000.0), 0.0);
  const sim::DepthNoise custom(0.2, 0.25, 8.0, 4.0, 3.0);
  EXPECT_DOUBLE_EQ(custom.baseline, 0.2);
  EXPECT_DOUBLE_EQ(custom.disparity_sigma, 0.25);
  EXPECT_DOUBLE_EQ(custom.correlation_px, 8.0);
  EXPECT_DOUBLE_EQ(custom.edge_fattening_px, 4.0);
  EXPECT_DOUBLE_EQ(custom.min_texture, 3.0);
}

TEST(DepthNoise, SigmaGrowsWithRangeSquaredAsTheFormulaSays) {
  const double f = kCamera.K(0, 0);
  for (const sim::DepthNoise& stereo :
       {sim::DepthNoise::Zed2(), sim::DepthNoise::D435(), sim::DepthNoise(0.12, 0.3, 20.0, 0.0)}) {
    for (double z : {2.0, 5.0, 10.0}) {
      const double expected = z * z * stereo.disparity_sigma / (f * stereo.baseline);
      const Stats s = Measure(ZOf(Cloud(Wall(z), stereo)));
      EXPECT_EQ(s.valid, kCamera.size.area()) << "no holes asked for";
      EXPECT_NEAR(s.sigma, expected, 0.15 * expected)
          << "B " << stereo.baseline << " corr " << stereo.correlation_px << " z " << z;
      EXPECT_NEAR(s.mean, z, 0.1 * expected) << "unbiased";
      std::printf("B %.3f m, sigma_d %.2f px, corr %4.1f px, z %4.1f m: sigma_z %.4f m (formula %.4f)\n",
                  stereo.baseline, stereo.disparity_sigma, stereo.correlation_px, z, s.sigma, expected);
    }
  }
  // Range squared: 5x the range is 25x the error (the same seed, so the same disparity field).
  const Stats near = Measure(ZOf(Cloud(Wall(2.0), sim::DepthNoise::Zed2())));
  const Stats far = Measure(ZOf(Cloud(Wall(10.0), sim::DepthNoise::Zed2())));
  EXPECT_NEAR(far.sigma / near.sigma, 25.0, 25.0 * 0.05);
}

TEST(DepthNoise, ErrorComesInPatchesNotSalt) {
  const double z = 5.0;
  const cv::Mat patches = ZOf(Cloud(Wall(z), sim::DepthNoise::Zed2()));
  const double lag1 = LagCorrelation(patches, z, 1);
  EXPECT_GT(lag1, 0.9) << "5 px correlation: neighbours nearly agree";
  EXPECT_GT(LagCorrelation(patches, z, 5), 0.5);
  EXPECT_LT(std::abs(LagCorrelation(patches, z, 40)), 0.1) << "patches, not one offset";
  const cv::Mat white = ZOf(Cloud(Wall(z), sim::DepthNoise(0.12, 0.15, 0.0, 0.0)));
  EXPECT_LT(std::abs(LagCorrelation(white, z, 1)), 0.03);
  std::printf("lag-1 correlation: ZED 2 preset %.3f, white %.3f\n", lag1, LagCorrelation(white, z, 1));
}

TEST(DepthNoise, OldRelativeNoiseStillWhiteAndProportional) {
  sim::CloudOptions options;
  options.depth_noise_sigma = 0.01;
  const cv::Mat z = ZOf(sim::MakeOrganizedCloud(kCamera, Wall(4.0), options));
  EXPECT_NEAR(Measure(z).sigma, 0.04, 0.002);
  EXPECT_LT(std::abs(LagCorrelation(z, 4.0, 1)), 0.03);
  // Without any noise the cloud's z is the depth itself.
  const cv::Mat clean = ZOf(sim::MakeOrganizedCloud(kCamera, Wall(4.0), sim::CloudOptions()));
  EXPECT_EQ(cv::countNonZero(clean != 4.0f), 0);
}

TEST(DepthNoise, HoleFractionAsConfiguredAndInBlobs) {
  for (double fraction : {0.05, 0.25, 0.4}) {
    const cv::Mat cloud = Cloud(Wall(3.0), sim::DepthNoise::Zed2(), 11, fraction);
    EXPECT_NEAR(HoleFraction(cloud), fraction, 0.01) << fraction;
    // Blobs: a hole's right neighbour is a hole far more often than the fraction alone.
    const cv::Mat z = ZOf(cloud);
    int holes = 0, both = 0;
    for (int v = 0; v < z.rows; ++v)
      for (int u = 0; u + 1 < z.cols; ++u)
        if (std::isnan(z.at<float>(v, u))) {
          ++holes;
          both += std::isnan(z.at<float>(v, u + 1));
        }
    EXPECT_GT(double(both) / holes, 0.6) << fraction;
  }
}

TEST(DepthNoise, FeaturelessPatchesGiveNoDepth) {
  // Plain grey, with a textured square in the middle: only the square keeps its depth.
  cv::Mat image(kCamera.size, CV_8UC3, cv::Scalar::all(128));
  const cv::Rect textured(400, 200, 300, 200);
  cv::Mat grain(textured.size(), CV_8UC3);
  cv::RNG(3).fill(grain, cv::RNG::UNIFORM, cv::Scalar::all(60), cv::Scalar::all(200));
  grain.copyTo(image(textured));
  const cv::Mat z = ZOf(Cloud(Wall(3.0), sim::DepthNoise::Zed2(), 5, 0.0, image));
  const cv::Mat inner = z(textured - cv::Point(-4, -4) - cv::Size(8, 8));
  EXPECT_EQ(cv::countNonZero(inner == inner), static_cast<int>(inner.total()));
  const int valid = cv::countNonZero(z == z);
  EXPECT_LE(valid, textured.area() + 2 * 3 * (textured.width + textured.height) + 36)
      << "the grey outside, beyond half a window, is all holes";
  // The D435's projector textures blank walls: no such holes.
  const cv::Mat lit = ZOf(Cloud(Wall(3.0), sim::DepthNoise::D435(), 5, 0.0, image));
  EXPECT_EQ(cv::countNonZero(lit == lit), kCamera.size.area());
}

TEST(DepthNoise, ForegroundDepthBleedsPastTheSilhouette) {
  sim::RenderOptions render;
  render.background_depth = 10.0;
  const sim::Marker marker = sim::FacingCamera(3, 0.3, {0.1, 0.0, 2.0}, 20.0, 0.0, 10.0);
  cv::Mat depth;
  sim::RenderScene(kCamera, {marker}, render, &depth);
  const cv::Mat silhouette = depth < 5.0f;
  ASSERT_GT(cv::countNonZero(silhouette), 10000);
  cv::Mat outside;  // px from each background pixel to the nearest foreground pixel
  cv::distanceTransform(~silhouette, outside, cv::DIST_L2, cv::DIST_MASK_PRECISE);

  for (const sim::DepthNoise& stereo : {sim::DepthNoise::Zed2(), sim::DepthNoise::D435()}) {
    const cv::Mat z = ZOf(Cloud(depth, stereo));
    const double r = stereo.edge_fattening_px;
    int ring = 0, ring_fg = 0, beyond = 0, beyond_fg = 0, inside = 0, inside_fg = 0;
    for (int v = 0; v < z.rows; ++v)
      for (int u = 0; u < z.cols; ++u) {
        const float d = outside.at<float>(v, u), zz = z.at<float>(v, u);
        const bool fg = zz < 5.0f;
        if (d == 0) {
          ++inside, inside_fg += fg;
        } else if (d <= r - 0.5) {
          ++ring, ring_fg += fg;
        } else if (d >= r + 1.5 && d < r + 10) {
          ++beyond, beyond_fg += fg;
        }
      }
    EXPECT_EQ(inside_fg, inside);
    ASSERT_GT(ring, 500);
    EXPECT_EQ(ring_fg, ring) << "within " << r << " px outside, every pixel has the marker's depth";
    EXPECT_EQ(beyond_fg, 0) << "farther out, the wall";
    std::printf("fattening %.0f px: %d ring pixels with the marker's depth, %d of %d beyond\n", r, ring_fg,
                beyond_fg, beyond);
  }
  // Without fattening the ring is the wall's.
  sim::DepthNoise sharp = sim::DepthNoise::Zed2();
  sharp.edge_fattening_px = 0;
  const cv::Mat z = ZOf(Cloud(depth, sharp));
  EXPECT_EQ(cv::countNonZero((z < 5.0f) & (outside > 0)), 0);
}

TEST(DepthNoise, SameSeedSameCloud) {
  sim::RenderOptions render;
  cv::Mat depth;
  const cv::Mat image =
      sim::RenderScene(kCamera, {sim::FacingCamera(1, 0.2, {0.0, 0.0, 3.0}, 30.0)}, render, &depth);
  auto make = [&](unsigned seed) { return Cloud(depth, sim::DepthNoise::Zed2(), seed, 0.2, image); };
  const cv::Mat a = make(9), b = make(9), c = make(10);
  ASSERT_TRUE(a.isContinuous() && b.isContinuous());
  EXPECT_EQ(std::memcmp(a.data, b.data, a.total() * a.elemSize()), 0) << "bytes, NaN included";
  EXPECT_NE(std::memcmp(a.data, c.data, a.total() * a.elemSize()), 0);
}

}  // namespace
}  // namespace arucotag

// The sample world: layout, rover motion, light, and a renderer that puts the markers drawn by
// arucotag::sim (exact geometry) in front of a world-anchored backdrop (ground, hills, sky, poles).
#include "sample_scene.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

namespace arucotag::replay {
namespace {

constexpr double kDeg = CV_PI / 180.0;
constexpr double kPathStep = 0.001;  // s, integration step of the rover path
constexpr double kPathLength = 60.0; // s integrated; later times continue straight
constexpr double kTexel = 0.02;      // m per ground texel at pyramid level 0
constexpr int kTextureSize = 2048;   // texels per side: 41 m of ground, tiled beyond
constexpr double kFar = 1.0e4;       // m, "no marker" depth from the marker renderer
constexpr double kSpeed = 0.56;      // m/s, a rover closing in on a post

cv::Matx33d RotZ(double a) { return {std::cos(a), -std::sin(a), 0, std::sin(a), std::cos(a), 0, 0, 0, 1}; }
cv::Matx33d RotY(double a) { return {std::cos(a), 0, std::sin(a), 0, 1, 0, -std::sin(a), 0, std::cos(a)}; }
cv::Matx33d RotX(double a) { return {1, 0, 0, 0, std::cos(a), -std::sin(a), 0, std::sin(a), std::cos(a)}; }

// Raised-cosine yaw-rate pulse that turns the rover by `angle` between t0 and t1.
double TurnRate(double t, double t0, double t1, double angle) {
  if (t < t0 || t > t1) return 0.0;
  return angle / (t1 - t0) * (1.0 - std::cos(2.0 * CV_PI * (t - t0) / (t1 - t0)));
}

double Smooth(double t, double t0, double t1) {  // 0 before t0, 1 after t1, C1 in between
  const double s = std::clamp((t - t0) / (t1 - t0), 0.0, 1.0);
  return s * s * (3.0 - 2.0 * s);
}

// A marker standing upright, its face looking along compass `facing_deg` (0 = +x, 90 = +y), its
// centre at `centre`; `lean_deg` tips the top away from the viewer, `roll_deg` turns it in its plane.
WorldMarker Upright(std::string name, int id, cv::Vec3d centre, double facing_deg, double lean_deg = 0.0,
                    double roll_deg = 0.0) {
  const double a = facing_deg * kDeg;
  const cv::Vec3d z(std::cos(a), std::sin(a), 0.0), y(0, 0, 1), x = y.cross(z);
  const cv::Matx33d facing(x[0], y[0], z[0], x[1], y[1], z[1], x[2], y[2], z[2]);
  WorldMarker m;
  m.name = std::move(name);
  m.id = id;
  m.pose = Transform(facing * RotX(-lean_deg * kDeg) * RotZ(roll_deg * kDeg), centre);
  return m;
}

cv::Mat GroundTexture() {
  cv::RNG rng(20240611);
  const cv::Size size(kTextureSize, kTextureSize);
  // Regolith: one rusty hue whose lightness drifts over metres, a little hue drift, then mottling.
  cv::Mat light(9, 9, CV_32F), hue(7, 7, CV_32FC3), mid(96, 96, CV_32F), texture, mottle, tint;
  rng.fill(light, cv::RNG::UNIFORM, cv::Scalar(0.75), cv::Scalar(1.15));
  rng.fill(mid, cv::RNG::NORMAL, cv::Scalar(0), cv::Scalar(0.07));
  cv::resize(light, texture, size, 0, 0, cv::INTER_CUBIC);
  cv::resize(mid, mottle, size, 0, 0, cv::INTER_CUBIC);
  texture += mottle;
  cv::merge(std::vector<cv::Mat>{texture * 72.0, texture * 98.0, texture * 150.0}, texture);
  rng.fill(hue, cv::RNG::NORMAL, cv::Scalar::all(0), cv::Scalar::all(6));
  cv::resize(hue, tint, size, 0, 0, cv::INTER_CUBIC);
  texture += tint;
  // Pebbles (2-8 cm) and rocks (15-50 cm): darker bodies with a sunlit rim.
  for (int i = 0; i < 30000; ++i) {
    const cv::Point c(rng.uniform(0, size.width), rng.uniform(0, size.height));
    const cv::Size axes(rng.uniform(1, 4), rng.uniform(1, 3));
    const double shade = rng.uniform(0.55, 1.25);
    const cv::Vec3f base = texture.at<cv::Vec3f>(c);
    cv::ellipse(texture, c, axes, rng.uniform(0.0, 180.0), 0, 360, cv::Scalar(base * shade), cv::FILLED, cv::LINE_AA);
  }
  for (int i = 0; i < 160; ++i) {
    const cv::Point c(rng.uniform(0, size.width), rng.uniform(0, size.height));
    const cv::Size axes(rng.uniform(8, 25), rng.uniform(6, 16));
    const double angle = rng.uniform(0.0, 180.0);
    cv::ellipse(texture, c + cv::Point(2, 2), axes, angle, 0, 360, cv::Scalar(30, 40, 60), cv::FILLED, cv::LINE_AA);
    cv::ellipse(texture, c, axes, angle, 0, 360, cv::Scalar(60, 75, 105), cv::FILLED, cv::LINE_AA);
    cv::ellipse(texture, c - cv::Point(2, 2), axes / 2, angle, 0, 360, cv::Scalar(85, 105, 140), cv::FILLED,
                cv::LINE_AA);
  }
  cv::Mat grain(size, CV_32FC3);
  rng.fill(grain, cv::RNG::NORMAL, cv::Scalar::all(0), cv::Scalar::all(6));
  texture += grain;
  cv::GaussianBlur(texture, texture, cv::Size(), 0.8);
  return texture;
}

// Bilinear lookup in a tiled texture whose sides are powers of two, coordinates in texels.
cv::Vec3f Bilinear(const cv::Mat& texture, double u, double v) {
  const long wm = texture.cols - 1, hm = texture.rows - 1;  // masks: wrap without a division
  const double fu = std::floor(u), fv = std::floor(v);
  const float au = static_cast<float>(u - fu), av = static_cast<float>(v - fv);
  const long iu = static_cast<long>(fu), iv = static_cast<long>(fv);
  const cv::Vec3f* r0 = texture.ptr<cv::Vec3f>(static_cast<int>(iv & hm));
  const cv::Vec3f* r1 = texture.ptr<cv::Vec3f>(static_cast<int>((iv + 1) & hm));
  const long u0 = iu & wm, u1 = (iu + 1) & wm;
  return (r0[u0] * (1 - au) + r0[u1] * au) * (1 - av) + (r1[u0] * (1 - au) + r1[u1] * au) * av;
}

// A centred linear-motion kernel of `length` px along `angle_deg`, drawn anti-aliased at 8x and
// area-averaged down so sub-pixel lengths and any angle work.
cv::Mat MotionKernel(double length, double angle_deg) {
  constexpr int kUp = 8;
  const int half = static_cast<int>(std::ceil(length / 2.0)) + 1;
  const int n = (2 * half + 1) * kUp;
  cv::Mat canvas(n, n, CV_32F, cv::Scalar(0));
  // The canvas's centre pixel's centre (pixel centres at integer coordinates, as cv::line draws): at n / 2
  // the streak sat half a canvas pixel off, and every blurred frame of the recording moved by -1/16 px in x
  // and y against its truth (found at stop 39: all markers' corners (-0.06, -0.07) px off).
  const cv::Point2d c((n - 1) / 2.0, (n - 1) / 2.0);
  const cv::Point2d d(std::cos(angle_deg * kDeg) * length * kUp / 2.0, std::sin(angle_deg * kDeg) * length * kUp / 2.0);
  constexpr int kShift = 4;  // sub-pixel line end points
  const auto fixed = [](const cv::Point2d& p) { return cv::Point(cvRound(p.x * (1 << kShift)), cvRound(p.y * (1 << kShift))); };
  cv::line(canvas, fixed(c - d), fixed(c + d), cv::Scalar(1.0), kUp, cv::LINE_AA, kShift);
  cv::Mat kernel;
  cv::resize(canvas, kernel, cv::Size(2 * half + 1, 2 * half + 1), 0, 0, cv::INTER_AREA);
  return kernel / cv::sum(kernel)[0];
}

}  // namespace

SampleScene::SampleScene(const SampleOptions& options)
    : options_(options), camera_(sim::MakeCamera(options.size, options.hfov_deg)) {
  if (options.cloud_factor < 1 || options.size.width % options.cloud_factor || options.size.height % options.cloud_factor) {
    throw std::invalid_argument("SampleOptions: cloud_factor must be >= 1 and divide the image's width and height");
  }
  // A URC post: one id on the three faces of a triangular prism (0.2 m faces, centre 0.6 m up).
  const cv::Vec3d post(7.65, -0.98, 0.6);
  const double post_turn = 21.6;  // deg: face a looks back along the approach, 20-50 deg off axis
  const double inradius = 0.2 / (2.0 * std::sqrt(3.0)) + 0.001;
  const char* faces[] = {"post_a", "post_b", "post_c"};
  for (int i = 0; i < 3; ++i) {
    const double facing = post_turn + 180.0 + 120.0 * i;
    const cv::Vec3d out(std::cos(facing * kDeg), std::sin(facing * kDeg), 0.0);
    markers_.push_back(Upright(faces[i], 1, post + out * inradius, facing));
  }
  poles_.push_back({{post[0], post[1]}, 0.04, 0.0, post[2] - 0.1, {70, 72, 78}});
  // Single markers on stakes and rocks, seen from 2 to 15 m along the way.
  markers_.push_back(Upright("stake_7", 7, {4.2, 2.5, 0.45}, 205.0));
  markers_.push_back(Upright("stake_12", 12, {15.5, 3.5, 0.55}, 195.0));
  markers_.push_back(Upright("rock_23", 23, {11.0, 4.2, 0.3}, 230.0, 25.0, 20.0));
  markers_.push_back(Upright("stake_3", 3, {12.5, -2.6, 0.5}, 170.0, 0.0, -10.0));
  markers_.push_back(Upright("stake_42", 42, {4.0, -1.2, 0.4}, 160.0));
  for (const auto& m : markers_) {
    if (m.name.rfind("stake_", 0) != 0) continue;
    const cv::Vec3d c = m.pose.translation(), normal = m.pose.rotation() * cv::Vec3d(0, 0, 1);
    poles_.push_back({{c[0] - 0.03 * normal[0], c[1] - 0.03 * normal[1]}, 0.015, 0.0, c[2], {60, 80, 100}});
  }

  cv::buildPyramid(GroundTexture(), ground_, 7);

  // Rover path: a slight right drift, then a left turn past the post.
  path_.reserve(static_cast<size_t>(kPathLength / kPathStep) + 1);
  double x = 0.0, y = 0.4, yaw = 2.5 * kDeg;
  for (size_t k = 0; k * kPathStep <= kPathLength; ++k) {
    const double t = k * kPathStep;
    path_.emplace_back(x, y, yaw);
    const double rate = TurnRate(t, 1.4, 5.5, -8.5 * kDeg) + TurnRate(t, 9.4, 14.2, 31.0 * kDeg);
    x += kSpeed * std::cos(yaw) * kPathStep;
    y += kSpeed * std::sin(yaw) * kPathStep;
    yaw += rate * kPathStep;
  }
}

Transform SampleScene::RoverPose(double t) const {
  t = std::max(0.0, t);
  cv::Vec3d p;
  const double k = t / kPathStep;
  if (k >= path_.size() - 1) {
    const cv::Vec3d last = path_.back();
    const double s = (t - (path_.size() - 1) * kPathStep) * kSpeed;
    p = {last[0] + s * std::cos(last[2]), last[1] + s * std::sin(last[2]), last[2]};
  } else {
    const size_t i = static_cast<size_t>(k);
    const double a = k - i;
    p = path_[i] * (1.0 - a) + path_[i + 1] * a;
  }
  // Suspension on rough ground: pitch and roll oscillations and a little bounce.
  const double w = 2.0 * CV_PI;
  const double pitch = (1.0 * std::sin(w * 1.7 * t) + 0.4 * std::sin(w * 3.3 * t + 1.0)) * kDeg;
  const double roll = 0.7 * std::sin(w * 1.1 * t + 0.4) * kDeg;
  const double bounce = 0.01 * std::sin(w * 1.7 * t + 0.5);
  return Transform(RotZ(p[2]) * RotY(pitch) * RotX(roll), cv::Vec3d(p[0], p[1], bounce));
}

sim::Camera SampleScene::CloudCamera() const {
  // Image pixel centres are at integer coordinates: block u spans f u - 0.5 ... f u + f - 0.5, whose
  // centre f u + (f - 1) / 2 must map to u.
  const double f = options_.cloud_factor;
  sim::Camera grid = camera_;
  grid.size = cv::Size(camera_.size.width / options_.cloud_factor, camera_.size.height / options_.cloud_factor);
  grid.K(0, 0) /= f;
  grid.K(1, 1) /= f;
  grid.K(0, 2) = (camera_.K(0, 2) - (f - 1.0) / 2.0) / f;
  grid.K(1, 2) = (camera_.K(1, 2) - (f - 1.0) / 2.0) / f;
  return grid;
}

Transform SampleScene::MastMount() { return Transform(RotY(4.0 * kDeg), cv::Vec3d(0.25, 0.06, 1.0)); }

Transform SampleScene::OpticalInBody() { return Transform(cv::Matx33d(0, 0, 1, -1, 0, 0, 0, -1, 0), cv::Vec3d()); }

Transform SampleScene::CameraPose(double t) const { return RoverPose(t) * MastMount() * OpticalInBody(); }

std::vector<sim::Marker> SampleScene::MarkersInView(const Transform& odom_optical) const {
  // Only markers (with their white margin) wholly in front of the camera and overlapping the image:
  // the renderer scans far more pixels for markers at the edge of the view than they cover.
  const Transform optical_odom = odom_optical.inv();
  std::vector<sim::Marker> out;
  for (const auto& m : markers_) {
    const Transform pose = optical_odom * m.pose;
    bool in_front = true;
    cv::Point2d lo(1e18, 1e18), hi(-1e18, -1e18);
    for (const auto& c : sim::MarkerCorners3d(m.side * 1.5)) {
      const cv::Vec3d q = pose * cv::Vec3d(c.x, c.y, c.z);
      in_front &= q[2] > 0.05;
      const cv::Point2d px(camera_.K(0, 0) * q[0] / q[2] + camera_.K(0, 2), camera_.K(1, 1) * q[1] / q[2] + camera_.K(1, 2));
      lo = {std::min(lo.x, px.x), std::min(lo.y, px.y)};
      hi = {std::max(hi.x, px.x), std::max(hi.y, px.y)};
    }
    const bool overlaps = hi.x > -1 && hi.y > -1 && lo.x < camera_.size.width && lo.y < camera_.size.height;
    if (!in_front || !overlaps) continue;
    sim::Marker s;
    s.id = m.id;
    s.side = m.side;
    cv::Rodrigues(pose.rotation(), s.rvec);
    s.tvec = pose.translation();
    out.push_back(s);
  }
  return out;
}

std::vector<TruthTag> SampleScene::TruthFor(const Transform& odom_optical, const cv::Mat* marker_depth) const {
  const Transform optical_odom = odom_optical.inv();
  const cv::Size size = camera_.size;
  std::vector<TruthTag> truth;
  for (const auto& m : markers_) {
    const Transform pose = optical_odom * m.pose;
    const cv::Vec3d t = pose.translation();
    const cv::Vec3d normal = pose.rotation() * cv::Vec3d(0, 0, 1);
    const double cos_view = -normal.dot(t) / cv::norm(t);
    if (t[2] <= 0.05 || cos_view <= 0.0) continue;  // behind the camera or seen from the back
    sim::Marker s;
    s.id = m.id;
    s.side = m.side;
    cv::Rodrigues(pose.rotation(), s.rvec);
    s.tvec = t;
    const cv::Point2f centre = sim::ProjectCentre(camera_, s);
    if (centre.x < 0 || centre.y < 0 || centre.x > size.width - 1 || centre.y > size.height - 1) continue;

    TruthTag tag;
    tag.name = m.name;
    tag.id = m.id;
    tag.side = m.side;
    tag.rvec = s.rvec;
    tag.tvec = t;
    tag.centre = centre;
    tag.distance = cv::norm(t);
    tag.yaw = std::atan2(t[0], t[2]);
    tag.obliquity = std::acos(std::min(1.0, cos_view)) / kDeg;
    tag.corners = sim::ProjectCorners(camera_, s);
    bool complete = true;
    for (const auto& c : tag.corners) {
      complete &= c.x >= 3 && c.y >= 3 && c.x <= size.width - 4 && c.y <= size.height - 4;
    }
    if (complete && marker_depth) {
      // Hidden when the renderer saw something nearer at the centre or near a corner.
      const auto corners3d = sim::MarkerCorners3d(m.side * 0.8);
      std::vector<cv::Point3d> probes(corners3d.begin(), corners3d.end());
      probes.emplace_back(0, 0, 0);
      for (const auto& p : probes) {
        const cv::Vec3d q = pose * cv::Vec3d(p.x, p.y, p.z);
        const cv::Point px(cvRound(camera_.K(0, 0) * q[0] / q[2] + camera_.K(0, 2)),
                           cvRound(camera_.K(1, 1) * q[1] / q[2] + camera_.K(1, 2)));
        if (!cv::Rect(cv::Point(), size).contains(px)) continue;
        complete &= marker_depth->at<float>(px) > q[2] * 0.98;
      }
    }
    tag.complete = complete;
    truth.push_back(tag);
  }
  return truth;
}

std::vector<TruthTag> SampleScene::Truth(double t) const { return TruthFor(CameraPose(t), nullptr); }

SampleScene::Photometry SampleScene::LightAt(double t, const std::vector<TruthTag>& truth) const {
  Photometry p{};
  // Slow sun drift, a cloud shadow from 4 to 8.5 s, glare towards the end.
  const double cloud = Smooth(t, 4.0, 5.2) * (1.0 - Smooth(t, 7.3, 8.5));
  p.brightness = 1.0 + 0.2 * std::sin(2.0 * CV_PI * t / 11.0 + 0.3) - 0.45 * cloud;
  p.contrast = 0.9 - 0.1 * cloud;
  p.exposure_ms = 6.0 / p.brightness;  // auto exposure opens up in the shade ...
  p.noise_sigma = 1.5 + 3.0 * std::max(0.0, 1.0 - p.brightness);  // ... and adds gain
  // Motion blur: how far the nearest whole marker (else a point 5 m ahead) moves in the image
  // while the shutter is open.
  cv::Vec3d anchor(0, 0, 5.0);
  double nearest = 1e9;
  for (const auto& tag : truth) {
    if (tag.complete && tag.distance < nearest) {
      nearest = tag.distance;
      anchor = tag.tvec;
    }
  }
  const cv::Vec3d world = CameraPose(t) * anchor;
  const cv::Vec3d later = CameraPose(t + p.exposure_ms * 1e-3).inv() * world;
  const cv::Matx33d& K = camera_.K;
  const cv::Point2d a(K(0, 0) * anchor[0] / anchor[2], K(1, 1) * anchor[1] / anchor[2]);
  const cv::Point2d b(K(0, 0) * later[0] / later[2], K(1, 1) * later[1] / later[2]);
  p.blur_px = cv::norm(b - a);
  p.blur_angle_deg = std::atan2(b.y - a.y, b.x - a.x) / kDeg;
  return p;
}

cv::Vec3f SampleScene::SampleGround(double x, double y, double footprint) const {
  // Trilinear: pick the two pyramid levels around the footprint so distant ground does not alias.
  const double level = std::clamp(std::log2(std::max(footprint, 1e-9) / kTexel), 0.0, ground_.size() - 1.0);
  const int l0 = static_cast<int>(level), l1 = std::min<int>(l0 + 1, ground_.size() - 1);
  const double a = level - l0;
  const auto at = [&](int l) {
    const double scale = 1.0 / (kTexel * (1 << l));
    return Bilinear(ground_[l], (x + 8.0) * scale, (y + 20.5) * scale);
  };
  return at(l0) * (1.0 - a) + at(l1) * a;
}

void SampleScene::RenderBackdrop(const Transform& odom_optical, cv::Mat& colour, cv::Mat& depth) const {
  const cv::Size size = camera_.size;
  colour.create(size, CV_32FC3);
  depth.create(size, CV_32F);
  const cv::Matx33d R = odom_optical.rotation();
  const cv::Vec3d eye = odom_optical.translation();
  const cv::Matx33d k_inv = camera_.K.inv();
  const double f = camera_.K(0, 0);
  const cv::Vec3f sky_low(150, 178, 210), sky_high(112, 138, 178), hills(118, 136, 168);
  cv::parallel_for_(cv::Range(0, size.height), [&](const cv::Range& rows) {
    for (int v = rows.start; v < rows.end; ++v) {
      auto* out = colour.ptr<cv::Vec3f>(v);
      auto* z = depth.ptr<float>(v);
      for (int u = 0; u < size.width; ++u) {
        const cv::Vec3d d = R * (k_inv * cv::Vec3d(u, v, 1.0));  // optical z = 1: scale = optical depth
        const double length = cv::norm(d), horizontal = std::hypot(d[0], d[1]);
        const double s = d[2] < -1e-6 ? -eye[2] / d[2] : -1.0;  // ray parameter at the ground
        if (s > 0 && s * horizontal < 400.0) {
          const double range = s * length;
          // Pixel footprint on the ground: range / f across the ray, stretched by the grazing angle
          // along it; the geometric mean blurs less than the long axis would.
          const double footprint = range / f / std::sqrt(-d[2] / length);
          const cv::Vec3f ground = SampleGround(eye[0] + s * d[0], eye[1] + s * d[1], footprint);
          const float haze = static_cast<float>(1.0 - std::exp(-range / 70.0));
          out[u] = ground * (1.0f - haze) + sky_low * haze;
          z[u] = static_cast<float>(s);
          continue;
        }
        // Far hills on the horizon (within 3 degrees of it), then the sky.
        const double elevation = std::asin(d[2] / length);
        const double ridge =
            elevation > 3.0 * kDeg ? 0.0
                                   : (1.2 + 0.8 * std::sin(3.0 * std::atan2(d[1], d[0]) + 0.7) +
                                      0.4 * std::sin(7.0 * std::atan2(d[1], d[0]) + 2.0)) * kDeg;
        if (elevation < ridge) {
          out[u] = hills * static_cast<float>(1.0 + 2.0 * (elevation - ridge));
        } else {
          const float a = static_cast<float>(std::clamp(elevation / (40.0 * kDeg), 0.0, 1.0));
          out[u] = sky_low * (1.0f - a) + sky_high * a;
        }
        z[u] = std::numeric_limits<float>::infinity();
      }
    }
  });
}

void SampleScene::RenderPoles(const Transform& odom_optical, cv::Mat& colour, cv::Mat& depth) const {
  const cv::Size size = camera_.size;
  const Transform optical_odom = odom_optical.inv();
  const cv::Matx33d R = odom_optical.rotation();
  const cv::Vec3d eye = odom_optical.translation();
  const cv::Matx33d k_inv = camera_.K.inv();
  const cv::Vec2d sun(std::cos(2.3), std::sin(2.3));
  for (const Pole& pole : poles_) {
    // Image box of the pole's bounding cylinder; skip poles reaching behind the camera.
    std::vector<cv::Point2d> px;
    bool in_front = true;
    for (double zz : {pole.bottom, pole.top})
      for (double a = 0; a < 2 * CV_PI; a += CV_PI / 2) {
        const cv::Vec3d q = optical_odom * cv::Vec3d(pole.axis[0] + pole.radius * 1.5 * std::cos(a),
                                                     pole.axis[1] + pole.radius * 1.5 * std::sin(a), zz);
        in_front &= q[2] > 0.05;
        px.emplace_back(camera_.K(0, 0) * q[0] / q[2] + camera_.K(0, 2), camera_.K(1, 1) * q[1] / q[2] + camera_.K(1, 2));
      }
    if (!in_front) continue;
    const cv::Rect box = (cv::boundingRect(std::vector<cv::Point2f>(px.begin(), px.end())) + cv::Size(3, 3) -
                          cv::Point(1, 1)) & cv::Rect(cv::Point(), size);
    for (int v = box.y; v < box.y + box.height; ++v)
      for (int u = box.x; u < box.x + box.width; ++u) {
        const cv::Vec3d d = R * (k_inv * cv::Vec3d(u, v, 1.0));
        // |eye_xy + s d_xy - axis|^2 = r^2, nearest root.
        const cv::Vec2d o(eye[0] - pole.axis[0], eye[1] - pole.axis[1]), dd(d[0], d[1]);
        const double a = dd.dot(dd), b = 2 * o.dot(dd), c = o.dot(o) - pole.radius * pole.radius;
        const double disc = b * b - 4 * a * c;
        if (a < 1e-12 || disc < 0) continue;
        const double s = (-b - std::sqrt(disc)) / (2 * a);
        const double zz = eye[2] + s * d[2];
        if (s <= 0 || zz < pole.bottom || zz > pole.top || s >= depth.at<float>(v, u)) continue;
        const cv::Vec2d n = (o + s * dd) / pole.radius;
        const float light = static_cast<float>(0.55 + 0.45 * std::max(0.0, n.dot(sun)));
        colour.at<cv::Vec3f>(v, u) = pole.colour * light;
        depth.at<float>(v, u) = static_cast<float>(s);
      }
  }
}

SampleFrame SampleScene::Render(double t, bool with_cloud) const {
  const Transform odom_optical = CameraPose(t);
  const std::vector<sim::Marker> markers = MarkersInView(odom_optical);
  // Two marker passes over a flat grey (128) background: printed levels, then all-white, which
  // gives each pixel's marker coverage c exactly: white = 128 (1 - c) + 255 c.
  sim::RenderOptions plain;
  plain.textured_background = false;
  plain.colour = false;
  plain.supersample = options_.supersample;
  plain.background_depth = kFar;
  cv::Mat marker_depth;
  const cv::Mat printed = sim::RenderScene(camera_, markers, plain, &marker_depth);
  sim::RenderOptions white = plain;
  white.black_level = white.white_level = 255.0;
  const cv::Mat coverage_img = markers.empty() ? printed : sim::RenderScene(camera_, markers, white);

  SampleFrame frame;
  frame.time = t;
  frame.truth = TruthFor(odom_optical, &marker_depth);

  cv::Mat colour, depth;
  RenderBackdrop(odom_optical, colour, depth);
  RenderPoles(odom_optical, colour, depth);
  cv::Mat coverage, ink;
  coverage_img.convertTo(coverage, CV_32F, 1.0 / 127.0, -128.0 / 127.0);
  printed.convertTo(ink, CV_32F);
  for (int v = 0; v < colour.rows; ++v) {
    auto* out = colour.ptr<cv::Vec3f>(v);
    const float* c = coverage.ptr<float>(v);
    const float* g = ink.ptr<float>(v);
    float* z = depth.ptr<float>(v);
    const float* mz = marker_depth.ptr<float>(v);
    for (int u = 0; u < colour.cols; ++u) {
      const float cov = std::clamp(c[u], 0.0f, 1.0f);
      if (cov <= 0.0f) continue;
      out[u] = out[u] * (1.0f - cov) + cv::Vec3f::all(g[u] - 128.0f * (1.0f - cov));
      if (mz[u] < kFar) z[u] = std::min(z[u], mz[u]);
    }
  }

  // Camera response: light level and contrast, lens blur, motion blur, sensor noise.
  const Photometry light = LightAt(t, frame.truth);
  frame.brightness = light.brightness;
  frame.exposure_ms = light.exposure_ms;
  frame.motion_blur_px = light.blur_px;
  colour = ((colour - cv::Scalar::all(128)) * light.contrast + cv::Scalar::all(128)) * light.brightness;
  cv::GaussianBlur(colour, colour, cv::Size(), 0.6);
  if (light.blur_px > 0.3) {
    cv::filter2D(colour, colour, -1, MotionKernel(light.blur_px, light.blur_angle_deg), cv::Point(-1, -1), 0,
                 cv::BORDER_REFLECT);
  }
  // What stereo matching sees for texture: the scene before sensor noise (noise is no texture: it
  // differs between the two imagers), on the cloud's grid.
  cv::Mat texture;
  if (with_cloud) cv::resize(colour, texture, CloudCamera().size, 0, 0, cv::INTER_AREA);
  const unsigned seed = 7919u * static_cast<unsigned>(std::llround(t * 1000.0)) + 17u;
  cv::RNG rng(seed);
  cv::Mat noise(colour.size(), colour.type());
  rng.fill(noise, cv::RNG::NORMAL, cv::Scalar::all(0), cv::Scalar::all(light.noise_sigma));
  colour += noise;
  colour.convertTo(frame.image, CV_8UC3);

  if (!with_cloud) return frame;
  // Stereo cloud at the reduced resolution: each block's mean depth (what it sees within range; NaN
  // when nothing is), dropouts and the stereo depth model on that grid, then into the body frame.
  const int f = options_.cloud_factor;
  const sim::Camera grid = CloudCamera();
  cv::Mat block_depth(grid.size, CV_32F);
  for (int v = 0; v < grid.size.height; ++v) {
    for (int u = 0; u < grid.size.width; ++u) {
      double sum = 0.0;
      int count = 0;
      for (int dv = 0; dv < f; ++dv) {
        const float* z = depth.ptr<float>(f * v + dv) + f * u;
        for (int du = 0; du < f; ++du) {
          if (std::isfinite(z[du]) && z[du] <= options_.cloud_range) {
            sum += z[du];
            ++count;
          }
        }
      }
      block_depth.at<float>(v, u) = count ? static_cast<float>(sum / count) : std::numeric_limits<float>::quiet_NaN();
    }
  }
  sim::CloudOptions cloud_options;
  cloud_options.nan_fraction = options_.cloud_holes;
  cloud_options.stereo = options_.cloud_stereo;
  cloud_options.seed = seed + 1;
  const cv::Mat optical = sim::MakeOrganizedCloud(grid, block_depth, cloud_options, texture);
  const cv::Matx33f to_body = OpticalInBody().rotation();
  frame.cloud.create(optical.size(), CV_32FC3);
  for (int v = 0; v < optical.rows; ++v) {
    const auto* in = optical.ptr<cv::Vec3f>(v);
    auto* out = frame.cloud.ptr<cv::Vec3f>(v);
    for (int u = 0; u < optical.cols; ++u) out[u] = to_body * in[u];  // NaN stays NaN
  }
  return frame;
}

}  // namespace arucotag::replay

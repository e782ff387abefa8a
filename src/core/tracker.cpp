#include <arucotag/tracker.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <tuple>

#include <opencv2/calib3d.hpp>

namespace arucotag {

namespace {

using Matx66 = cv::Matx<double, 6, 6>;
using Vec6 = cv::Vec<double, 6>;

void Require(bool ok, const char* what) {
  if (!ok) throw Error(std::string("tracker: ") + what);
}

bool AllFinite(const PoseCovariance& c) {
  return std::all_of(c.val, c.val + 36, [](double v) { return std::isfinite(v); });
}

bool Contains(const std::vector<std::string>& names, const std::string& name) {
  return std::find(names.begin(), names.end(), name) != names.end();
}

// B C B^T with B = diag(R, R): a pose covariance expressed in a frame rotated by R.
PoseCovariance Rotate(const PoseCovariance& c, const cv::Matx33d& r) {
  Matx66 b = Matx66::zeros();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) b(i, j) = b(3 + i, 3 + j) = r(i, j);
  }
  return b * c * b.t();
}

Matx66 Symmetric(const Matx66& m) { return (m + m.t()) * 0.5; }

// rad between two rotations.
double Angle(const cv::Matx33d& a, const cv::Matx33d& b) {
  const double c = (cv::trace(a * b.t()) - 1.0) / 2.0;
  return std::acos(std::max(-1.0, std::min(1.0, c)));
}

// rad between the directions of two points seen from the origin.
double Bearing(const cv::Vec3d& a, const cv::Vec3d& b) {
  const double norms = cv::norm(a) * cv::norm(b);
  return norms > 0.0 ? std::acos(std::max(-1.0, std::min(1.0, a.dot(b) / norms))) : 0.0;
}

// The measurement minus the track: position difference and the small rotation taking the track's
// orientation to the measured one, both in the fixed frame. With left perturbations on both, the
// measurement matrix is the identity.
Vec6 Innovation(const Track& track, const TrackMeasurement& m) {
  cv::Vec3d dtheta;
  cv::Rodrigues(m.rotation * track.rotation.t(), dtheta);
  const cv::Vec3d dp = m.position - track.position;
  return Vec6(dp[0], dp[1], dp[2], dtheta[0], dtheta[1], dtheta[2]);
}

}  // namespace

void TrackerConfig::Validate() const {
  Require(validation_hits >= 1, "validation_hits must be >= 1");
  Require(std::isfinite(validation_window) && validation_window > 0.0, "validation_window must be > 0 s");
  Require(max_misses >= 1, "max_misses must be >= 1");
  Require(std::isfinite(max_unseen) && max_unseen > 0.0, "max_unseen must be > 0 s");
  Require(std::isfinite(gate) && gate > 0.0, "gate must be > 0 (a squared Mahalanobis distance)");
  Require(std::isfinite(position_noise) && position_noise >= 0.0, "position_noise must be >= 0 m/sqrt(s)");
  Require(std::isfinite(rotation_noise) && rotation_noise >= 0.0, "rotation_noise must be >= 0 rad/sqrt(s)");
  Require(std::isfinite(association_distance) && association_distance > 0.0, "association_distance must be > 0 m");
  Require(std::isfinite(association_angle) && association_angle > 0.0 && association_angle <= M_PI,
          "association_angle must be in (0, pi] rad");
}

TrackMeasurement MeasurementInFrame(const ArucoTag& tag, const cv::Matx33d& rotation, const cv::Vec3d& translation) {
  if (!tag.HasPose()) throw Error("tracker: tag " + std::to_string(tag.id) + " has no pose to track");
  cv::Matx33d marker_to_camera;
  cv::Rodrigues(tag.rvec, marker_to_camera);
  TrackMeasurement m;
  m.id = tag.id;
  m.position = rotation * tag.tvec + translation;
  m.rotation = rotation * marker_to_camera;
  m.covariance = Rotate(tag.covariance, rotation);
  const PnpResult& pnp = tag.pnp;
  const bool is_pnp = tag.pose_source == PoseSource::kPnp || tag.pose_source == PoseSource::kFused;
  if (is_pnp && pnp.valid && pnp.solutions == 2 && AllFinite(pnp.covariance[0]) && AllFinite(pnp.covariance[1])) {
    const int other = tag.rvec == pnp.rvec[0] && tag.tvec == pnp.tvec[0] ? 1 : 0;
    cv::Matx33d other_to_camera;
    cv::Rodrigues(pnp.rvec[other], other_to_camera);
    m.has_alternative = true;
    m.alternative_position = rotation * pnp.tvec[other] + translation;
    m.alternative_rotation = rotation * other_to_camera;
    m.alternative_covariance = Rotate(pnp.covariance[other], rotation);
  }
  return m;
}

std::vector<TrackMeasurement> MeasurementsInFrame(const std::vector<ArucoTag>& tags, const cv::Matx33d& rotation,
                                                  const cv::Vec3d& translation) {
  std::vector<TrackMeasurement> measurements;
  for (const auto& tag : tags) {
    if (tag.HasPose() && AllFinite(tag.covariance)) measurements.push_back(MeasurementInFrame(tag, rotation, translation));
  }
  return measurements;
}

TagTracker::TagTracker(const TrackerConfig& config) : config_(config) { config_.Validate(); }

void TagTracker::SetConfig(const TrackerConfig& config) {
  config.Validate();
  const bool frame_changes = config.filter != config_.filter;
  config_ = config;
  if (frame_changes) Reset();
}

void TagTracker::Reset() {
  tracks_.clear();
  has_stamp_ = false;
  ++counts_.resets;
}

void TagTracker::Predict(Track& track, double stamp) const {
  const double dt = stamp - track.filter_stamp;
  if (dt <= 0.0) return;  // out of order by less than max_unseen: no time passes
  const double qp = config_.position_noise * config_.position_noise * dt;
  const double qr = config_.rotation_noise * config_.rotation_noise * dt;
  for (int i = 0; i < 3; ++i) {
    track.covariance(i, i) += qp;
    track.covariance(3 + i, 3 + i) += qr;
  }
  track.filter_stamp = stamp;
}

void TagTracker::Start(Track& track, const TrackMeasurement& m, double stamp) const {
  track.position = m.position;
  track.rotation = m.rotation;
  track.covariance = m.covariance;
  track.filter_stamp = stamp;
  track.outliers_in_row = 0;
  track.flips_in_row = 0;
}

void TagTracker::Fuse(Track& track, const TrackMeasurement& m) const {
  const Matx66 gain = track.covariance * (track.covariance + m.covariance).inv(cv::DECOMP_CHOLESKY);
  const Vec6 dx = gain * Innovation(track, m);
  track.position += cv::Vec3d(dx[0], dx[1], dx[2]);
  cv::Matx33d correction;
  cv::Rodrigues(cv::Vec3d(dx[3], dx[4], dx[5]), correction);
  track.rotation = correction * track.rotation;
  // Joseph form: stays symmetric and positive definite with a badly conditioned gain.
  const Matx66 i_kh = Matx66::eye() - gain;
  track.covariance = Symmetric(i_kh * track.covariance * i_kh.t() + gain * m.covariance * gain.t());
}

double TagTracker::Distance(const Track& track, const TrackMeasurement& m) const {
  Matx66 s_inv;
  if (cv::invert(track.covariance + m.covariance, s_inv, cv::DECOMP_CHOLESKY) == 0.0) {
    return std::numeric_limits<double>::infinity();
  }
  const Vec6 y = Innovation(track, m);
  return (y.t() * s_inv * y)(0);
}

void TagTracker::Hit(Track& track, const std::string& camera, double stamp) {
  ++track.hits;
  track.misses = 0;
  // Cameras' frames interleave: one stamped before the track's latest hit must not set it back
  // (max_unseen would then drop the track early).
  track.last_seen = std::max(track.last_seen, stamp);
  if (!Contains(track.cameras, camera)) track.cameras.push_back(camera);
  track.recent_hits.push_back(stamp);
  while (!track.recent_hits.empty() && track.recent_hits.front() < stamp - config_.validation_window) {
    track.recent_hits.pop_front();
  }
  if (!track.validated && static_cast<int>(track.recent_hits.size()) >= config_.validation_hits) {
    track.validated = true;
    track.frames_to_validate = track.frames;
    ++counts_.validated;
  }
}

void TagTracker::Update(const std::string& camera, double stamp, const std::vector<TrackMeasurement>& measurements) {
  if (has_stamp_ && stamp < latest_stamp_ - config_.max_unseen) Reset();
  latest_stamp_ = has_stamp_ ? std::max(latest_stamp_, stamp) : stamp;
  has_stamp_ = true;

  // Which live tracks this frame may update: without a fixed frame a track belongs to one camera.
  const size_t existing = tracks_.size();
  std::vector<bool> mine(existing);
  for (size_t j = 0; j < existing; ++j) mine[j] = config_.filter || tracks_[j].cameras.front() == camera;

  // Pair detections with tracks of their id, nearest first, one to one.
  std::vector<std::tuple<double, size_t, size_t>> pairs;  // distance, measurement, track
  for (size_t i = 0; i < measurements.size(); ++i) {
    for (size_t j = 0; j < existing; ++j) {
      if (!mine[j] || tracks_[j].id != measurements[i].id) continue;
      const TrackMeasurement& m = measurements[i];
      const double d = cv::norm(m.position - tracks_[j].position);
      const double angle = std::min(Angle(m.rotation, tracks_[j].rotation),
                                    m.has_alternative ? Angle(m.alternative_rotation, tracks_[j].rotation) : M_PI);
      // In a moving camera's frame a marker moves with the camera: only its direction stays put enough.
      const bool near = config_.filter ? d <= config_.association_distance
                                       : Bearing(m.position, tracks_[j].position) <= config_.association_angle;
      if (near && angle <= config_.association_angle) pairs.emplace_back(d, i, j);
    }
  }
  std::sort(pairs.begin(), pairs.end());
  std::vector<TrackMeasurement> alternatives(measurements.size());
  for (size_t i = 0; i < measurements.size(); ++i) {
    const TrackMeasurement& m = measurements[i];
    alternatives[i].id = m.id;
    alternatives[i].position = m.alternative_position;
    alternatives[i].rotation = m.alternative_rotation;
    alternatives[i].covariance = m.alternative_covariance;
  }
  std::vector<bool> used(measurements.size(), false);
  std::vector<const TrackMeasurement*> taken(existing, nullptr);
  std::vector<bool> restart(existing, false);
  for (const auto& [distance, i, j] : pairs) {
    if (used[i] || taken[j]) continue;
    used[i] = true;
    taken[j] = &measurements[i];
    if (!config_.filter) continue;
    Track& track = tracks_[j];
    Predict(track, stamp);
    const double primary = Distance(track, measurements[i]);
    const double alternative =
        measurements[i].has_alternative ? Distance(track, alternatives[i]) : std::numeric_limits<double>::infinity();
    if (std::min(primary, alternative) > config_.gate) {
      ++track.outliers;
      ++counts_.outliers;
      if (++track.outliers_in_row < kRestartAfter) taken[j] = nullptr;  // no sighting: the frame counts as a miss
      restart[j] = taken[j] != nullptr;
      continue;
    }
    track.outliers_in_row = 0;
    if (alternative < primary) {
      taken[j] = &alternatives[i];
      ++track.flips;
      ++counts_.flips;
      restart[j] = ++track.flips_in_row >= kRestartAfter;
      if (restart[j]) taken[j] = &measurements[i];
    } else {
      track.flips_in_row = 0;
    }
  }

  for (size_t j = 0; j < existing; ++j) {
    Track& track = tracks_[j];
    const bool seen_by_camera = Contains(track.cameras, camera);
    if (!taken[j] && !seen_by_camera) continue;  // another camera's frame says nothing about this track
    ++track.frames;
    if (!taken[j]) {
      ++track.misses;
      continue;
    }
    if (!config_.filter) {
      Start(track, *taken[j], stamp);  // the last detection is the track's pose
    } else if (restart[j]) {
      Start(track, *taken[j], stamp);
      ++track.restarts;
      ++counts_.restarts;
    } else {
      Fuse(track, *taken[j]);
    }
    Hit(track, camera, stamp);
  }
  for (size_t i = 0; i < measurements.size(); ++i) {
    if (used[i]) continue;
    Track track;
    track.track_id = next_track_id_++;
    track.id = measurements[i].id;
    track.first_seen = stamp;
    track.frames = 1;
    Start(track, measurements[i], stamp);
    Hit(track, camera, stamp);
    tracks_.push_back(std::move(track));
    ++counts_.created;
  }

  const auto gone = [this](const Track& track) {
    return track.misses >= config_.max_misses || latest_stamp_ - track.last_seen > config_.max_unseen;
  };
  const size_t before = tracks_.size();
  tracks_.erase(std::remove_if(tracks_.begin(), tracks_.end(), gone), tracks_.end());
  counts_.dropped += before - tracks_.size();
  for (auto& track : tracks_) {
    track.age = latest_stamp_ - track.first_seen;
    if (config_.filter) Predict(track, latest_stamp_);
  }
}

}  // namespace arucotag

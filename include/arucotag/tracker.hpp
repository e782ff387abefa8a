#pragma once

// Tracks of markers over time: which detections are one physical marker, which are validated (seen
// often enough to be real), and a filtered pose of each in a frame that does not move with the camera.
#include <cstdint>
#include <deque>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include <arucotag/aruco_tag.hpp>

namespace arucotag {

/// Tuning of TagTracker. Times are the stamps' seconds.
struct TrackerConfig {
  /// A track is validated once it has this many hits within validation_window s (1: at its first hit).
  int validation_hits = 3;
  double validation_window = 1.0;  ///< s
  /// A track is dropped after this many consecutive frames of its cameras without a hit ...
  int max_misses = 15;
  /// ... or when it has not been seen for this long (s), whichever comes first.
  double max_unseen = 2.0;
  /// Mahalanobis gate: a detection whose squared distance to its track (6 dof, innovation covariance
  /// = track + detection) exceeds this is an outlier, counted and not fused. 22.46 is the chi-square
  /// 99.9 % quantile for 6 degrees of freedom. Only with `filter`.
  double gate = 22.46;
  /// Random-walk process noise of the constant-position model: how fast the marker (or the fixed
  /// frame's drift, e.g. odometry under the camera) may wander. m/sqrt(s) and rad/sqrt(s).
  double position_noise = 0.005;
  double rotation_noise = 0.01;
  /// A detection farther than this (m) from every track of its id, or turned from each by more than
  /// association_angle (rad; either planar solution counts), starts a new track: the faces of a URC
  /// post share an id, stand 0.1 m apart and face 120 degrees apart. Without `filter` the poses are
  /// in a moving camera's frame, where a marker's position jumps with every turn of the camera: there
  /// the position test is on its direction instead (within association_angle of the track's).
  double association_distance = 0.3;
  double association_angle = 0.785;
  /// true: the measurements are in a fixed frame and each track is a Kalman filter of its marker's
  /// pose, shared by every camera. false: the measurements are in their camera's own (moving) frame,
  /// so tracks are kept per camera, carry the last detection's pose and covariance, and no gate.
  bool filter = true;

  /// Throws arucotag::Error naming the first value out of range (hits < 1, window, T, gate, distance
  /// not > 0, angle not in (0, pi], misses < 1, noise < 0 or any value not finite).
  void Validate() const;
};

/// One detection handed to the tracker: its pose in the tracker's frame (see TrackerConfig::filter).
struct TrackMeasurement {
  int id = -1;
  cv::Vec3d position;                             ///< marker centre (m)
  cv::Matx33d rotation = cv::Matx33d::eye();      ///< marker -> frame rotation
  /// Covariance of (position, rotation) in the convention of PoseCovariance, in this frame.
  PoseCovariance covariance = UnknownCovariance();
  /// The other planar (IPPE) solution, when PnP found two: a small or distant marker's corners often
  /// cannot tell them apart, and a track's history can. Same frame and conventions as above.
  bool has_alternative = false;
  cv::Vec3d alternative_position;
  cv::Matx33d alternative_rotation = cv::Matx33d::eye();
  PoseCovariance alternative_covariance = UnknownCovariance();
};

/// A detection's pose moved into another frame: `rotation` and `translation` map points of the camera
/// frame the tag's pose is in into the target frame (T_target_camera). The covariance turns with the
/// frame (C' = B C B^T, B = diag(R, R)); the translation adds nothing. The other PnP solution, when
/// the pose is one of two, comes along as the alternative. The tag must have a pose.
TrackMeasurement MeasurementInFrame(const ArucoTag& tag, const cv::Matx33d& rotation, const cv::Vec3d& translation);

/// The same for every tag with a pose and a finite covariance (the others cannot be tracked).
std::vector<TrackMeasurement> MeasurementsInFrame(const std::vector<ArucoTag>& tags, const cv::Matx33d& rotation,
                                                  const cv::Vec3d& translation);

/// One physical marker over time.
struct Track {
  std::uint32_t track_id = 0;        ///< unique within a tracker, never reused (a dropped track's successor gets a new one)
  int id = -1;                       ///< marker id
  std::vector<std::string> cameras;  ///< cameras whose detections it holds, in order of first contribution
  bool validated = false;            ///< validation_hits hits within validation_window; stays until dropped
  int hits = 0;                      ///< detections taken (fused) since the track began
  int misses = 0;                    ///< consecutive frames of its cameras without a hit since the last one
  int outliers = 0;                  ///< detections refused by the gate
  int flips = 0;                     ///< detections taken as their other planar solution (a flip undone)
  int restarts = 0;                  ///< times the filter was restarted from a detection it kept refusing
  double first_seen = 0.0;           ///< s, stamp of the first hit
  double last_seen = 0.0;            ///< s, latest stamp of its hits (a camera's older frame does not set it back)
  double age = 0.0;                  ///< s, from first_seen to the tracker's latest stamp
  int frames_to_validate = 0;        ///< frames of its cameras from the first hit to validation (0 until validated)
  cv::Vec3d position;                ///< filtered (or last) marker centre (m)
  cv::Matx33d rotation = cv::Matx33d::eye();  ///< filtered (or last) marker -> frame rotation
  /// Covariance of (position, rotation) as PoseCovariance; with `filter`, predicted to the tracker's latest stamp.
  PoseCovariance covariance = UnknownCovariance();

  std::deque<double> recent_hits;  ///< stamps of the hits within the validation window
  int frames = 0;                  ///< frames of its cameras since the first hit
  int outliers_in_row = 0;         ///< consecutive refused detections
  int flips_in_row = 0;            ///< consecutive detections taken as their alternative
  double filter_stamp = 0.0;       ///< s, the stamp `covariance` was predicted to
};

/// What the tracker did, counted since construction (Reset keeps the counts).
struct TrackerCounts {
  std::size_t created = 0, dropped = 0, validated = 0, outliers = 0, flips = 0, restarts = 0, resets = 0;
};

/// Keeps a track per physical marker (per id, told apart by position) and, with TrackerConfig::filter,
/// filters each track's pose with a constant-position Kalman filter on SE(3): position and a small
/// rotation about the frame's axes (left perturbation, R_true = exp([d]x) R), six states with the
/// detections' 6x6 covariances. Not thread-safe; ROS-free.
class TagTracker {
 public:
  /// Consecutive refused (or flipped) detections after which a track's filter restarts from the
  /// latest one: the detections agree with each other and not with the track, so the track is wrong.
  static constexpr int kRestartAfter = 3;

  /// Throws arucotag::Error on an invalid config (TrackerConfig::Validate).
  explicit TagTracker(const TrackerConfig& config = {});

  /// Takes one processed frame of `camera` (any stable name, e.g. its frame_id) at `stamp` (s) and the
  /// frame's detections. Detections are paired with tracks of the same id (and camera, without
  /// `filter`) nearest first, one detection per track, within association_distance; the rest start
  /// tracks. Paired detections are gated, then fused (or taken); tracks of this camera left without
  /// one count a miss. With `filter`, of a detection's two planar solutions the one nearer the track
  /// (Mahalanobis) is gated; a track that refuses kRestartAfter detections in a row, or takes the
  /// alternative that often (it had started from a flipped pose), restarts from the detection. Then tracks past max_misses or max_unseen are dropped. A stamp more than
  /// max_unseen before the latest one (a bag loop, a clock reset) clears every track first; smaller
  /// steps back are taken as no time passing.
  void Update(const std::string& camera, double stamp, const std::vector<TrackMeasurement>& measurements);

  /// The live tracks, oldest first.
  const std::vector<Track>& Tracks() const { return tracks_; }
  const TrackerCounts& Counts() const { return counts_; }
  const TrackerConfig& Config() const { return config_; }

  /// New tuning for the next Update; the tracks stay (switching `filter` clears them, their poses
  /// would be in the wrong frame). Throws arucotag::Error on an invalid config, keeping the old one.
  void SetConfig(const TrackerConfig& config);
  /// Forgets every track (counted in resets).
  void Reset();

 private:
  void Start(Track& track, const TrackMeasurement& measurement, double stamp) const;
  void Predict(Track& track, double stamp) const;
  double Distance(const Track& track, const TrackMeasurement& measurement) const;
  void Fuse(Track& track, const TrackMeasurement& measurement) const;
  void Hit(Track& track, const std::string& camera, double stamp);

  TrackerConfig config_;
  std::vector<Track> tracks_;
  TrackerCounts counts_;
  std::uint32_t next_track_id_ = 1;
  bool has_stamp_ = false;
  double latest_stamp_ = 0.0;
};

}  // namespace arucotag

// The sample recording's world, ROS-free: a rover drives past a URC post (one id on three faces)
// and a few single markers on a textured Martian-looking plain; light, exposure and motion blur
// change over time. Every frame is a pure function of its time, so frames can be rendered in any
// order, on any thread, and a short excerpt equals the same stretch of the full recording.
#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/core/affine.hpp>

#include <arucotag/sim.hpp>

namespace arucotag::replay {

/// A rigid transform T_a_b: maps points expressed in frame b into frame a.
using Transform = cv::Affine3d;

/// One printed marker standing in the world (frame "odom": x forward at the start, y left, z up).
struct WorldMarker {
  std::string name;  ///< stable label, e.g. "post_a"
  int id = 0;
  double side = 0.15;  ///< m, black square
  Transform pose;      ///< T_odom_marker; marker axes as cv::aruco (x right, y up, z out of the face)
};

/// What a detector should report for one marker in one frame.
struct TruthTag {
  std::string name;
  int id = 0;
  double side = 0.15;
  cv::Vec3d rvec, tvec;  ///< marker -> optical frame
  std::array<cv::Point2f, 4> corners;  ///< px, TL TR BR BL
  cv::Point2f centre;                   ///< px
  double distance = 0;   ///< m
  double yaw = 0;        ///< rad, atan2(x, z)
  double obliquity = 0;  ///< deg between face normal and line of sight
  bool complete = false;  ///< all corners >= 3 px inside the image and the face not hidden
};

/// One rendered frame: what the camera driver publishes and what is true.
struct SampleFrame {
  double time = 0;        ///< s since the start of the scene
  cv::Mat image;          ///< CV_8UC3 BGR
  /// CV_32FC3 organized stereo cloud at 1 / SampleOptions::cloud_factor of the image's width and height
  /// (point (u, v) covers image pixels [f u, f u + f) x [f v, f v + f)), in the body frame (x forward,
  /// z up), NaN holes; empty when Render was asked for no cloud.
  cv::Mat cloud;
  std::vector<TruthTag> truth;  ///< markers facing the camera with their centre in the image
  double brightness = 1, exposure_ms = 0, motion_blur_px = 0;  ///< what the photometry did (for the log)
};

/// Rendering quality knobs; the defaults are what make_sample_bag writes.
struct SampleOptions {
  cv::Size size{1280, 720};
  double hfov_deg = 70.0;
  int supersample = 4;         ///< per axis inside marker boxes; 4 keeps corners well under 0.05 px
  double cloud_holes = 0.25;   ///< fraction of NaN pixels (stereo dropouts), on top of the sky
  /// Stereo depth error of the cloud (range-squared, correlated disparity noise, edge fattening,
  /// featureless holes), at the cloud grid's focal length; the rover's camera is a ZED 2.
  sim::DepthNoise cloud_stereo = sim::DepthNoise::Zed2();
  double cloud_range = 20.0;   ///< m, stereo cut-off: farther points are NaN
  /// Image pixels per cloud point along each axis: a stereo camera computes depth at a reduced
  /// resolution (a ZED's cloud can be a half or a quarter of its image). Each point lies on the ray
  /// through its pixel block's centre at the mean depth of the block.
  int cloud_factor = 2;
};

/// The sample world and its renderer. Construction builds the ground texture (about a second).
class SampleScene {
 public:
  explicit SampleScene(const SampleOptions& options = {});

  /// Camera model (rectified: no distortion) of every frame.
  const sim::Camera& Camera() const { return camera_; }
  const std::vector<WorldMarker>& Markers() const { return markers_; }

  /// T_odom_base at time t (s), including the suspension's pitch, roll and bounce.
  Transform RoverPose(double t) const;
  /// T_base_body: the stereo camera's body frame (x forward, z up) on the mast.
  static Transform MastMount();
  /// T_body_optical: the standard optical axes (x right, y down, z forward) in the body frame.
  static Transform OpticalInBody();
  /// T_odom_optical at time t.
  Transform CameraPose(double t) const;

  /// Truth only (cheap): the markers a frame at time t shows.
  std::vector<TruthTag> Truth(double t) const;
  /// Renders the frame at time t (s), with its stereo cloud unless `with_cloud` is false (the
  /// cloud's holes and noise depend on t only, so skipping it changes nothing else). Deterministic in t.
  SampleFrame Render(double t, bool with_cloud = true) const;
  /// The camera model of the cloud's grid: Camera() scaled down by cloud_factor, with the principal
  /// point moved so that cloud point (u, v) looks through the centre of its image pixel block.
  sim::Camera CloudCamera() const;

 private:
  struct Pole {
    cv::Vec2d axis;  ///< x, y in odom
    double radius, bottom, top;
    cv::Vec3f colour;  ///< BGR
  };
  struct Photometry {
    double brightness, contrast, exposure_ms, noise_sigma, blur_px, blur_angle_deg;
  };

  std::vector<TruthTag> TruthFor(const Transform& odom_optical, const cv::Mat* marker_depth) const;
  std::vector<sim::Marker> MarkersInView(const Transform& odom_optical) const;
  Photometry LightAt(double t, const std::vector<TruthTag>& truth) const;
  void RenderBackdrop(const Transform& odom_optical, cv::Mat& colour, cv::Mat& depth) const;
  void RenderPoles(const Transform& odom_optical, cv::Mat& colour, cv::Mat& depth) const;
  cv::Vec3f SampleGround(double x, double y, double footprint) const;

  SampleOptions options_;
  sim::Camera camera_;
  std::vector<WorldMarker> markers_;
  std::vector<Pole> poles_;
  std::vector<cv::Mat> ground_;  ///< texture pyramid, CV_32FC3, level 0 = kTexel m per texel
  std::vector<cv::Vec3d> path_;  ///< x, y, yaw of the base at kPathStep intervals from t = 0
};

}  // namespace arucotag::replay

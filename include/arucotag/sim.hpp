// ROS-free synthetic scene renderer for tests, bag generation and benchmarks.
// Renders ArUco markers with exact (supersampled, ray-cast) geometry so that a
// detector's corners can be compared against ProjectCorners() to sub-pixel level.
#pragma once

#include <array>
#include <vector>

#include <opencv2/aruco.hpp>
#include <opencv2/core.hpp>

namespace arucotag::sim {

// Pinhole camera with optional OpenCV distortion (k1 k2 p1 p2 [k3 ...], any
// count cv::projectPoints accepts; empty = none), or with fisheye set, an
// equidistant (cv::fisheye) lens: dist = k1 k2 k3 k4 and a ray theta off axis
// lands f * theta * (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
// from the principal point. Pixel centres are at integer coordinates (OpenCV
// convention).
struct Camera {
  cv::Matx33d K;
  std::vector<double> dist;
  cv::Size size;
  bool fisheye = false;
};

// Takes the image size and horizontal field of view in degrees; returns a
// square-pixel camera with the principal point at the image centre
// ((w-1)/2, (h-1)/2) and no distortion.
Camera MakeCamera(cv::Size size, double hfov_deg);

// Takes the image size, horizontal field of view in degrees (below 180) and
// the equidistant coefficients k1..k4; returns a square-pixel fisheye camera
// with the principal point at the image centre whose left and right image
// edges lie hfov_deg / 2 off axis.
Camera MakeFisheyeCamera(cv::Size size, double hfov_deg, const std::vector<double>& k = {0, 0, 0, 0});

// A square marker placed in the camera optical frame (x right, y down, z forward).
// Marker frame = OpenCV aruco convention: origin at the marker centre, x to the
// marker's right, y up, z out of the printed face (towards a viewer).
// Corners in marker frame: TL(-s/2, s/2, 0), TR(s/2, s/2, 0), BR(s/2, -s/2, 0),
// BL(-s/2, -s/2, 0), s = side = the black square's side in metres.
struct Marker {
  int id = 0;
  double side = 0.15;
  cv::Vec3d rvec;  // marker->camera rotation, like cv::solvePnP output
  cv::Vec3d tvec;  // marker centre in the camera frame, metres
};

struct RenderOptions {
  int dictionary = cv::aruco::DICT_4X4_50;  // predefined dictionary enum
  double quiet_zone = 1.0;                  // white margin around the black square, in marker cells
  // Samples per pixel per axis inside marker bounding boxes (n*n per pixel, as
  // a per-pixel-shifted rank-1 lattice: unbiased coverage, no axis-aligned
  // edge quantization; measured edge bias <= 0.003 px at 8).
  int supersample = 8;
  double background_depth = 20.0;   // m, fronto-parallel wall behind everything (depth/cloud)
  bool textured_background = true;  // clutter (blobs/lines/gradients) vs plain grey, seeded
  unsigned seed = 1;
  double brightness = 1.0, contrast = 1.0;  // out = ((v - 128) * contrast + 128) * brightness
  double blur_sigma = 0.0;                  // Gaussian blur sigma, pixels
  double motion_blur_px = 0.0;              // linear motion-blur length, pixels (centred, no shift)
  double motion_blur_angle_deg = 0.0;       // direction of motion blur, 0 = along +x (image right)
  double noise_sigma = 0.0;                 // additive Gaussian pixel noise, grey levels
  bool colour = true;                       // CV_8UC3 BGR output; false -> CV_8UC1
  double black_level = 25.0, white_level = 230.0;  // printed ink / paper grey, pre-lighting
};

// Takes a camera, markers (any pose; behind-camera or out-of-view ones are
// fine), and options; returns the rendered CV_8UC3 (or CV_8UC1) image of
// cam.size. Markers occlude each other by depth and are hidden behind the wall.
// The back of a marker renders as plain paper. If depth is non-null it receives
// a CV_32F image: metres along optical z of the first surface hit by each pixel
// centre's ray (marker incl. quiet zone, else opt.background_depth).
// Deterministic: same inputs give identical bytes.
cv::Mat RenderScene(const Camera& cam, const std::vector<Marker>& markers, const RenderOptions& opt,
                    cv::Mat* depth = nullptr);

// Takes a camera and marker; returns the true image corners TL TR BR BL via
// cv::projectPoints or cv::fisheye::projectPoints (distortion honoured). Assumes the marker is in front.
std::array<cv::Point2f, 4> ProjectCorners(const Camera& cam, const Marker& m);

// Takes a camera and marker; returns the image of the marker centre.
cv::Point2f ProjectCentre(const Camera& cam, const Marker& m);

// Returns the four 3D corners TL TR BR BL of a marker of the given side, in
// the marker frame (same order/convention as cv::aruco).
std::array<cv::Point3d, 4> MarkerCorners3d(double side);

// Stereo depth error as a block-matching camera makes it. Depth comes from disparity,
// z = f B / d, so a disparity error of sigma_d px gives sigma_z = z^2 sigma_d / (f B): the error
// grows with the square of range. Matching windows share pixels, so neighbouring errors are alike
// (patches, not salt); a window straddling a depth edge matches the foreground's texture, so the
// foreground's depth spreads a few pixels past its silhouette (edge fattening); a window on a
// featureless patch matches nothing (a hole). f is the camera's focal length in pixels of the
// depth image (MakeOrganizedCloud takes it from the camera it is given).
struct DepthNoise {
  double baseline = 0.0;         // m between the two imagers; 0 = no stereo model
  double disparity_sigma = 0.0;  // px, per-pixel RMS disparity error (subpixel accuracy)
  double correlation_px = 0.0;   // px, Gaussian sigma of the error's spatial correlation; 0 = white
  double edge_fattening_px = 0.0;  // px the nearer surface's depth bleeds across a depth edge
  double edge_jump_px = 1.0;       // px of disparity step that counts as a depth edge
  // Grey-level standard deviation over a 7x7 window below which stereo finds no match and the pixel
  // is a hole; 0 = off. Acts only when MakeOrganizedCloud is given the image.
  double min_texture = 0.0;

  DepthNoise() = default;
  // Takes the baseline (m), RMS disparity error (px), correlation length (px), edge fattening
  // (px) and texture threshold (grey levels); the edge threshold stays at 1 px of disparity.
  DepthNoise(double baseline_m, double disparity_sigma_px, double correlation_px = 4.0,
             double edge_fattening_px = 2.0, double min_texture = 0.0);

  // Stereolabs ZED 2: 0.12 m baseline, 0.15 px disparity RMS, 5 px correlation, 3 px fattening.
  static DepthNoise Zed2();
  // Intel RealSense D435: 0.050 m baseline, 0.10 px disparity RMS, 3 px correlation, 2 px fattening.
  static DepthNoise D435();

  // Takes a depth z (m) and focal length f (px); returns sigma_z = z^2 sigma_d / (f B) in m
  // (0 without a stereo model).
  double SigmaZ(double z, double focal_px) const;
};

struct CloudOptions {
  double nan_fraction = 0.0;       // fraction of pixels turned into holes
  double depth_noise_sigma = 0.0;  // relative white noise, e.g. 0.005 = 0.5% of depth, along the ray
  unsigned seed = 2;
  bool hole_blobs = true;  // holes mostly as clustered blobs (stereo-like), rest salt
  DepthNoise stereo;       // stereo disparity noise, edge fattening, textureless holes (default none)
};

// Takes a camera, a CV_32F depth image of cam.size (e.g. from RenderScene) and optionally the
// rendered image (any type RenderScene makes, cam.size; only used for opt.stereo.min_texture);
// returns a CV_32FC3 organized cloud of the same size: each pixel is the 3D point (x, y, z) in
// the optical frame on the pixel centre's undistorted ray with z = depth (noise moves it along the
// ray); holes are NaN in all three. Non-finite or non-positive depths also become holes (or, within
// opt.stereo.edge_fattening_px of a valid surface, take its depth). Stereo noise is applied in
// disparity with f = cam.K(0, 0). Deterministic per seed.
cv::Mat MakeOrganizedCloud(const Camera& cam, const cv::Mat& depth, const CloudOptions& opt,
                           const cv::Mat& image = cv::Mat());

// Takes an id, side (m), centre position in the optical frame (m) and Euler
// angles (deg) applied in the marker frame as R = R_facing * Ry(yaw) *
// Rx(pitch) * Rz(roll); returns a marker whose printed face looks straight at
// the camera's image plane (upright, x right, y up in the image) when all
// angles are 0. roll is the in-plane rotation; yaw/pitch tilt it.
// An organized cloud (CV_32FC3, optical frame) of flat markers in front of a wall, for a camera
// with intrinsics K and distortion D (OpenCV order) seeing image_size: each point lies on the ray
// through its pixel centre, on a marker's plane within 0.7 sides of its centre, else on a wall
// `wall_depth` m away. `factor` image pixels per cloud point (a depth camera at a fraction of the
// image's resolution); no noise. For real photos whose marker poses are known.
cv::Mat MarkerPlanesCloud(const cv::Matx33d& K, const std::vector<double>& D, cv::Size image_size, int factor,
                          const std::vector<Marker>& markers, double wall_depth);

Marker FacingCamera(int id, double side, cv::Vec3d position, double yaw_deg = 0.0,
                    double pitch_deg = 0.0, double roll_deg = 0.0);

// Takes an id, side (m), centre position in the optical frame (m), a tilt
// (deg) of the marker normal away from the line of sight, the direction of
// the tilt axis within the marker plane (deg, 0 = marker x axis) and an
// in-plane roll (deg); returns the marker. tilt_deg is exactly the viewing
// angle (normal vs ray to the centre), which is what makes a view "oblique".
// At tilt 0 the marker squarely faces the camera centre, x roughly image right.
Marker FacingRay(int id, double side, cv::Vec3d position, double tilt_deg = 0.0,
                 double tilt_axis_deg = 0.0, double roll_deg = 0.0);

// Takes an RNG, camera, id, side, range interval (m, along z) and a maximum
// viewing angle (deg); returns a randomly posed marker (FacingRay with random
// roll, tilt axis and tilt <= max_tilt_deg) whose projected quad, enlarged
// 1.5x for quiet zone and detector margins, lies inside the image. Markers
// may overlap each other. Falls back to a centred frontal marker after 200
// failed tries.
Marker RandomMarker(cv::RNG& rng, const Camera& cam, int id, double side, double min_range,
                    double max_range, double max_tilt_deg);

}  // namespace arucotag::sim

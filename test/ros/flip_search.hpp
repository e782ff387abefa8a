// Finds frames where PnP on the corners alone picks the mirrored planar pose. Kept apart from the
// rig because the core's ArucoTag and the generated ArucoTag message cannot share a translation unit.
#pragma once

#include <opencv2/core.hpp>

#include <arucotag/sim.hpp>

namespace arucotag::test {

/// Runs the core with its default configuration on `image` (PreprocessFrame, Detect, PnP) and tells
/// whether the marker's PnP pose is more than 10 degrees off the truth while the other IPPE solution
/// is within 2 degrees of it: the case only depth can fix.
bool PnpPicksMirror(const sim::Camera& camera, const sim::Marker& marker, const cv::Mat& image);

}  // namespace arucotag::test

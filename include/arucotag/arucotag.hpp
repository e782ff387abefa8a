#pragma once

// The whole ROS-free core: detection, preprocessing, pose, bundles, drawing, tracking.
#include <arucotag/aruco_tag.hpp>
#include <arucotag/bundle.hpp>
#include <arucotag/detector.hpp>
#include <arucotag/draw.hpp>
#include <arucotag/pose.hpp>
#include <arucotag/preprocess.hpp>
#include <arucotag/refine.hpp>
#include <arucotag/tracker.hpp>

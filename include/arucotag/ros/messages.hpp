#pragma once

// The generated message headers, under names that do not collide with the core.
//
// genmsg puts ArucoTag.msg into `arucotag::ArucoTag`, the name the core's detection struct has kept
// since the seed (include/arucotag/aruco_tag.hpp). The two cannot share a translation unit, so the
// message typedef is renamed `arucotag::ArucoTagMsg` here; `ArucoTag_<>`, `ArucoTagPtr`,
// `ArucoTagConstPtr`, `ArucoTagArray` and the wire name "arucotag/ArucoTag" are untouched. Include
// this header, never <arucotag/ArucoTag.h> directly, in code that also sees the core; it must come
// before any other header that includes the generated ones.
#ifdef ARUCOTAG_MESSAGE_ARUCOTAG_H
#error "include <arucotag/ros/messages.hpp> before any generated arucotag message header"
#endif

#define ArucoTag ArucoTagMsg
#include <arucotag/ArucoTag.h>
#include <arucotag/ArucoTagArray.h>
#undef ArucoTag

#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include <arucotag/aruco_tag.hpp>

namespace arucotag {

/// Where DrawDetections puts one tag's label.
struct LabelPlacement {
  std::string text;  ///< what the label says: "id N", plus " D.DDm" when the tag has a finite distance
  /// The label's background box (px). Inside the image whenever the label fits in it, and clear of
  /// every other label's box while the image has room for all of them.
  cv::Rect box;
  cv::Point text_origin;  ///< baseline start of the text inside `box`, for cv::putText
  /// Whether the label left its default spot (centred just above the tag, or just below when above
  /// would leave the image) to make room; moved labels get a leader line.
  bool moved = false;
  cv::Point2f anchor;      ///< leader line's end on the tag's outline (only meaningful when `moved`)
  cv::Point2f leader_end;  ///< leader line's end on the border of `box` (only meaningful when `moved`)
};

/// Lays out the labels of `tags` for an image of `image_size`; returns one placement per tag, in
/// the order of `tags`. Labels are placed top to bottom (by tag centre), each at the cheapest of its
/// default spot and candidate spots around its tag (above and below slid sideways, beside it, then
/// rings further out, and when none is free of other labels, anywhere in the image); then a few
/// passes move each label to its cheapest spot given all the others. A spot overlapping another
/// label loses to any that does not; beyond that, covering a tag's quad (its own included) or
/// running the leader over another tag costs the image's diagonal, a leader crossing a label or
/// another leader a quarter of it, and then the distance from the default spot counts. So labels
/// never overlap each other while the image has room for all of them, stay inside it whenever a
/// label fits in it, and cover a tag only where no free spot exists. Text size and padding grow with the image
/// (readable from 320x240 to 4K, never smaller than a legible minimum). Deterministic.
/// Throws arucotag::Error on an empty size or a corner that is not finite or over 2^20 px off.
std::vector<LabelPlacement> LayoutLabels(cv::Size image_size, const std::vector<ArucoTag>& tags);

/// Draws each tag onto `image` in place: its outline, a filled square on corner 0 (top-left in the
/// marker's frame, so the marker's rotation is visible), and its label as LayoutLabels places it
/// (its id and, when the tag has a pose, its distance in metres) as light text on a dark box, with a
/// leader line to the tag when the label was moved. Colour images get a green outline, a red
/// corner-0 square and cyan text; grey images get white outlines and text and a black square.
/// Works on 8-bit 1- or 3-channel images. Throws arucotag::Error on an empty image or any other
/// channel count or depth, and on a corner that is not finite or over 2^20 px off (drawing nothing).
void DrawDetections(cv::Mat& image, const std::vector<ArucoTag>& tags);

}  // namespace arucotag

#include <arucotag/ros/parameters.hpp>

#include <cmath>
#include <cstdio>
#include <set>

#include <ros/param.h>

namespace arucotag {

namespace {

using Reconfigure = ArucotagDetectorConfig;

// One live-tunable value: its ROS name, where the core keeps it and where dynamic_reconfigure does.
template <class Core, class T>
struct Field {
  const char* name;
  T Core::*core;
  T Reconfigure::*live;
};

#define ARUCOTAG_FIELD(CORE, NAME) \
  Field<CORE, decltype(CORE::NAME)> { #NAME, &CORE::NAME, &Reconfigure::NAME }

const Field<DetectorConfig, int> kDetectorInts[] = {
    ARUCOTAG_FIELD(DetectorConfig, adaptive_thresh_win_size_min),
    ARUCOTAG_FIELD(DetectorConfig, adaptive_thresh_win_size_max),
    ARUCOTAG_FIELD(DetectorConfig, adaptive_thresh_win_size_step),
    ARUCOTAG_FIELD(DetectorConfig, min_distance_to_border),
    ARUCOTAG_FIELD(DetectorConfig, perspective_remove_pixel_per_cell),
    ARUCOTAG_FIELD(DetectorConfig, corner_refinement_win_size),
    ARUCOTAG_FIELD(DetectorConfig, corner_refinement_max_iterations),
    ARUCOTAG_FIELD(DetectorConfig, full_search_interval),
    ARUCOTAG_FIELD(DetectorConfig, pattern_fit_max_side),
    ARUCOTAG_FIELD(DetectorConfig, pattern_fit_sharp_max_side),
    ARUCOTAG_FIELD(DetectorConfig, pattern_fit_max_markers),
    ARUCOTAG_FIELD(DetectorConfig, threads),
};
const Field<DetectorConfig, double> kDetectorDoubles[] = {
    ARUCOTAG_FIELD(DetectorConfig, adaptive_thresh_constant),
    ARUCOTAG_FIELD(DetectorConfig, min_marker_perimeter_rate),
    ARUCOTAG_FIELD(DetectorConfig, max_marker_perimeter_rate),
    ARUCOTAG_FIELD(DetectorConfig, polygonal_approx_accuracy_rate),
    ARUCOTAG_FIELD(DetectorConfig, min_corner_distance_rate),
    ARUCOTAG_FIELD(DetectorConfig, min_marker_distance_rate),
    ARUCOTAG_FIELD(DetectorConfig, perspective_remove_ignored_margin_per_cell),
    ARUCOTAG_FIELD(DetectorConfig, max_erroneous_bits_in_border_rate),
    ARUCOTAG_FIELD(DetectorConfig, min_otsu_std_dev),
    ARUCOTAG_FIELD(DetectorConfig, error_correction_rate),
    ARUCOTAG_FIELD(DetectorConfig, corner_refinement_min_accuracy),
};
const Field<DetectorConfig, bool> kDetectorBools[] = {
    ARUCOTAG_FIELD(DetectorConfig, detect_inverted_marker),
    ARUCOTAG_FIELD(DetectorConfig, fast_path),
    ARUCOTAG_FIELD(DetectorConfig, tracking),
};
const Field<PreprocessOptions, int> kPreprocessInts[] = {
    ARUCOTAG_FIELD(PreprocessOptions, clahe_tile_grid),
};
const Field<PreprocessOptions, double> kPreprocessDoubles[] = {
    ARUCOTAG_FIELD(PreprocessOptions, clahe_clip_limit),
    ARUCOTAG_FIELD(PreprocessOptions, unsharp_amount),
    ARUCOTAG_FIELD(PreprocessOptions, unsharp_sigma),
};
const Field<PreprocessOptions, bool> kPreprocessBools[] = {
    ARUCOTAG_FIELD(PreprocessOptions, equalize),
};

#undef ARUCOTAG_FIELD

// The tracker's values: ROS names carry a track_ prefix the core's fields do not.
const Field<TrackerConfig, int> kTrackerInts[] = {
    {"track_validation_hits", &TrackerConfig::validation_hits, &Reconfigure::track_validation_hits},
    {"track_max_misses", &TrackerConfig::max_misses, &Reconfigure::track_max_misses},
};
const Field<TrackerConfig, double> kTrackerDoubles[] = {
    {"track_validation_window", &TrackerConfig::validation_window, &Reconfigure::track_validation_window},
    {"track_max_unseen", &TrackerConfig::max_unseen, &Reconfigure::track_max_unseen},
    {"track_gate", &TrackerConfig::gate, &Reconfigure::track_gate},
    {"track_position_noise", &TrackerConfig::position_noise, &Reconfigure::track_position_noise},
    {"track_rotation_noise", &TrackerConfig::rotation_noise, &Reconfigure::track_rotation_noise},
    {"track_association_distance", &TrackerConfig::association_distance, &Reconfigure::track_association_distance},
    {"track_association_angle", &TrackerConfig::association_angle, &Reconfigure::track_association_angle},
};

template <class Visit>
void ForEachTrackField(Visit&& visit) {
  for (const auto& field : kTrackerInts) visit(field);
  for (const auto& field : kTrackerDoubles) visit(field);
}

// Private parameters read outside the tables above.
const char* const kOtherNames[] = {
    "dictionary", "tag_size", "tag_sizes", "allowed_ids", "ignored_ids", "corner_refinement", "marker_border_bits",
    "image_transport", "use_point_cloud", "queue_size", "pose_source", "publish_tf", "output_frame",
    "frame_prefix", "rectified", "corner_noise", "camera_info_max_age", "camera_info_wait", "cloud_max_dt",
    "cloud_cache_size", "depth_noise", "tf_from_validated_tracks", "bundles",
    "diagnostic_period",  // diagnostic_updater's own
};
const char* const kFuserNames[] = {"inputs", "output_frame", "queue_size", "publish_tf", "frame_prefix"};

template <class T>
const char* TypeName();
template <>
const char* TypeName<int>() { return "an integer"; }
template <>
const char* TypeName<double>() { return "a number"; }
template <>
const char* TypeName<bool>() { return "true or false"; }
template <>
const char* TypeName<std::string>() { return "a string"; }
template <>
const char* TypeName<std::vector<int>>() { return "a list of integers"; }
template <>
const char* TypeName<std::vector<std::string>>() { return "a list of strings"; }

// Absent keeps `value`; present with another type throws.
template <class T>
void Get(const ros::NodeHandle& pnh, const std::string& name, T& value) {
  if (pnh.hasParam(name) && !pnh.getParam(name, value)) {
    throw Error("~" + name + " must be " + TypeName<T>());
  }
}

void Require(bool ok, const std::string& name, const std::string& why) {
  if (!ok) throw Error("~" + name + " " + why);
}

// Calls visit(field, core) for every live-tunable field with the struct it belongs to.
template <class Visit>
void ForEachField(DetectorConfig& detector, PreprocessOptions& preprocess, Visit&& visit) {
  const auto each = [&visit](const auto& fields, auto& core) {
    for (const auto& field : fields) visit(field, core);
  };
  each(kDetectorInts, detector);
  each(kDetectorDoubles, detector);
  each(kDetectorBools, detector);
  each(kPreprocessInts, preprocess);
  each(kPreprocessDoubles, preprocess);
  each(kPreprocessBools, preprocess);
}

std::map<int, double> ReadTagSizes(const ros::NodeHandle& pnh) {
  std::map<int, double> sizes;
  XmlRpc::XmlRpcValue value;
  if (!pnh.getParam("tag_sizes", value)) return sizes;
  // XmlRpc structs have string keys; roslaunch even refuses integer yaml keys, so ids come quoted.
  Require(value.getType() == XmlRpc::XmlRpcValue::TypeStruct, "tag_sizes",
          "must be a map from id to side length in m, e.g. {\"3\": 0.2}");
  for (auto& [key, side_value] : value) {
    int id = -1;
    size_t used = 0;
    try {
      id = std::stoi(key, &used);
    } catch (const std::exception&) {
      used = 0;
    }
    Require(used == key.size() && id >= 0, "tag_sizes", "has key '" + key + "', which is not a marker id");
    double side = 0.0;
    if (side_value.getType() == XmlRpc::XmlRpcValue::TypeDouble) {
      side = static_cast<double>(side_value);
    } else if (side_value.getType() == XmlRpc::XmlRpcValue::TypeInt) {
      side = static_cast<int>(side_value);
    } else {
      Require(false, "tag_sizes", "must map id " + key + " to a number (m)");
    }
    Require(std::isfinite(side) && side > 0.0, "tag_sizes", "must map id " + key + " to a side > 0 m");
    sizes[id] = side;
  }
  return sizes;
}

// A rosparam value as JSON, so the core's one bundle parser (BundlesFromText) reads ~bundles as it
// reads the yaml file. Booleans and non-finite numbers become strings: the parser then names them
// as values of the wrong type instead of reading true as 1.
void AppendJson(XmlRpc::XmlRpcValue& value, std::string& out) {
  using XmlRpc::XmlRpcValue;
  const auto quoted = [&out](const std::string& text) {
    out += '"';
    for (const char c : text) {
      if (c == '"' || c == '\\') {
        out += '\\';
        out += c;
      } else if (static_cast<unsigned char>(c) < 0x20) {
        out += ' ';
      } else {
        out += c;
      }
    }
    out += '"';
  };
  switch (value.getType()) {
    case XmlRpcValue::TypeInt:
      out += std::to_string(static_cast<int>(value));
      break;
    case XmlRpcValue::TypeDouble: {
      const double d = static_cast<double>(value);
      if (!std::isfinite(d)) {
        quoted(std::to_string(d));
        break;
      }
      char text[32];
      std::snprintf(text, sizeof(text), "%.17g", d);
      out += text;
      break;
    }
    case XmlRpcValue::TypeBoolean:
      quoted(static_cast<bool>(value) ? "true" : "false");
      break;
    case XmlRpcValue::TypeString:
      quoted(static_cast<std::string>(value));
      break;
    case XmlRpcValue::TypeArray:
      out += '[';
      for (int i = 0; i < value.size(); ++i) {
        if (i > 0) out += ", ";
        AppendJson(value[i], out);
      }
      out += ']';
      break;
    case XmlRpcValue::TypeStruct: {
      out += '{';
      bool first = true;
      for (auto& [key, member] : value) {
        if (!first) out += ", ";
        first = false;
        quoted(key);
        out += ": ";
        AppendJson(member, out);
      }
      out += '}';
      break;
    }
    default:
      throw Error("holds a value that is not a number, string, list or map");
  }
}

std::vector<MarkerBundle> ReadBundles(const ros::NodeHandle& pnh) {
  XmlRpc::XmlRpcValue value;
  if (!pnh.getParam("bundles", value)) return {};
  try {
    std::string json = "{\"bundles\": ";
    AppendJson(value, json);
    json += '}';
    return BundlesFromText(json);
  } catch (const Error& e) {
    throw Error(std::string("~bundles: ") + e.what());
  }
}

void RequireIds(const std::vector<int>& ids, const std::string& name) {
  for (int id : ids) Require(id >= 0, name, "must hold marker ids >= 0, got " + std::to_string(id));
}

// ~track_*, validated.
void ReadTrackParameters(const ros::NodeHandle& pnh, TrackerConfig& tracker) {
  ForEachTrackField([&](const auto& field) { Get(pnh, field.name, tracker.*field.core); });
  try {
    tracker.Validate();
  } catch (const Error& e) {
    throw Error(std::string("~track_* parameters: ") + e.what());
  }
}

// Every private parameter the detector reads but ~track_*.
std::set<std::string> DetectorNames() {
  std::set<std::string> known(std::begin(kOtherNames), std::end(kOtherNames));
  DetectorConfig detector;
  PreprocessOptions preprocess;
  ForEachField(detector, preprocess, [&known](const auto& field, auto&) { known.insert(field.name); });
  return known;
}

// Private parameters on the server that are neither in `known` nor ~track_*.
std::vector<std::string> Unknown(const ros::NodeHandle& pnh, std::set<std::string> known) {
  ForEachTrackField([&known](const auto& field) { known.insert(field.name); });
  std::vector<std::string> names;
  ros::param::getParamNames(names);
  const std::string prefix = pnh.getNamespace() + "/";
  std::set<std::string> unknown;
  for (const auto& name : names) {
    if (name.compare(0, prefix.size(), prefix) != 0) continue;
    const std::string top = name.substr(prefix.size(), name.find('/', prefix.size()) - prefix.size());
    if (!known.count(top)) unknown.insert(top);
  }
  return {unknown.begin(), unknown.end()};
}

}  // namespace

NodeletParameters ReadParameters(const ros::NodeHandle& pnh) {
  NodeletParameters p;
  DetectorConfig& d = p.detector;

  Get(pnh, "dictionary", d.dictionary);
  try {
    DictionaryFromName(d.dictionary);
  } catch (const Error& e) {
    throw Error(std::string("~dictionary: ") + e.what());
  }
  Get(pnh, "tag_size", d.default_side_length);
  Require(std::isfinite(d.default_side_length) && d.default_side_length > 0.0, "tag_size",
          "must be > 0 m, got " + std::to_string(d.default_side_length));
  d.side_lengths = ReadTagSizes(pnh);
  Get(pnh, "allowed_ids", d.allowed_ids);
  RequireIds(d.allowed_ids, "allowed_ids");
  Get(pnh, "ignored_ids", d.ignored_ids);
  RequireIds(d.ignored_ids, "ignored_ids");

  std::string refinement = CornerRefinementName(d.corner_refinement);
  Get(pnh, "corner_refinement", refinement);
  try {
    d.corner_refinement = CornerRefinementFromName(refinement);
  } catch (const Error& e) {
    throw Error(std::string("~corner_refinement: ") + e.what());
  }
  Get(pnh, "marker_border_bits", d.marker_border_bits);
  ForEachField(d, p.preprocess, [&pnh](const auto& field, auto& core) { Get(pnh, field.name, core.*field.core); });
  try {
    Detector check(d);
  } catch (const Error& e) {
    throw Error(std::string("~") + e.what());
  }

  Require(std::isfinite(p.preprocess.clahe_clip_limit) && p.preprocess.clahe_clip_limit > 0.0, "clahe_clip_limit",
          "must be > 0");
  Require(p.preprocess.clahe_tile_grid >= 1, "clahe_tile_grid", "must be >= 1");
  Require(std::isfinite(p.preprocess.unsharp_amount) && p.preprocess.unsharp_amount >= 0.0, "unsharp_amount",
          "must be >= 0");
  Require(std::isfinite(p.preprocess.unsharp_sigma) && p.preprocess.unsharp_sigma > 0.0, "unsharp_sigma",
          "must be > 0 px");

  std::string transport = "auto";
  Get(pnh, "image_transport", transport);
  using Transport = NodeletParameters::Transport;
  if (transport == "auto") {
    p.transport = Transport::kAuto;
  } else if (transport == "raw") {
    p.transport = Transport::kRaw;
  } else if (transport == "compressed") {
    p.transport = Transport::kCompressed;
  } else {
    Require(false, "image_transport",
            "must be auto, raw or compressed (the nodelet decodes compressed jpeg/png itself), got '" + transport +
                "'");
  }

  Get(pnh, "use_point_cloud", p.use_point_cloud);
  Get(pnh, "queue_size", p.queue_size);
  Require(p.queue_size >= 1, "queue_size", "must be >= 1");

  std::string source = "fused";
  Get(pnh, "pose_source", source);
  if (source == "pnp") {
    p.pose_source = PoseSource::kPnp;
  } else if (source == "point_cloud") {
    p.pose_source = PoseSource::kPointCloud;
  } else if (source == "fused") {
    p.pose_source = PoseSource::kFused;
  } else {
    Require(false, "pose_source", "must be pnp, point_cloud or fused, got '" + source + "'");
  }

  Get(pnh, "publish_tf", p.publish_tf);
  Get(pnh, "output_frame", p.output_frame);
  Get(pnh, "frame_prefix", p.frame_prefix);
  Get(pnh, "rectified", p.rectified);
  Get(pnh, "corner_noise", p.corner_noise);
  Require(std::isfinite(p.corner_noise) && p.corner_noise >= 0.0, "corner_noise",
          "must be >= 0 px (the corner error the camera adds: calibration residual, compression, motion blur)");
  const auto seconds = [&pnh](const char* name, double& value) {
    Get(pnh, name, value);
    Require(std::isfinite(value) && value >= 0.0, name, "must be >= 0 s, got " + std::to_string(value));
  };
  seconds("camera_info_max_age", p.camera_info_max_age);
  seconds("camera_info_wait", p.camera_info_wait);
  seconds("cloud_max_dt", p.cloud_max_dt);
  Get(pnh, "depth_noise", p.cloud.depth_noise_per_m2);
  Require(std::isfinite(p.cloud.depth_noise_per_m2) && p.cloud.depth_noise_per_m2 >= 0.0, "depth_noise",
          "must be >= 0 (sigma_z / z^2, 1/m)");
  Get(pnh, "cloud_cache_size", p.cloud_cache_size);
  Require(p.cloud_cache_size >= 1, "cloud_cache_size", "must be >= 1");

  ReadTrackParameters(pnh, p.tracker);
  p.tracker.filter = !p.output_frame.empty();
  Get(pnh, "tf_from_validated_tracks", p.tf_from_validated_tracks);
  p.bundles = ReadBundles(pnh);
  return p;
}

std::vector<std::string> UnknownParameters(const ros::NodeHandle& pnh) { return Unknown(pnh, DetectorNames()); }

FuserParameters ReadFuserParameters(const ros::NodeHandle& pnh) {
  FuserParameters p;
  Get(pnh, "inputs", p.inputs);
  Require(!p.inputs.empty(), "inputs", "must list the tags topics to fuse, e.g. [/front/tags, /rear/tags]");
  const std::set<std::string> distinct(p.inputs.begin(), p.inputs.end());
  Require(distinct.size() == p.inputs.size(), "inputs", "names a topic twice");
  Require(!distinct.count(""), "inputs", "holds an empty topic name");
  Get(pnh, "output_frame", p.fixed_frame);
  Require(!p.fixed_frame.empty(), "output_frame",
          "must name the fixed frame (e.g. odom) every input's detector publishes in (its ~output_frame)");
  Get(pnh, "queue_size", p.queue_size);
  Require(p.queue_size >= 1, "queue_size", "must be >= 1");
  ReadTrackParameters(pnh, p.tracker);
  p.tracker.filter = true;
  Get(pnh, "publish_tf", p.publish_tf);
  Get(pnh, "frame_prefix", p.frame_prefix);
  if (p.frame_prefix.empty()) p.frame_prefix = FuserParameters().frame_prefix;  // as the detector's: "" = default
  Require(p.frame_prefix[0] != '/', "frame_prefix",
          "must be a TF frame prefix without a leading '/' (tf2 refuses those), e.g. fused/aruco_");
  return p;
}

std::vector<std::string> UnknownFuserParameters(const ros::NodeHandle& pnh) {
  // The detector's keys too: one config file (config/urc.yaml) serves the detectors and the fuser.
  std::set<std::string> known = DetectorNames();
  known.insert(std::begin(kFuserNames), std::end(kFuserNames));
  return Unknown(pnh, known);
}

void ApplyReconfigure(const ArucotagDetectorConfig& config, DetectorConfig& detector, PreprocessOptions& preprocess) {
  detector.corner_refinement = CornerRefinementFromName(config.corner_refinement);
  ForEachField(detector, preprocess, [&config](const auto& field, auto& core) { core.*field.core = config.*field.live; });
}

ArucotagDetectorConfig ToReconfigure(DetectorConfig detector, PreprocessOptions preprocess) {
  ArucotagDetectorConfig config = ArucotagDetectorConfig::__getDefault__();
  config.corner_refinement = CornerRefinementName(detector.corner_refinement);
  ForEachField(detector, preprocess, [&config](const auto& field, auto& core) { config.*field.live = core.*field.core; });
  return config;
}

void ApplyTrackReconfigure(const ArucotagDetectorConfig& config, TrackerConfig& tracker, bool& tf_from_validated_tracks) {
  TrackerConfig fresh = tracker;
  ForEachTrackField([&](const auto& field) { fresh.*field.core = config.*field.live; });
  fresh.Validate();
  tracker = fresh;
  tf_from_validated_tracks = config.tf_from_validated_tracks;
}

void TrackToReconfigure(const TrackerConfig& tracker, bool tf_from_validated_tracks, ArucotagDetectorConfig& config) {
  ForEachTrackField([&](const auto& field) { config.*field.live = tracker.*field.core; });
  config.tf_from_validated_tracks = tf_from_validated_tracks;
}

}  // namespace arucotag

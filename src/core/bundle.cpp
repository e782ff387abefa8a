#include <arucotag/bundle.hpp>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <fstream>
#include <map>
#include <set>
#include <sstream>

#include <opencv2/calib3d.hpp>

#include "reprojection.hpp"

namespace arucotag {

namespace {

// Two members with one id closer than this (m) are one member written twice.
constexpr double kSamePlace = 1e-3;
// A rotation matrix whose columns are further than this from orthonormal is not a rotation.
constexpr double kRotationTolerance = 1e-6;
// A detection matches a member when the member's projected corners lie within this RMS distance
// of its corners: the larger of a floor (px) and a share of the detection's side. A hypothesis
// from one face's PnP predicts the other faces a few px off at 15 m, a flipped one tens of px.
constexpr double kMatchFloor = 8.0;
constexpr double kMatchShareOfSide = 0.5;
// A member matches only when its face is turned towards the camera, up to this much past edge-on
// (cosine of the angle between face normal and the ray from the face to the camera; -0.17 =
// 100 degrees): a face 80-90 degrees off may still be detected, and its predicted normal is noisy.
constexpr double kMinFacingCos = -0.17;
// Detection corners the lens model cannot undistort come back this large (cv::fisheye).
constexpr double kMaxNormalized = 1e5;

std::string Where(const MarkerBundle& bundle) { return "bundle '" + bundle.name + "'"; }

std::string Where(const MarkerBundle& bundle, int id) { return Where(bundle) + " member id " + std::to_string(id); }

bool Finite(const cv::Vec3d& v) { return std::isfinite(v[0]) && std::isfinite(v[1]) && std::isfinite(v[2]); }

// ---- parsing ----

double Number(const cv::FileNode& node, const std::string& what) {
  if (!node.isInt() && !node.isReal()) throw Error(what + " must be a number");
  return static_cast<double>(node);
}

cv::Vec3d Triple(const cv::FileNode& node, const std::string& what) {
  if (node.empty() || node.isNone()) return {};
  if (!node.isSeq() || node.size() != 3) throw Error(what + " must be a list of three numbers");
  return {Number(node[0], what), Number(node[1], what), Number(node[2], what)};
}

void RejectUnknownKeys(const cv::FileNode& map, const std::set<std::string>& known, const std::string& what) {
  for (auto it = map.begin(); it != map.end(); ++it) {
    const std::string key = (*it).name();
    if (!known.count(key)) {
      std::string list;
      for (const auto& k : known) list += (list.empty() ? "" : ", ") + k;
      throw Error(what + " has an unknown key '" + key + "' (known: " + list + ")");
    }
  }
}

BundleMember ParseMember(const cv::FileNode& node, const MarkerBundle& bundle, size_t index) {
  const std::string where = Where(bundle) + " member #" + std::to_string(index + 1);
  if (!node.isMap()) throw Error(where + " must be a map with id, size, position and rpy_deg");
  const cv::FileNode id = node["id"];
  if (!id.isInt()) throw Error(where + " needs an integer id");
  BundleMember member;
  member.id = static_cast<int>(id);
  const std::string named = Where(bundle, member.id);
  RejectUnknownKeys(node, {"id", "size", "position", "rpy_deg"}, named);
  if (node["size"].empty()) throw Error(named + " needs a size (m)");
  member.side_length = Number(node["size"], named + " size");
  member.position = Triple(node["position"], named + " position");
  const cv::Vec3d rpy = Triple(node["rpy_deg"], named + " rpy_deg") * (CV_PI / 180.0);
  member.rotation = RotationFromRpy(rpy[0], rpy[1], rpy[2]);
  return member;
}

// ---- estimation ----

// A detection of a member id, in the two coordinate systems the solver and the errors use.
struct Sighting {
  int tag = -1;  // index into the tags given
  int id = -1;
  std::vector<cv::Point2d> image;       // corners, image px
  std::vector<cv::Point2d> normalized;  // the same undistorted (the solver's input)
  double side_px = 0.0;
};

// A bundle pose and the detections it explains.
struct Hypothesis {
  cv::Vec3d rvec, tvec;
  std::vector<std::pair<int, int>> matches;  // (sighting, member), the seed's first
  double sum_sq = std::numeric_limits<double>::infinity();
  cv::Mat jacobian;
  int seed_sighting = -1, seed_member = -1, seed_solution = -1;

  bool Better(const Hypothesis& other) const {
    if (matches.size() != other.matches.size()) return matches.size() > other.matches.size();
    return sum_sq < other.sum_sq;
  }
};

// Bundle -> camera pose of a member seen at (rvec, tvec) (member -> camera).
void BundleFromMember(const BundleMember& member, const cv::Vec3d& rvec, const cv::Vec3d& tvec, cv::Vec3d& bundle_rvec,
                      cv::Vec3d& bundle_tvec) {
  cv::Matx33d r;
  cv::Rodrigues(rvec, r);
  const cv::Matx33d bundle = r * member.rotation.t();
  cv::Rodrigues(bundle, bundle_rvec);
  bundle_tvec = tvec - bundle * member.position;
}

class Solver {
 public:
  Solver(const CameraModel& camera, const MarkerBundle& bundle, const std::vector<Sighting>& sightings)
      : camera_(camera), bundle_(bundle), sightings_(sightings) {
    for (const auto& m : bundle.members) {
      const auto c = m.Corners();
      corners_.emplace_back(c.begin(), c.end());
    }
  }

  // Matches sightings to members at the hypothesis' pose (the seed's pair kept), refines over all
  // of them, matches again from the refined pose (and refines again when that changed the
  // matches). False when a matched corner falls behind the camera.
  bool Complete(Hypothesis& h) const {
    Match(h);
    if (!Refine(h)) return false;
    const auto first = h.matches;
    Match(h);
    return h.matches == first || Refine(h);
  }

  // Fills the hypothesis' error and Jacobian at its pose over its matches; false when a point is
  // behind the camera.
  bool Evaluate(Hypothesis& h) const {
    std::vector<cv::Point3d> object;
    std::vector<cv::Point2d> image;
    Gather(h, object, image, nullptr);
    std::vector<cv::Point2d> projected;
    if (!internal::ProjectWithJacobian(camera_, object, h.rvec, h.tvec, projected, h.jacobian)) return false;
    h.sum_sq = 0.0;
    for (size_t k = 0; k < image.size(); ++k) {
      const cv::Point2d d = projected[k] - image[k];
      h.sum_sq += d.dot(d);
    }
    return std::isfinite(h.sum_sq);
  }

 private:
  void Gather(const Hypothesis& h, std::vector<cv::Point3d>& object, std::vector<cv::Point2d>& image,
              std::vector<cv::Point2d>* normalized) const {
    for (const auto& [s, m] : h.matches) {
      object.insert(object.end(), corners_[m].begin(), corners_[m].end());
      image.insert(image.end(), sightings_[s].image.begin(), sightings_[s].image.end());
      if (normalized) normalized->insert(normalized->end(), sightings_[s].normalized.begin(), sightings_[s].normalized.end());
    }
  }

  // Greedy, nearest first: each sighting to the free member with its id whose face turns to the
  // camera and whose projected corners lie nearest, within the gate.
  void Match(Hypothesis& h) const {
    cv::Matx33d r;
    cv::Rodrigues(h.rvec, r);
    std::vector<std::pair<double, std::pair<int, int>>> pairs;
    for (size_t m = 0; m < bundle_.members.size(); ++m) {
      const BundleMember& member = bundle_.members[m];
      const cv::Vec3d centre = r * member.position + h.tvec;
      const cv::Vec3d normal = r * member.rotation * cv::Vec3d(0, 0, 1);
      if (!(centre[2] > 0.0) || normal.dot(-centre) < kMinFacingCos * cv::norm(centre)) continue;
      std::vector<cv::Point2d> projected;
      cv::Mat unused;
      if (!internal::ProjectWithJacobian(camera_, corners_[m], h.rvec, h.tvec, projected, unused)) continue;
      for (size_t s = 0; s < sightings_.size(); ++s) {
        if (sightings_[s].id != member.id) continue;
        double sum_sq = 0.0;
        for (int k = 0; k < 4; ++k) {
          const cv::Point2d d = projected[k] - sightings_[s].image[k];
          sum_sq += d.dot(d);
        }
        const double rms = std::sqrt(sum_sq / 4.0);
        if (rms <= std::max(kMatchFloor, kMatchShareOfSide * sightings_[s].side_px)) {
          pairs.push_back({rms, {static_cast<int>(s), static_cast<int>(m)}});
        }
      }
    }
    std::sort(pairs.begin(), pairs.end());
    std::vector<char> sighting_used(sightings_.size(), 0), member_used(bundle_.members.size(), 0);
    h.matches.assign(1, {h.seed_sighting, h.seed_member});
    sighting_used[h.seed_sighting] = member_used[h.seed_member] = 1;
    for (const auto& [rms, pair] : pairs) {
      if (sighting_used[pair.first] || member_used[pair.second]) continue;
      sighting_used[pair.first] = member_used[pair.second] = 1;
      h.matches.push_back(pair);
    }
  }

  // Levenberg-Marquardt over every matched corner from the hypothesis' pose; keeps the start when
  // that fits the image better (the solver minimizes in normalized coordinates).
  bool Refine(Hypothesis& h) const {
    if (!Evaluate(h)) return false;
    if (h.matches.size() < 2) return true;  // one member: the IPPE pose is its own minimum
    std::vector<cv::Point3d> object;
    std::vector<cv::Point2d> image, normalized;
    Gather(h, object, image, &normalized);
    Hypothesis refined = h;
    cv::solvePnPRefineLM(object, normalized, cv::Matx33d::eye(), cv::noArray(), refined.rvec, refined.tvec);
    if (Evaluate(refined) && refined.sum_sq < h.sum_sq) h = refined;
    return true;
  }

  const CameraModel& camera_;
  const MarkerBundle& bundle_;
  const std::vector<Sighting>& sightings_;
  std::vector<std::vector<cv::Point3d>> corners_;  // per member, bundle frame
};

}  // namespace

std::array<cv::Point3d, 4> BundleMember::Corners() const {
  const double h = side_length / 2.0;
  const cv::Vec3d local[4] = {{-h, h, 0.0}, {h, h, 0.0}, {h, -h, 0.0}, {-h, -h, 0.0}};
  std::array<cv::Point3d, 4> corners;
  for (int k = 0; k < 4; ++k) corners[k] = cv::Point3d(rotation * local[k] + position);
  return corners;
}

bool MarkerBundle::Contains(int id) const {
  return std::any_of(members.begin(), members.end(), [id](const BundleMember& m) { return m.id == id; });
}

cv::Matx33d RotationFromRpy(double roll, double pitch, double yaw) {
  const double cr = std::cos(roll), sr = std::sin(roll), cp = std::cos(pitch), sp = std::sin(pitch);
  const double cy = std::cos(yaw), sy = std::sin(yaw);
  const cv::Matx33d rx(1, 0, 0, 0, cr, -sr, 0, sr, cr), ry(cp, 0, sp, 0, 1, 0, -sp, 0, cp), rz(cy, -sy, 0, sy, cy, 0, 0, 0, 1);
  return rz * ry * rx;
}

void ValidateBundles(const std::vector<MarkerBundle>& bundles) {
  std::map<int, std::string> owner;  // id -> bundle name
  std::set<std::string> names;
  for (const auto& bundle : bundles) {
    if (bundle.name.empty()) throw Error("a bundle has no name");
    if (!names.insert(bundle.name).second) throw Error("two bundles are named '" + bundle.name + "'");
    if (bundle.frame.empty()) throw Error(Where(bundle) + " has no frame");
    if (bundle.members.empty()) throw Error(Where(bundle) + " has no members");
    for (size_t i = 0; i < bundle.members.size(); ++i) {
      const BundleMember& m = bundle.members[i];
      const std::string where = Where(bundle, m.id);
      if (m.id < 0) throw Error(where + ": ids are >= 0");
      if (!(std::isfinite(m.side_length) && m.side_length > 0.0)) {
        throw Error(where + ": size must be > 0 m, got " + std::to_string(m.side_length));
      }
      if (!Finite(m.position)) throw Error(where + ": position is not finite");
      const cv::Matx33d r = m.rotation;
      if (!cv::checkRange(cv::Mat(r)) || cv::norm(r.t() * r - cv::Matx33d::eye(), cv::NORM_INF) > kRotationTolerance ||
          cv::determinant(r) < 0.0) {
        throw Error(where + ": orientation is not a rotation");
      }
      const auto other = owner.find(m.id);
      if (other != owner.end() && other->second != bundle.name) {
        throw Error(where + ": id " + std::to_string(m.id) + " is also in bundle '" + other->second +
                    "'; a detection must belong to one bundle");
      }
      owner[m.id] = bundle.name;
      for (size_t j = 0; j < i; ++j) {
        if (bundle.members[j].id == m.id && cv::norm(bundle.members[j].position - m.position) <= kSamePlace) {
          throw Error(where + " is listed twice at the same place (" + std::to_string(m.position[0]) + ", " +
                      std::to_string(m.position[1]) + ", " + std::to_string(m.position[2]) + ")");
        }
      }
    }
  }
}

std::vector<MarkerBundle> ParseBundles(const cv::FileNode& node) {
  std::vector<MarkerBundle> bundles;
  if (node.empty() || node.isNone()) return bundles;
  if (!node.isSeq()) throw Error("bundles must be a list of bundles (name, frame, members)");
  for (size_t i = 0; i < node.size(); ++i) {
    const cv::FileNode b = node[static_cast<int>(i)];
    const std::string where = "bundle #" + std::to_string(i + 1);
    if (!b.isMap()) throw Error(where + " must be a map with name, frame and members");
    MarkerBundle bundle;
    if (!b["name"].isString()) throw Error(where + " needs a name (a string)");
    bundle.name = static_cast<std::string>(b["name"]);
    RejectUnknownKeys(b, {"name", "frame", "members"}, Where(bundle));
    if (b["frame"].empty()) {
      bundle.frame = bundle.name;
    } else if (!b["frame"].isString()) {
      throw Error(Where(bundle) + " frame must be a string");
    } else {
      bundle.frame = static_cast<std::string>(b["frame"]);
    }
    const cv::FileNode members = b["members"];
    if (!members.empty() && !members.isSeq()) throw Error(Where(bundle) + " members must be a list");
    for (size_t j = 0; j < members.size(); ++j) bundle.members.push_back(ParseMember(members[static_cast<int>(j)], bundle, j));
    bundles.push_back(bundle);
  }
  ValidateBundles(bundles);
  return bundles;
}

namespace {

// The text without its yaml comments: OpenCV's parser keeps a comment after a plain string value
// as part of the string ("post_1  # front" for `name: post_1  # front`). A comment is a '#' at the
// start of a line or after whitespace, outside quotes.
std::string WithoutComments(const std::string& text) {
  std::istringstream in(text);
  std::string out, line;
  while (std::getline(in, line)) {
    char quote = 0;
    for (size_t i = 0; i < line.size(); ++i) {
      const char c = line[i];
      if (quote) {
        if (c == quote) quote = 0;
      } else if (c == '"' || c == '\'') {
        quote = c;
      } else if (c == '#' && (i == 0 || std::isspace(static_cast<unsigned char>(line[i - 1])))) {
        line.resize(i);
        break;
      }
    }
    line.erase(line.find_last_not_of(" \t\r") + 1);
    out += line + '\n';
  }
  return out;
}

}  // namespace

std::vector<MarkerBundle> BundlesFromText(const std::string& text) {
  const size_t begin = text.find_first_not_of(" \t\r\n");
  std::string document = text;
  if (begin != std::string::npos && text[begin] != '{') document = WithoutComments(text);
  if (begin != std::string::npos && text[begin] != '{' && text.compare(begin, 5, "%YAML") != 0) {
    // OpenCV reads yaml from memory only after a directive.
    document = (text.compare(begin, 3, "---") == 0 ? "%YAML:1.0\n" : "%YAML:1.0\n---\n") + document;
  }
  cv::FileStorage storage;
  try {
    storage.open(document, cv::FileStorage::READ | cv::FileStorage::MEMORY);
  } catch (const cv::Exception& e) {
    throw Error(std::string("bundles: the yaml does not parse: ") + e.what());
  }
  if (!storage.isOpened()) throw Error("bundles: the yaml does not parse");
  return ParseBundles(storage["bundles"]);
}

std::vector<MarkerBundle> LoadBundles(const std::string& path) {
  std::ifstream file(path);
  if (!file) throw Error("bundles: cannot read " + path);
  std::stringstream text;
  text << file.rdbuf();
  try {
    return BundlesFromText(text.str());
  } catch (const Error& e) {
    throw Error(path + ": " + e.what());
  }
}

BundlePose EstimateBundlePose(const CameraModel& camera, const MarkerBundle& bundle, const std::vector<ArucoTag>& tags) {
  camera.Validate();
  BundlePose result;
  result.name = bundle.name;

  std::vector<Sighting> sightings;
  for (size_t t = 0; t < tags.size(); ++t) {
    const ArucoTag& tag = tags[t];
    if (!bundle.Contains(tag.id)) continue;
    Sighting s;
    s.tag = static_cast<int>(t);
    s.id = tag.id;
    for (const auto& c : tag.corners) s.image.emplace_back(c);
    bool usable = true;
    for (const auto& p : s.image) usable = usable && std::isfinite(p.x) && std::isfinite(p.y);
    if (!usable) continue;
    try {
      s.normalized = camera.Normalize(s.image);
    } catch (const cv::Exception& e) {
      throw Error(std::string("EstimateBundlePose: OpenCV rejected the camera: ") + e.what());
    }
    for (const auto& p : s.normalized) {
      usable = usable && std::isfinite(p.x) && std::isfinite(p.y) && std::abs(p.x) < kMaxNormalized &&
               std::abs(p.y) < kMaxNormalized;
    }
    if (!usable) continue;
    for (int k = 0; k < 4; ++k) s.side_px += 0.25 * cv::norm(s.image[(k + 1) % 4] - s.image[k]);
    sightings.push_back(s);
  }
  if (sightings.empty()) return result;

  // Hypotheses: each sighting as each member with its id, from both IPPE solutions at the member's
  // side length (the detector's configured size may differ from the bundle's).
  const Solver solver(camera, bundle, sightings);
  std::vector<Hypothesis> hypotheses;
  std::map<std::pair<int, int>, ArucoTag> seeds;  // (sighting, member) -> the detection's own PnP
  const Hypothesis* best = nullptr;
  for (size_t s = 0; s < sightings.size(); ++s) {
    for (size_t m = 0; m < bundle.members.size(); ++m) {
      const BundleMember& member = bundle.members[m];
      if (member.id != tags[sightings[s].tag].id) continue;
      // A face already matched by a joint hypothesis would seed that same joint minimum again.
      const std::pair<int, int> pair(static_cast<int>(s), static_cast<int>(m));
      if (best && best->matches.size() > 1 &&
          std::find(best->matches.begin(), best->matches.end(), pair) != best->matches.end()) {
        continue;
      }
      ArucoTag seed = tags[sightings[s].tag];
      seed.side_length = member.side_length;
      if (!EstimatePoseFromPNP(camera, seed)) continue;
      for (int solution = 0; solution < seed.pnp.solutions; ++solution) {
        Hypothesis h;
        BundleFromMember(member, seed.pnp.rvec[solution], seed.pnp.tvec[solution], h.rvec, h.tvec);
        h.seed_sighting = static_cast<int>(s);
        h.seed_member = static_cast<int>(m);
        h.seed_solution = solution;
        if (solver.Complete(h)) hypotheses.push_back(h);
      }
      seeds.emplace(pair, seed);
      best = nullptr;  // the vector may have moved
      for (const auto& h : hypotheses) {
        if (!best || h.Better(*best)) best = &h;
      }
    }
  }
  if (!best) return result;
  result.pose_source = PoseSource::kPnp;
  if (best->matches.size() == 1) {
    // One face: the planar ambiguity is the tag's, and so is the cloud's say in it.
    const ArucoTag& seed = seeds.at({best->seed_sighting, best->seed_member});
    if (seed.cloud.valid && seed.cloud.has_normal) {
      const int choice = FusedChoice(seed);
      for (const auto& h : hypotheses) {
        if (h.matches.size() == 1 && h.seed_sighting == best->seed_sighting && h.seed_member == best->seed_member &&
            h.seed_solution == choice) {
          best = &h;
        }
      }
      result.pose_source = PoseSource::kFused;
    }
  }

  Hypothesis chosen = *best;
  std::sort(chosen.matches.begin(), chosen.matches.end(),
            [](const auto& a, const auto& b) { return a.second < b.second; });
  if (!solver.Evaluate(chosen)) return result;
  const int coordinates = chosen.jacobian.rows;
  // The members' corner noise priors pooled: each sighting gives four corners.
  double prior_variance = 0.0;
  for (const auto& [s, m] : chosen.matches) {
    const double prior = internal::CornerSigmaPrior(sightings[s].side_px, tags[sightings[s].tag].pattern_fitted);
    prior_variance += prior * prior / chosen.matches.size();
    result.member_ids.push_back(bundle.members[m].id);
    result.members.push_back(m);
    result.tags.push_back(sightings[s].tag);
  }
  result.valid = true;
  result.rvec = chosen.rvec;
  result.tvec = chosen.tvec;
  result.reprojection_error = std::sqrt(chosen.sum_sq / coordinates);
  result.corner_sigma = internal::PooledCornerSigma(chosen.sum_sq, coordinates - 6.0, std::sqrt(prior_variance),
                                                    camera.corner_noise);
  const auto covariance = [&](const Hypothesis& h) {
    const cv::Mat jtj = h.jacobian.t() * h.jacobian;
    return internal::CovarianceFromNormalMatrix(cv::Matx66d(jtj.ptr<double>()), result.corner_sigma);
  };
  result.covariance = covariance(chosen);
  if (chosen.matches.size() == 1 && result.pose_source == PoseSource::kPnp) {
    // One face and no plane: its other planar solution stays possible, as for the tag (ResolvePose).
    for (const auto& h : hypotheses) {
      if (h.matches.size() != 1 || h.seed_sighting != chosen.seed_sighting || h.seed_member != chosen.seed_member ||
          h.seed_solution == chosen.seed_solution) {
        continue;
      }
      Hypothesis rival = h;
      if (!solver.Evaluate(rival)) break;
      result.covariance = internal::CovarianceWithRival(
          {chosen.rvec, chosen.tvec, result.covariance}, {rival.rvec, rival.tvec, covariance(rival)},
          internal::RivalWeight(chosen.sum_sq, rival.sum_sq, result.corner_sigma));
      break;
    }
  }
  return result;
}

}  // namespace arucotag

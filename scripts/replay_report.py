#!/usr/bin/env python3
"""Replays a recording through launch/replay.launch and scores the detector against its truth.

The recording must carry a truth topic (arucotag/ArucoTagTruth, one per image, same stamp): the
sample that make_sample_bag writes does. Its images are counted on --image-topic (the sample's are
jpeg, sensor_msgs/CompressedImage on <image>/compressed, which launch/replay.launch feeds the
nodelet by default; pass --launch-arg image_transport:=raw and the raw topic for a bag of raw
images). Prints one row per marker -- frames seen / frames visible, distance, yaw and rotation
errors, pose source -- then one row per track the detector kept (its `tracks` topic), saves a few
overlay images, and exits non-zero when a marker misses the thresholds or a track of an id that is
not in the recording was validated. Also imported by the replay rostests (capture and scoring).

    scripts/replay_report.py --bag build/sample/sample.bag --own-master --out output/demo
"""

import argparse
import math
import os
import signal
import socket
import statistics
import struct
import subprocess
import sys
import time
import zlib

import rosbag
import rosgraph
import rospy

from arucotag.msg import ArucoTagArray, ArucoTagTruth, TagTracks
from sensor_msgs.msg import Image

SOURCES = {0: "none", 1: "pnp", 2: "point_cloud", 3: "fused"}
VISIBLE_PX = 20.0  # px (sqrt of the marker's image area): smaller markers are not required
FLIP_DEG = 10.0    # a pose this far off in rotation took the wrong planar solution (or worse)
NEAR_M = 5.0       # m, the near range bin of the rotation gate (far: up to 15 m)


class Thresholds:
    """What a marker must achieve over its visible frames (the foundation issue's accuracy, plus recall)."""

    def __init__(self, min_px=VISIBLE_PX, max_obliquity_deg=70.0, min_recall=0.90, max_distance_error=0.005,
                 max_yaw_error_deg=1.0, min_frames=5, max_rotation_near_deg=1.0, max_rotation_far_deg=3.0,
                 max_flips=0):
        self.min_px = min_px                          # px, sqrt of the marker's image area to count as visible
        self.max_obliquity_deg = max_obliquity_deg    # deg, more oblique views are not required (beyond the core's 60)
        self.min_recall = min_recall                  # share of visible frames with a matching detection
        self.max_distance_error = max_distance_error  # median |distance - true| / true distance
        self.max_yaw_error_deg = max_yaw_error_deg    # median |yaw - true yaw|, deg
        self.min_frames = min_frames                  # markers visible in fewer frames are reported, not judged
        self.max_rotation_near_deg = max_rotation_near_deg  # median rotation error of detections up to 5 m, deg
        self.max_rotation_far_deg = max_rotation_far_deg    # ... of detections 5-15 m away, deg
        self.max_flips = max_flips                    # detections whose rotation is off by more than FLIP_DEG


class Replay:
    """What one replay produced: truth and tag arrays by stamp (the arrays also as raw bytes)."""

    def __init__(self, images):
        self.images = images  # image messages (any transport) on the image topic in the bag
        self.truth = {}       # stamp -> ArucoTagTruth
        self.tags = {}        # stamp -> ArucoTagArray
        self.raw_tags = []    # serialized ArucoTagArray, in arrival order
        self.tracks = []      # TagTracks, in arrival order
        self.raw_tracks = []  # the same serialized
        self.overlays = {}    # stamp -> Image, the few kept
        self.seconds = 0.0    # wall time of the replay


def free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def master_up():
    try:
        rosgraph.Master("/replay_report").getPid()
        return True
    except Exception:  # noqa: BLE001 - any failure means "not reachable"
        return False


def start_private_master(log):
    """A roscore on a free port, so the replay shares no master with anything else on the machine."""
    port = free_port()
    os.environ["ROS_MASTER_URI"] = "http://localhost:%d" % port
    proc = subprocess.Popen(["roscore", "-p", str(port)], stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    deadline = time.time() + 30
    while not master_up():
        if proc.poll() is not None or time.time() > deadline:
            raise RuntimeError("roscore did not start (see %s)" % log.name)
        time.sleep(0.2)
    return proc


def stop(proc, grace=15.0):
    """SIGINT (roslaunch and roscore shut their children down cleanly), then harder."""
    if proc is None or proc.poll() is not None:
        return
    for sig, wait in ((signal.SIGINT, grace), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(wait)
            return
        except subprocess.TimeoutExpired:
            continue


def side_px(tag):
    """sqrt of the quadrilateral's area: the marker's size in the image, foreshortening included."""
    c = tag.corners
    area = 0.0
    for i in range(4):
        area += c[i].x * c[(i + 1) % 4].y - c[(i + 1) % 4].x * c[i].y
    return math.sqrt(abs(area) / 2.0)


IMAGE_TOPIC = "/zed/left/image_rect_color/compressed"  # the sample's images (make_sample_bag)


def bag_images(path, topic):
    """Number of messages on `topic` and the bag's time span, from its index (no decompression).
    Raises when the bag has no such topic: counting zero images would report every frame lost."""
    with rosbag.Bag(path) as bag:
        topics = bag.get_type_and_topic_info().topics
        if topic not in topics:
            raise RuntimeError("%s has no topic %s (it has %s)" % (path, topic, ", ".join(sorted(topics))))
        return bag.get_message_count(topic_filters=[topic]), bag.get_start_time(), bag.get_end_time()


class Recorder:
    """Subscribes to truth, tags and (optionally) the overlay; keeps the best overlay per time slot."""

    def __init__(self, truth_topic, tags_topic, overlay_topic=None, overlay_slots=0, tracks_topic=None):
        self.replay = None
        self.slots = overlay_slots
        self.span = (0.0, 1.0)
        self.best = {}  # slot -> (score, stamp)
        # Tags first: by the time the truth subscriber lets `--wait-for-subscribers` start the bag,
        # the tags connection is up too.
        self.subs = [rospy.Subscriber(tags_topic, rospy.AnyMsg, self.on_tags, queue_size=1000)]
        self.tracks_topic = tracks_topic
        if tracks_topic:
            self.subs.append(rospy.Subscriber(tracks_topic, rospy.AnyMsg, self.on_tracks, queue_size=1000))
        if overlay_topic and overlay_slots > 0:
            self.subs.append(rospy.Subscriber(overlay_topic, Image, self.on_overlay, queue_size=30,
                                              buff_size=2 ** 26))
        self.subs.append(rospy.Subscriber(truth_topic, ArucoTagTruth, self.on_truth, queue_size=1000))

    def on_truth(self, msg):
        if self.replay is not None:
            self.replay.truth[msg.header.stamp] = msg

    def on_tags(self, raw):
        if self.replay is None:
            return
        msg = ArucoTagArray().deserialize(raw._buff)
        self.replay.raw_tags.append(bytes(raw._buff))
        self.replay.tags[msg.header.stamp] = msg

    def on_tracks(self, raw):
        if self.replay is None:
            return
        self.replay.raw_tracks.append(bytes(raw._buff))
        self.replay.tracks.append(TagTracks().deserialize(raw._buff))

    def on_overlay(self, msg):
        replay = self.replay
        truth = replay.truth.get(msg.header.stamp) if replay else None
        if truth is None:
            return
        visible = [t for t, whole in zip(truth.tags, truth.complete) if whole and side_px(t) >= VISIBLE_PX]
        ids = [t.id for t in visible]
        score = len(visible) + 2 * (len(ids) - len(set(ids)))  # favour two faces of one post
        start, end = self.span
        slot = min(self.slots - 1, int((msg.header.stamp.to_sec() - start) / max(end - start, 1e-9) * self.slots))
        if score > 0 and score > self.best.get(slot, (0, None))[0]:
            old = self.best.get(slot, (0, None))[1]
            replay.overlays.pop(old, None)
            self.best[slot] = (score, msg.header.stamp)
            replay.overlays[msg.header.stamp] = msg

    def run(self, bag, rate=1.0, launch_args=(), image_topic=IMAGE_TOPIC, timeout=600.0,
            log=None):
        """Plays `bag` through replay.launch (headless) and collects until every image has its tag
        array (and, with a tracks topic, as many track arrays, or 5 s more), playback has been over
        for a while, or `timeout` s passed. Returns a Replay."""
        images, start, end = bag_images(bag, image_topic)
        self.span = (start, end)
        self.best = {}
        replay = Replay(images)
        self.replay = replay
        cmd = ["roslaunch", "arucotag", "replay.launch", "bag:=" + os.path.abspath(bag), "rate:=%g" % rate,
               "wait_for_subscribers:=true", "rate_control:=true", "quiet:=true"] + list(launch_args)
        began = time.time()
        proc = subprocess.Popen(cmd, stdout=log or subprocess.DEVNULL, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            last_count, last_change, complete = 0, time.time(), None
            while time.time() - began < timeout:
                time.sleep(0.2)
                count = len(replay.tags)
                if count >= images:
                    # The fuser answers each tag array after the detector has published it: the last
                    # track array can still be on its way (a CI run stopped one short, 14 of 15).
                    complete = complete or time.time()
                    if not self.tracks_topic or len(replay.raw_tracks) >= count or time.time() - complete > 5:
                        break
                    continue
                if count != last_count:
                    last_count, last_change = count, time.time()
                # Playback lasts (end - start) / rate; after that, 10 s of silence means frames were lost.
                if time.time() - began > (end - start) / rate + 10 and time.time() - last_change > 10:
                    break
                if proc.poll() is not None:
                    raise RuntimeError("roslaunch replay.launch exited early with code %d" % proc.returncode)
        finally:
            stop(proc)
            self.replay = None
        replay.seconds = time.time() - began
        return replay


def angle_between(q1, q2):
    """deg, rotation angle taking one unit quaternion to the other."""
    dot = abs(q1.x * q2.x + q1.y * q2.y + q1.z * q2.z + q1.w * q2.w)
    return math.degrees(2.0 * math.acos(min(1.0, dot)))


def quaternion_matrix(q):
    """3x3 rotation matrix (rows) of a unit geometry_msgs/Quaternion."""
    x, y, z, w = q.x, q.y, q.z, q.w
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]


def rotation_residual(measured, true):
    """rad, the rotation vector taking the true orientation to the measured one about the frame's fixed
    axes (measured = exp(e) true): the convention of ArucoTag.covariance's rotation block."""
    a, b = quaternion_matrix(measured), quaternion_matrix(true)
    m = [[sum(a[i][k] * b[j][k] for k in range(3)) for j in range(3)] for i in range(3)]  # a b^T
    angle = math.acos(max(-1.0, min(1.0, (m[0][0] + m[1][1] + m[2][2] - 1.0) / 2.0)))
    axis = (m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1])
    scale = angle / (2.0 * math.sin(angle)) if angle > 1e-9 else 0.5
    return [scale * v for v in axis]


def nees(covariance, offset, error):
    """error^T C^-1 error over the 3x3 block of a row-major 6x6 covariance starting at `offset` (0:
    position, 3: rotation); None when the block is not finite or not invertible."""
    c = [[covariance[6 * (offset + i) + offset + j] for j in range(3)] for i in range(3)]
    if not all(math.isfinite(v) for row in c for v in row):
        return None
    cof = [[c[(i + 1) % 3][(j + 1) % 3] * c[(i + 2) % 3][(j + 2) % 3] -
            c[(i + 1) % 3][(j + 2) % 3] * c[(i + 2) % 3][(j + 1) % 3] for j in range(3)] for i in range(3)]
    det = sum(c[0][j] * cof[0][j] for j in range(3))
    if not det > 0.0:
        return None
    # C^-1 = cof^T / det (C symmetric)
    return sum(error[i] * cof[j][i] * error[j] for i in range(3) for j in range(3)) / det


def corner_distance(a, b):
    """px, mean distance between corresponding corners of two tags."""
    return sum(math.hypot(p.x - q.x, p.y - q.y) for p, q in zip(a.corners, b.corners)) / 4.0


def match(truth, tags):
    """Pairs detections with truth of the same id, closest corners first, when the corners are on
    average within a quarter of the marker's size (at least 4 px): the faces of one post share an
    id and can sit a few pixels apart. Returns ({truth index: detection}, [unmatched detections])."""
    candidates = sorted((corner_distance(det, t), d, i) for d, det in enumerate(tags.tags)
                        for i, t in enumerate(truth.tags) if t.id == det.id)
    pairs, used = {}, set()
    for cost, d, i in candidates:
        if i in pairs or d in used or cost > max(4.0, 0.25 * side_px(truth.tags[i])):
            continue
        pairs[i] = tags.tags[d]
        used.add(d)
    return pairs, [det for d, det in enumerate(tags.tags) if d not in used]


class MarkerScore:
    def __init__(self, name, marker_id):
        self.name, self.id = name, marker_id
        self.visible = 0      # whole, facing, >= min_px
        self.seen = 0         # of those, detected
        self.small_seen = 0   # detected while too small or partly outside (not required)
        self.errors = []      # (distance error m, relative, yaw error deg, rotation error deg, true distance m)
        self.nees = []        # (position NEES, rotation NEES or None) of poses that are not flips
        self.sources = {}
        self.failures = []

    def flips(self):
        return sum(1 for e in self.errors if e[3] > FLIP_DEG)

    def mean_nees(self):
        """Mean NEES of position and of rotation (None where nothing counted); 3 is calibrated."""
        t = [n[0] for n in self.nees if n[0] is not None]
        r = [n[1] for n in self.nees if n[1] is not None]
        return (statistics.mean(t) if t else None), (statistics.mean(r) if r else None)


def score(replay, thresholds):
    """Per-marker statistics and the list of threshold failures."""
    markers = {}
    false_positives = []
    missing = []  # truth stamps without a tag array
    for stamp, truth in sorted(replay.truth.items()):
        tags = replay.tags.get(stamp)
        if tags is None:
            missing.append(stamp)
            continue
        if tags.header.frame_id != truth.header.frame_id:
            raise RuntimeError("tags are in frame %s, truth in %s: replay with an empty output_frame"
                               % (tags.header.frame_id, truth.header.frame_id))
        pairs, unmatched = match(truth, tags)
        false_positives += unmatched
        for i, t in enumerate(truth.tags):
            name = truth.names[i]
            m = markers.setdefault(name, MarkerScore(name, t.id))
            visible = (truth.complete[i] and side_px(t) >= thresholds.min_px
                       and truth.obliquity[i] <= thresholds.max_obliquity_deg)
            m.visible += visible
            det = pairs.get(i)
            if det is None:
                continue
            if not visible:
                m.small_seen += 1
                continue
            m.seen += 1
            source = SOURCES.get(det.pose_source, str(det.pose_source))
            m.sources[source] = m.sources.get(source, 0) + 1
            if det.pose_source != 0:
                derr = abs(det.distance - t.distance)
                yaw = math.degrees(abs(math.atan2(math.sin(det.yaw - t.yaw), math.cos(det.yaw - t.yaw))))
                rotation = angle_between(det.pose.orientation, t.pose.orientation)
                m.errors.append((derr, derr / t.distance, yaw, rotation, t.distance))
                if rotation <= FLIP_DEG:  # a flip is `ambiguity`'s to report, not the covariance's
                    p, q = det.pose.position, t.pose.position
                    m.nees.append((nees(det.covariance, 0, (p.x - q.x, p.y - q.y, p.z - q.z)),
                                   nees(det.covariance, 3, rotation_residual(det.pose.orientation, t.pose.orientation))
                                   if det.orientation_measured else None))
    for m in markers.values():
        if m.visible < thresholds.min_frames:
            continue
        recall = m.seen / m.visible
        if recall < thresholds.min_recall:
            m.failures.append("recall %.1f%% < %.0f%%" % (100 * recall, 100 * thresholds.min_recall))
        if not m.errors:
            m.failures.append("no pose")
            continue
        rel = statistics.median(e[1] for e in m.errors)
        yaw = statistics.median(e[2] for e in m.errors)
        if rel > thresholds.max_distance_error:
            m.failures.append("median distance error %.2f%% > %.2f%%" % (100 * rel, 100 * thresholds.max_distance_error))
        if yaw > thresholds.max_yaw_error_deg:
            m.failures.append("median yaw error %.2f deg > %.2f deg" % (yaw, thresholds.max_yaw_error_deg))
        for lo, hi, bound in ((0.0, NEAR_M, thresholds.max_rotation_near_deg),
                              (NEAR_M, 15.0, thresholds.max_rotation_far_deg)):
            rot = [e[3] for e in m.errors if lo < e[4] <= hi]
            if rot and statistics.median(rot) > bound:
                m.failures.append("median rotation error %.2f deg at %g-%g m > %.1f deg"
                                  % (statistics.median(rot), lo, hi, bound))
        if m.flips() > thresholds.max_flips:
            m.failures.append("%d flipped poses (rotation error > %.0f deg) > %d" % (m.flips(), FLIP_DEG,
                                                                                      thresholds.max_flips))
    return markers, false_positives, missing


def format_table(replay, markers, false_positives, missing, thresholds):
    lines = []
    header = ("%-9s %3s %13s %7s %6s  %-17s %-26s %-13s %-21s %-11s %s"
              % ("marker", "id", "seen/visible", "recall", "small", "dist err median", "dist err worst (range)",
                 "yaw err deg", "rot err <5m/>5m", "NEES t / r", "pose source"))
    lines.append(header)
    lines.append("-" * len(header))
    for name in sorted(markers):
        m = markers[name]
        recall = "%6.1f%%" % (100.0 * m.seen / m.visible) if m.visible else "     -"
        if m.errors:
            med = statistics.median(e[0] for e in m.errors)
            rel = statistics.median(e[1] for e in m.errors)
            worst = max(m.errors, key=lambda e: e[0])
            yaw_med = statistics.median(e[2] for e in m.errors)
            yaw_max = max(e[2] for e in m.errors)
            near = [e[3] for e in m.errors if e[4] <= NEAR_M]
            far = [e[3] for e in m.errors if e[4] > NEAR_M]
            dist = "%.3f m %5.2f%%" % (med, 100 * rel)
            dist_worst = "%.3f m %5.2f%% (%4.1f m)" % (worst[0], 100 * worst[1], worst[4])
            yaw = "%.2f / %.2f" % (yaw_med, yaw_max)
            rot = "%s / %s, %d flips" % ("%.1f" % statistics.median(near) if near else "-",
                                          "%.1f" % statistics.median(far) if far else "-", m.flips())
        else:
            dist = dist_worst = yaw = rot = "-"
        nees_t, nees_r = m.mean_nees()
        consistency = "%s / %s" % tuple("%.1f" % v if v is not None else "-" for v in (nees_t, nees_r))
        total = sum(m.sources.values())
        sources = ", ".join("%s %d%%" % (k, round(100.0 * v / total)) for k, v in sorted(m.sources.items())) or "-"
        verdict = "" if m.visible >= thresholds.min_frames else "  (too few visible frames to judge)"
        if m.failures:
            verdict = "  FAIL: " + "; ".join(m.failures)
        lines.append("%-9s %3d %13s %7s %6d  %-17s %-26s %-13s %-21s %-11s %s%s"
                     % (name, m.id, "%d/%d" % (m.seen, m.visible), recall, m.small_seen, dist, dist_worst, yaw, rot,
                        consistency, sources, verdict))
    lines.append("")
    lines.append("visible = whole in the image, >= %.0f px (sqrt of its area), <= %.0f deg off head-on; small = "
                 "detections while not visible (too small, cut off or grazing); yaw err = median / worst; rot err = median "
                 "rotation error (deg) up to 5 m / 5-15 m, flips = rotation error > %.0f deg; NEES t / r = mean "
                 "normalised estimation error squared of position / rotation against the pose's own covariance (3 "
                 "is calibrated; flips left out); errors over visible frames"
                 % (thresholds.min_px, thresholds.max_obliquity_deg, FLIP_DEG))
    lines.append("frames: %d images in the bag, %d truth, %d tag arrays received, %d truth frames without tags; "
                 "%d detections matching no marker (%s); replay took %.0f s"
                 % (replay.images, len(replay.truth), len(replay.tags), len(missing), len(false_positives),
                    ", ".join(sorted(set("id %d" % d.id for d in false_positives))) or "none", replay.seconds))
    return "\n".join(lines)


class TrackSummary:
    """One track over a replay: its last state and when it was validated."""

    def __init__(self, track, index):
        self.first = index       # index of the first tracks message holding it
        self.validated_at = None  # index of the first one where it was validated
        self.last = track
        self.last_index = index

    def frames_to_validate(self):
        return None if self.validated_at is None else self.validated_at - self.first + 1


def summarize_tracks(replay):
    """{track_id: TrackSummary} over every tracks message of the replay, in arrival order."""
    tracks = {}
    for index, msg in enumerate(replay.tracks):
        for track in msg.tracks:
            summary = tracks.setdefault(track.track_id, TrackSummary(track, index))
            summary.last, summary.last_index = track, index
            if track.validated and summary.validated_at is None:
                summary.validated_at = index
    return tracks


def false_tracks(replay, tracks):
    """Validated tracks whose id no truth message of the replay holds."""
    ids = {t.id for truth in replay.truth.values() for t in truth.tags}
    return [s for s in tracks.values() if s.validated_at is not None and s.last.id not in ids]


def format_track_table(replay, tracks):
    frame = replay.tracks[-1].header.frame_id if replay.tracks else "-"
    header = ("%5s %3s %-9s %5s %6s %8s %6s %7s %-9s %-26s %-11s %s"
              % ("track", "id", "validated", "hits", "misses", "outliers", "age s", "to val", "last seen",
                 "position (m, %s)" % frame, "sigma xyz mm", "pose"))
    lines = [header, "-" * len(header)]
    start = min(replay.truth).to_sec() if replay.truth else 0.0
    for track_id in sorted(tracks):
        s = tracks[track_id]
        t = s.last
        p = t.pose.pose.position
        sigma = "/".join("%.0f" % (1e3 * math.sqrt(max(0.0, t.pose.covariance[7 * i]))) for i in range(3))
        validated = "yes" if t.validated else ("was" if s.validated_at is not None else "no")
        gone = "" if s.last_index == len(replay.tracks) - 1 else " (dropped)"
        lines.append("%5d %3d %-9s %5d %6d %8d %6.2f %7s %8.2fs %-26s %-11s %s%s"
                     % (track_id, t.id, validated, t.hits, t.misses, t.outliers, t.age,
                        "-" if s.frames_to_validate() is None else "%d fr" % s.frames_to_validate(),
                        t.last_seen.to_sec() - start, "%7.3f %7.3f %7.3f" % (p.x, p.y, p.z), sigma,
                        "filtered" if t.filtered else "last detection", gone))
    validated = [s for s in tracks.values() if s.validated_at is not None]
    latencies = sorted(s.frames_to_validate() for s in validated)
    lines.append("")
    lines.append("tracks: %d, validated %d (after %s frames), false tracks (validated, id not in the recording) %d; "
                 "to val = frames from the first detection to validation; without output_frame the poses are the "
                 "last detection's, in the camera frame"
                 % (len(tracks), len(validated),
                    "-" if not latencies else "%d-%d" % (latencies[0], latencies[-1]),
                    len(false_tracks(replay, tracks))))
    return "\n".join(lines)


def write_png(path, image):
    """A bgr8/rgb8/mono8 sensor_msgs/Image as a PNG, without OpenCV or numpy."""
    w, h, step = image.width, image.height, image.step
    data = bytes(image.data)
    if image.encoding in ("bgr8", "rgb8"):
        colour, rows = 2, []
        for v in range(h):
            row = data[v * step:v * step + 3 * w]
            if image.encoding == "bgr8":
                rgb = bytearray(len(row))
                rgb[0::3], rgb[1::3], rgb[2::3] = row[2::3], row[1::3], row[0::3]
                row = bytes(rgb)
            rows.append(b"\x00" + row)
    elif image.encoding == "mono8":
        colour, rows = 0, [b"\x00" + data[v * step:v * step + w] for v in range(h)]
    else:
        raise ValueError("cannot write %s images" % image.encoding)

    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))
                + chunk(b"IDAT", zlib.compress(b"".join(rows), 6)) + chunk(b"IEND", b""))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bag", required=True, help="recording with a truth topic (make_sample_bag)")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1)")
    parser.add_argument("--out", help="folder for overlay PNGs (none when omitted)")
    parser.add_argument("--overlays", type=int, default=4, help="how many overlay PNGs, spread over the bag")
    parser.add_argument("--own-master", action="store_true", help="start a private roscore on a free port")
    parser.add_argument("--launch-arg", action="append", default=[], metavar="NAME:=VALUE",
                        help="extra replay.launch argument (repeatable)")
    parser.add_argument("--tags-topic", default="/zed/tags")
    parser.add_argument("--tracks-topic", default="/zed/tracks")
    parser.add_argument("--truth-topic", default="/truth/tags")
    parser.add_argument("--overlay-topic", default="/zed/overlay")
    parser.add_argument("--image-topic", default=IMAGE_TOPIC,
                        help="topic whose messages are the frames to expect (default: the sample's jpeg images)")
    parser.add_argument("--log", help="file for roslaunch's output (default: <ROS_LOG_DIR or /tmp>/replay_report.log)")
    parser.add_argument("--timeout", type=float, default=600.0, help="s before giving up on the replay")
    t = Thresholds()
    parser.add_argument("--min-px", type=float, default=t.min_px)
    parser.add_argument("--max-obliquity", type=float, default=t.max_obliquity_deg)
    parser.add_argument("--min-recall", type=float, default=t.min_recall)
    parser.add_argument("--max-distance-error", type=float, default=t.max_distance_error,
                        help="median |distance error| / distance (default 0.005)")
    parser.add_argument("--max-yaw-error", type=float, default=t.max_yaw_error_deg, help="deg, median")
    parser.add_argument("--min-frames", type=int, default=t.min_frames)
    args = parser.parse_args()
    thresholds = Thresholds(args.min_px, args.max_obliquity, args.min_recall, args.max_distance_error,
                            args.max_yaw_error, args.min_frames)

    log_path = args.log or os.path.join(os.environ.get("ROS_LOG_DIR", "/tmp"), "replay_report.log")
    os.makedirs(os.path.dirname(os.path.abspath(log_path)), exist_ok=True)
    master = None
    with open(log_path, "w") as log:
        try:
            if args.own_master:
                master = start_private_master(log)
            elif not master_up():
                raise RuntimeError("no ROS master at %s (start roscore or pass --own-master)"
                                   % os.environ.get("ROS_MASTER_URI"))
            rospy.init_node("replay_report", anonymous=True, disable_signals=True)
            recorder = Recorder(args.truth_topic, args.tags_topic, args.overlay_topic if args.out else None,
                                args.overlays, args.tracks_topic)
            replay = recorder.run(args.bag, args.rate, args.launch_arg, args.image_topic, args.timeout, log)
        finally:
            if not rospy.is_shutdown():
                rospy.signal_shutdown("done")
            stop(master)

    markers, false_positives, missing = score(replay, thresholds)
    print(format_table(replay, markers, false_positives, missing, thresholds))
    tracks = summarize_tracks(replay)
    print()
    print(format_track_table(replay, tracks))
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        start = min(replay.truth) if replay.truth else None
        for stamp, image in sorted(replay.overlays.items()):
            path = os.path.join(args.out, "overlay_%05.2fs.png" % (stamp - start).to_sec())
            write_png(path, image)
            print("overlay: %s" % path)
    failed = [m for m in markers.values() if m.failures]
    judged = [m for m in markers.values() if m.visible >= thresholds.min_frames]
    if not replay.tags:
        print("FAIL: no tag arrays received (roslaunch output: %s)" % log_path)
        return 1
    if not judged:
        print("FAIL: no marker visible in %d frames or more" % thresholds.min_frames)
        return 1
    if failed:
        print("FAIL: %d of %d judged markers below the thresholds" % (len(failed), len(judged)))
        return 1
    if not replay.tracks:
        print("FAIL: no tracks received on %s" % args.tracks_topic)
        return 1
    if false_tracks(replay, tracks):
        print("FAIL: validated tracks of ids not in the recording: %s"
              % ", ".join("%d (id %d)" % (s.last.track_id, s.last.id) for s in false_tracks(replay, tracks)))
        return 1
    print("PASS: %d markers judged; recall >= %.0f%%, median distance error <= %.2f%% of range, median yaw error "
          "<= %.2f deg, median rotation error <= %.1f deg to 5 m and <= %.1f deg to 15 m, flipped poses <= %d"
          % (len(judged), 100 * thresholds.min_recall, 100 * thresholds.max_distance_error,
             thresholds.max_yaw_error_deg, thresholds.max_rotation_near_deg, thresholds.max_rotation_far_deg,
             thresholds.max_flips))
    return 0


if __name__ == "__main__":
    sys.exit(main())

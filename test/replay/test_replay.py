#!/usr/bin/env python3
"""Checks the short sample recording is recorded like a field bag (jpeg images only, camera_info on
its own timer, a half-resolution cloud for every third image, ahead of it in bag time), replays it
through launch/replay.launch and checks the detector's tags against the recording's truth (recall,
distance and yaw error, both faces of the post), then replays it again and checks the tag and track
messages are identical, stamps included; then twice more with output_frame odom: validated tracks
with filtered poses at the recording's true marker poses, identical over the two replays."""

import argparse
import math
import os
import struct
import sys
import unittest

import rosbag
import rospy
import rostest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "scripts"))
import replay_report  # noqa: E402

# The rover's preset (config/urc.yaml), as `make demo` runs it.
LAUNCH_ARGS = []
BAG = None


IMAGE = "/zed/left/image_rect_color/compressed"
INFO = "/zed/left/camera_info"
CLOUD = "/zed/point_cloud/cloud_registered"
RATE = 5.0  # Hz, the excerpt's image rate (cmake/replay.cmake)


def jpeg_size(data):
    """(width, height, components) from a baseline or progressive JPEG's frame header."""
    data = bytes(data)
    assert data[:2] == b"\xff\xd8" and data[-2:] == b"\xff\xd9", "not a complete JPEG"
    i = 2
    while i < len(data):
        marker, length = data[i + 1], struct.unpack(">H", data[i + 2:i + 4])[0]
        if marker in (0xC0, 0xC1, 0xC2):
            height, width, components = struct.unpack(">HHB", data[i + 5:i + 10])
            return width, height, components
        i += 2 + length
    raise AssertionError("no frame header")


def first_difference(a, b, path="tracks", tolerance=0.0):
    """Where two (deserialized) messages or lists of them first differ, with both values; floats
    count as equal within `tolerance` relative to their size (at least 1)."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return "%s: %d against %d elements" % (path, len(a), len(b))
        for i, (x, y) in enumerate(zip(a, b)):
            found = first_difference(x, y, "%s[%d]" % (path, i), tolerance)
            if found:
                return found
        return ""
    if hasattr(a, "__slots__") and type(a) is type(b):
        for slot in a.__slots__:
            found = first_difference(getattr(a, slot), getattr(b, slot), path + "." + slot, tolerance)
            if found:
                return found
        return ""
    if isinstance(a, float) and isinstance(b, float):
        same = (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tolerance * max(1.0, abs(a), abs(b))
    else:
        same = a == b
    return "" if same else "%s: %r against %r" % (path, a, b)


class RecordingTest(unittest.TestCase):
    """What is in the bag, read back with rosbag (no replay)."""

    @classmethod
    def setUpClass(cls):
        cls.messages = {}  # topic -> [(bag time, message)]
        with rosbag.Bag(BAG) as bag:
            cls.types = {t: info.msg_type for t, info in bag.get_type_and_topic_info().topics.items()}
            cls.order = []  # (topic, stamp) in bag order
            for topic, msg, t in bag.read_messages():
                cls.messages.setdefault(topic, []).append((t, msg))
                if topic in (IMAGE, CLOUD):
                    cls.order.append((topic, msg.header.stamp))
        cls.image_stamps = [m.header.stamp for _, m in cls.messages[IMAGE]]

    def test_images_are_jpeg_only(self):
        self.assertNotIn("sensor_msgs/Image", self.types.values())
        self.assertEqual(self.types[IMAGE], "sensor_msgs/CompressedImage")
        self.assertEqual(len(self.messages[IMAGE]), 15)
        for t, msg in self.messages[IMAGE]:
            self.assertEqual(msg.format, "bgr8; jpeg compressed bgr8")
            self.assertEqual(msg.header.frame_id, "zed_left_camera_optical_frame")
            self.assertEqual(t, msg.header.stamp)
            self.assertEqual(jpeg_size(msg.data), (1280, 720, 3))
            self.assertLess(len(msg.data), 200000)

    def test_camera_info_has_its_own_timer(self):
        infos = [m for _, m in self.messages[INFO]]
        stamps = [m.header.stamp.to_sec() for m in infos]
        images = [s.to_sec() for s in self.image_stamps]
        # 2 Hz, never at an image's stamp, the first one before the first image.
        for a, b in zip(stamps, stamps[1:]):
            self.assertAlmostEqual(b - a, 0.5, places=6)
        self.assertLess(stamps[0], images[0])
        self.assertGreater(stamps[-1], images[-1] - 0.5)
        for image in images:
            self.assertGreater(min(abs(image - s) for s in stamps), 1e-3)
            age = image - max(s for s in stamps if s <= image)
            self.assertTrue(0.0 < age < 0.5, age)
        self.assertEqual((infos[0].width, infos[0].height), (1280, 720))

    def test_one_cloud_for_every_third_image_ahead_of_it(self):
        clouds = self.messages[CLOUD]
        # The excerpt's frames are 40-54 on the recording's 5 Hz grid: 42, 45, 48, 51 and 54 have a cloud.
        self.assertEqual([m.header.stamp for _, m in clouds], self.image_stamps[2::3])
        for t, msg in clouds:
            # 2.5 image periods ahead, so it is delivered before the image one period before its own.
            self.assertAlmostEqual((msg.header.stamp - t).to_sec(), 2.5 / RATE, places=6)
            position = self.order.index((CLOUD, msg.header.stamp))
            earlier_images = [stamp for topic, stamp in self.order[position:] if topic == IMAGE][:2]
            self.assertLess(earlier_images[0], msg.header.stamp)
            self.assertLess(earlier_images[1], msg.header.stamp)
            self.assertEqual((msg.width, msg.height), (640, 360))
            self.assertEqual((msg.point_step, msg.row_step, msg.is_bigendian), (16, 16 * 640, False))
            self.assertEqual([(f.name, f.offset, f.datatype, f.count) for f in msg.fields],
                             [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)])
            self.assertEqual(len(msg.data), 16 * 640 * 360)
            self.assertEqual(msg.header.frame_id, "zed_left_camera_frame")

    def test_cloud_points_lie_on_their_pixel_blocks_and_markers(self):
        k = self.messages[INFO][0][1].K
        fx, cx, fy, cy = k[0], k[2], k[4], k[5]
        truth = {m.header.stamp: m for _, m in self.messages["/truth/tags"]}
        checked = 0
        for _, cloud in self.messages[CLOUD]:
            data = bytes(cloud.data)
            valid, worst = 0, 0.0
            for v in range(0, 360, 7):
                for u in range(0, 640, 5):
                    x, y, z, pad = struct.unpack_from("<3fI", data, 16 * (v * 640 + u))
                    self.assertEqual(pad, 0)
                    if math.isnan(x):
                        continue
                    valid += 1
                    # Body frame (x forward, y left, z up) to optical (x right, y down, z forward); the
                    # point must be on the ray through the centre of image pixels 2u..2u+1, 2v..2v+1.
                    ox, oy, oz = -y, -z, x
                    worst = max(worst, abs(fx * ox / oz + cx - (2 * u + 0.5)), abs(fy * oy / oz + cy - (2 * v + 0.5)))
            self.assertGreater(valid, 1000)
            self.assertLess(worst, 0.01)
            # Depth at each whole marker's centre (nearest valid point in the 3x3 cells around the one
            # its centre pixel maps to; none when a dropout covers them all) against the truth.
            for tag, whole in zip(truth[cloud.header.stamp].tags, truth[cloud.header.stamp].complete):
                if not whole:
                    continue
                cu, cv = int(round(tag.center.x)) // 2, int(round(tag.center.y)) // 2
                near = []
                for dv in (-1, 0, 1):
                    for du in (-1, 0, 1):
                        if 0 <= cu + du < 640 and 0 <= cv + dv < 360:
                            x = struct.unpack_from("<f", data, 16 * ((cv + dv) * 640 + cu + du))[0]
                            if not math.isnan(x):
                                near.append((abs(du) + abs(dv), x))
                if not near:
                    continue
                depth = min(near)[1]
                # The recording's stereo model (sim::DepthNoise::Zed2: 0.12 m baseline, 0.15 px of
                # disparity noise on the half-resolution grid, f = fx / 2) gives sigma_z = z^2 0.15 / (f B):
                # 2 % of range, or 4 sigma where that is more (beyond about 3 m).
                z = tag.pose.position.z
                self.assertLess(abs(depth - z), max(0.02 * z, 4 * z * z * 0.15 / (fx / 2 * 0.12)), z)
                checked += 1
        self.assertGreaterEqual(checked, 5)


class ReplayTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("test_replay", anonymous=True)
        cls.recorder = replay_report.Recorder("/truth/tags", "/zed/tags", tracks_topic="/zed/tracks")
        cls.first = cls.recorder.run(BAG, launch_args=LAUNCH_ARGS, timeout=120)
        cls.thresholds = replay_report.Thresholds(min_frames=3)
        cls.markers, cls.false_positives, cls.missing = replay_report.score(cls.first, cls.thresholds)
        print(replay_report.format_table(cls.first, cls.markers, cls.false_positives, cls.missing, cls.thresholds))

    def test_every_frame_has_a_tag_array(self):
        self.assertEqual(self.first.images, 15)
        self.assertEqual(len(self.first.truth), 15)
        self.assertEqual(sorted(self.first.tags), sorted(self.first.truth))

    def test_recall_and_pose_error_against_truth(self):
        # The excerpt (8-10.8 s) closes in on the post from 3.2 to 2 m; stake_3 is 7-8 m away.
        post_a, post_c, stake_3 = (self.markers[n] for n in ("post_a", "post_c", "stake_3"))
        self.assertEqual((post_a.id, post_c.id, stake_3.id), (1, 1, 3))
        self.assertGreaterEqual(post_a.visible, 12)
        self.assertGreaterEqual(post_c.visible, 4)
        self.assertGreaterEqual(stake_3.visible, 4)
        # Median / worst relative distance error: the foundation's 0.5 % for the post at 2-3 m; stake_3
        # is only 20-22 px wide at 7-8 m, where 0.1 px of corner noise is already 0.5 %.
        for m, median_limit, worst_limit in ((post_a, 0.005, 0.02), (post_c, 0.005, 0.02), (stake_3, 0.01, 0.03)):
            self.assertGreaterEqual(m.seen / m.visible, 0.9, m.name)
            errors = sorted(e[1] for e in m.errors)
            yaws = sorted(e[2] for e in m.errors)
            self.assertLessEqual(errors[len(errors) // 2], median_limit, "%s median distance error" % m.name)
            self.assertLessEqual(max(errors), worst_limit, "%s worst distance error" % m.name)
            self.assertLessEqual(yaws[len(yaws) // 2], 1.0, "%s median yaw error (deg)" % m.name)
            # Fused on the images that have a cloud close enough in stamp, PnP on the others.
            self.assertTrue(set(m.sources) <= {"fused", "pnp"}, m.sources)
        # Rotation: the gates (1 deg to 5 m, 3 deg beyond) and no flipped pose.
        for m, limit in ((post_a, 1.0), (post_c, 1.0), (stake_3, 3.0)):
            rotations = sorted(e[3] for e in m.errors)
            self.assertLessEqual(rotations[len(rotations) // 2], limit, "%s median rotation error (deg)" % m.name)
            self.assertEqual(m.flips(), 0, "%s flipped poses" % m.name)
        # Close to the post the distance is within a centimetre.
        self.assertLessEqual(max(e[0] for e in post_a.errors), 0.02)
        self.assertEqual(self.false_positives, [])

    def test_pose_covariance_holds_the_errors(self):
        # Mean NEES of each pose against the truth (flips left out; 3 is calibrated). The recording's
        # moving camera (motion blur up to 2.6 px, noise, JPEG) moves corners 0.03-0.07 px more than
        # the still renders the covariance was calibrated on: ~corner_noise (0.05 px) carries it.
        # Measured: positions 0.9-2.5, rotations 1.6-2.7 for the post's faces and 14.7 for the 7 m stake
        # (17-22 px: not calibrated yet); with ~corner_noise 0 positions 7.5-14.6, rotations 10-27 and 103.
        for name, rotation_limit in (("post_a", 6.0), ("post_c", 6.0), ("stake_3", 20.0)):
            nees_t, nees_r = self.markers[name].mean_nees()
            self.assertGreaterEqual(len(self.markers[name].nees), 4, name)
            self.assertLessEqual(nees_t, 6.0, "%s position NEES" % name)
            self.assertGreaterEqual(nees_t, 0.2, "%s position NEES: the covariance is not uselessly wide" % name)
            self.assertLessEqual(nees_r, rotation_limit, "%s rotation NEES" % name)

    def test_both_post_faces_reported_in_one_frame(self):
        both = 0
        for stamp, truth in self.first.truth.items():
            pairs, _ = replay_report.match(truth, self.first.tags[stamp])
            names = {truth.names[i] for i in pairs}
            both += {"post_a", "post_c"} <= names
        self.assertGreaterEqual(both, 4)

    def test_second_replay_gives_identical_tag_messages(self):
        second = self.recorder.run(BAG, launch_args=LAUNCH_ARGS, timeout=120)
        self.assertEqual(len(second.raw_tags), len(self.first.raw_tags))
        for i, (a, b) in enumerate(zip(self.first.raw_tags, second.raw_tags)):
            self.assertEqual(a, b, "tag array %d differs between replays" % i)
        self.assertEqual(len(second.raw_tracks), 15)
        self.assertEqual(second.raw_tracks, self.first.raw_tracks)

    def test_tracks_in_odom_are_validated_at_the_true_poses_and_replay_identically(self):
        # Where the recording put each marker in odom (its latched truth_<name> frames).
        truth = {}
        with rosbag.Bag(BAG) as bag:
            for _, msg, _ in bag.read_messages(topics=["/tf_static"]):
                for t in msg.transforms:
                    if t.child_frame_id.startswith("truth_"):
                        truth[t.child_frame_id[len("truth_"):]] = t.transform.translation
        ids = {}
        for msg in self.first.truth.values():
            ids.update(zip(msg.names, (t.id for t in msg.tags)))
        runs = [self.recorder.run(BAG, launch_args=LAUNCH_ARGS + ["output_frame:=odom"], timeout=120)
                for _ in range(2)]
        self.assertEqual(len(runs[0].raw_tracks), 15)
        # Alike to 1e-12, not to the bit as in the optical frame: the odom pose of an image comes from tf2,
        # and the recording's odom transforms share the images' stamps; tf2 returns the stored transform when
        # it is the newest it holds, and interpolates to it (slerp at ratio 0: an ulp off) once the next one
        # has arrived, so the result hangs on which came first (seen in the sanitizer build, which is slower).
        self.assertEqual(first_difference(runs[0].tracks, runs[1].tracks, tolerance=1e-12), "",
                         "tracks differ between two replays")
        tracks = replay_report.summarize_tracks(runs[0])
        print(replay_report.format_track_table(runs[0], tracks))
        self.assertEqual(replay_report.false_tracks(runs[0], tracks), [])
        matched = set()
        for summary in tracks.values():
            track = summary.last
            self.assertEqual(runs[0].tracks[summary.last_index].header.frame_id, "odom")
            self.assertTrue(track.filtered)
            if summary.validated_at is None:
                continue
            p = track.pose.pose.position
            name, error = min(((n, math.dist((p.x, p.y, p.z), (t.x, t.y, t.z))) for n, t in truth.items()
                               if ids.get(n) == track.id), key=lambda e: e[1])
            # 5 Hz, 3 hits within 1 s (config/urc.yaml keeps the defaults): the third frame, or up to
            # the sixth for a marker the detector misses now and then: stake_12 at 15 m, or post_c, which
            # starts 77 deg off head-on (past the 70 deg the recall counts) and may be read in the first
            # frame and not the second.
            self.assertGreaterEqual(summary.frames_to_validate(), 3, "track %d" % track.track_id)
            self.assertLessEqual(summary.frames_to_validate(), 6, "track %d" % track.track_id)
            if name == "post_a":
                self.assertEqual(summary.frames_to_validate(), 3,
                                 "post_a, 2-3 m away and 46-58 deg off head-on, is seen in every frame")
            print("track %d (id %d, %s): %.1f mm from the truth" % (track.track_id, track.id, name, 1e3 * error))
            self.assertLess(error, 0.02, "track %d (id %d) is %.3f m from %s" % (track.track_id, track.id, error, name))
            matched.add(name)
        # Both faces of the post (one id) are tracks of their own, and so is the stake.
        self.assertLessEqual({"post_a", "post_c", "stake_3"}, matched)


def suite():
    """The recording's checks, then the replays (rostest.rosrun runs one suite)."""
    loader = unittest.TestLoader()
    return unittest.TestSuite([loader.loadTestsFromTestCase(RecordingTest), loader.loadTestsFromTestCase(ReplayTest)])


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--bag", required=True)
    args, rest = parser.parse_known_args(rospy.myargv()[1:])
    BAG = args.bag
    rostest.rosrun("arucotag", "replay", "__main__.suite", sysargs=[sys.argv[0]] + rest)

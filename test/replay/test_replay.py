#!/usr/bin/env python3
"""Replays the short sample recording through launch/replay.launch and checks the detector's tags
against the recording's truth (recall, distance and yaw error, both faces of the post), then
replays it again and checks the tag messages are identical, stamps included."""

import argparse
import os
import sys
import unittest

import rospy
import rostest

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "scripts"))
import replay_report  # noqa: E402

# The rover's preset (config/urc.yaml), as `make demo` runs it.
LAUNCH_ARGS = []
BAG = None


class ReplayTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("test_replay", anonymous=True)
        cls.recorder = replay_report.Recorder("/truth/tags", "/zed/tags")
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
            self.assertEqual(set(m.sources), {"fused"}, m.name)
        # Close to the post the distance is within a centimetre.
        self.assertLessEqual(max(e[0] for e in post_a.errors), 0.02)
        self.assertEqual(self.false_positives, [])

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


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--bag", required=True)
    args, rest = parser.parse_known_args(rospy.myargv()[1:])
    BAG = args.bag
    rostest.rosrun("arucotag", "replay", ReplayTest, sysargs=[sys.argv[0]] + rest)

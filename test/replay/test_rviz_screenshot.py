#!/usr/bin/env python3
"""Runs scripts/rviz_screenshot.sh on the short sample recording and checks that rviz came up
without errors and that the screenshot shows the camera overlay and the 3D view."""

import argparse
import os
import subprocess
import sys
import unittest

import rospy
import rostest

SCRIPTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "scripts")
ARGS = None


def read_rgb(png):
    """(width, height, bytes) of a PNG as raw 8-bit RGB, through ImageMagick."""
    size = subprocess.run(["/usr/bin/identify", "-format", "%w %h", png], check=True, stdout=subprocess.PIPE)
    width, height = (int(v) for v in size.stdout.split())
    rgb = subprocess.run(["/usr/bin/convert", png, "-depth", "8", "rgb:-"], check=True, stdout=subprocess.PIPE).stdout
    assert len(rgb) == 3 * width * height, (len(rgb), width, height)
    return width, height, rgb


def region_stats(image, x0, y0, x1, y1):
    """Mean R, G, B and the standard deviation of the grey level over a rectangle."""
    w, _, data = image
    n, sums, grey, grey2 = 0, [0, 0, 0], 0.0, 0.0
    for y in range(y0, y1, 2):
        row = data[3 * (y * w + x0):3 * (y * w + x1)]
        for i in range(0, len(row), 6):
            r, g, b = row[i], row[i + 1], row[i + 2]
            sums[0] += r
            sums[1] += g
            sums[2] += b
            v = (r + g + b) / 3.0
            grey += v
            grey2 += v * v
            n += 1
    mean = grey / n
    return [s / n for s in sums], max(0.0, grey2 / n - mean * mean) ** 0.5


class RvizScreenshotTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        out = ARGS.out
        if os.path.exists(out):
            os.remove(out)
        cls.result = subprocess.run(["bash", os.path.join(SCRIPTS, "rviz_screenshot.sh"), "--bag", ARGS.bag, "--out", out,
                                  "--start", "0", "--duration", "1.5"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                 universal_newlines=True, timeout=200)
        print(cls.result.stdout)
        # The replay's log and rviz's own (the script starts rviz first, alone).
        logs = [out[:-len(".png")] + suffix for suffix in (".log", "_rviz.log")]
        cls.log = "".join(open(log, errors="replace").read() for log in logs if os.path.exists(log))
        cls.image = read_rgb(out) if os.path.exists(out) else None

    def test_script_succeeded(self):
        self.assertEqual(self.result.returncode, 0, self.result.stdout)
        self.assertIsNotNone(self.image)
        self.assertEqual(self.image[:2], (1280, 800))

    def test_rviz_started_without_errors(self):
        self.assertIn("rviz version", self.log)
        self.assertIn("process[rviz", self.log)
        for bad in ("[ERROR]", "process has died", "Segmentation fault"):
            self.assertNotIn(bad, self.log)

    def test_overlay_panel_shows_the_camera_image(self):
        self.assertIsNotNone(self.image, self.result.stdout)
        # config/arucotag.rviz docks the overlay at the bottom left (600 px wide); the sample's
        # rusty ground and sky are red-dominated and textured, the "No Image" placeholder is not.
        (r, g, b), spread = region_stats(self.image, 10, 420, 590, 740)
        self.assertGreater(spread, 12.0)
        self.assertGreater(r, b + 15.0)

    def test_3d_view_is_drawn(self):
        self.assertIsNotNone(self.image, self.result.stdout)
        # Right of the docks: the grid and TF axes on a dark background.
        (r, g, b), spread = region_stats(self.image, 640, 80, 1250, 760)
        self.assertLess((r + g + b) / 3.0, 120.0)
        self.assertGreater(spread, 4.0)

    def test_bundle_is_drawn(self):
        self.assertIsNotNone(self.image, self.result.stdout)
        # The script replays with the sample's post as a bundle (config/sample_bundles.yaml). The first
        # 1.5 s of the excerpt (8-9.5 s) end with the post in view; by 11 s it has left, and the last
        # frame's DELETEALL clears the bundle (its TF frame stays). Its faces are drawn violet
        # (ToBundleMarkers), a colour nothing else in the view has: tags and tracks are green or
        # orange, TF axes pure red, green and blue. scripts/rviz_screenshot.sh on the sample's
        # 6.5-10 s: 3275 such pixels with the bundle (every pixel counted; this test counts one in
        # four), 0 with --bundles "".
        w, _, data = self.image
        violet = 0
        for y in range(80, 760, 2):
            row = data[3 * (y * w + 640):3 * (y * w + 1250)]
            for i in range(0, len(row), 6):
                r, g, b = row[i], row[i + 1], row[i + 2]
                violet += r > 60 and g < r and b > r + 40 and b > g + 60
        self.assertGreater(violet, 50)


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--bag", required=True)
    parser.add_argument("--out", required=True)
    ARGS, rest = parser.parse_known_args(rospy.myargv()[1:])
    rostest.rosrun("arucotag", "rviz_screenshot", RvizScreenshotTest, sysargs=[sys.argv[0]] + rest)

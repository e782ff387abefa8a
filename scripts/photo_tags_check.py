#!/usr/bin/env python3
"""Publishes a photo with its camera_info to a running detector and checks the tags it reports.

scripts/workspace_test.sh runs it against the README's commands (detector_node, detector.launch, a
nodelet loaded into a manager). The image is sent as rgb8 (ImageMagick reads the file: no OpenCV or
cv_bridge in Python), re-sent every 0.5 s with a new stamp until a tags message with a pose arrives,
since the detector subscribes to its inputs only once it has started. Exits 0 when the expected id
is reported with a PnP pose at the expected distance, 1 otherwise, printing the reason either way.

    photo_tags_check.py --image tag.png --camera-info camera.yaml --image-topic /front/image_raw \
        --camera-info-topic /front/camera_info --tags-topic /front/tags --id 1 --side 0.145 --distance 0.73
"""
import argparse
import math
import subprocess
import sys
import threading

import rospy
import yaml
from sensor_msgs.msg import CameraInfo, Image

from arucotag.msg import ArucoTag, ArucoTagArray


def read_rgb(path):
    """(width, height, bytes) of an image file as raw 8-bit RGB, through ImageMagick."""
    size = subprocess.run(["/usr/bin/identify", "-format", "%w %h", path], check=True, stdout=subprocess.PIPE)
    width, height = (int(v) for v in size.stdout.split())
    rgb = subprocess.run(["/usr/bin/convert", path, "-depth", "8", "rgb:-"], check=True,
                         stdout=subprocess.PIPE).stdout
    if len(rgb) != 3 * width * height:
        raise RuntimeError("%s: %d bytes of RGB for %dx%d" % (path, len(rgb), width, height))
    return width, height, rgb


def read_camera_info(path):
    """sensor_msgs/CameraInfo from a ROS camera calibration yaml (camera_calibration_parsers' format)."""
    with open(path) as f:
        calib = yaml.safe_load(f)
    info = CameraInfo()
    info.width = calib["image_width"]
    info.height = calib["image_height"]
    info.distortion_model = calib["distortion_model"]
    info.D = calib["distortion_coefficients"]["data"]
    info.K = calib["camera_matrix"]["data"]
    info.R = calib["rectification_matrix"]["data"]
    info.P = calib["projection_matrix"]["data"]
    return info


def summary_of(msg):
    """One line per tags message for the failure reasons: id, pose source and distance of each tag."""
    return "[" + ", ".join("id %d source %d distance %.3f m" % (t.id, t.pose_source, t.distance)
                           for t in msg.tags) + "]"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--image", required=True)
    parser.add_argument("--camera-info", required=True, help="camera calibration yaml")
    parser.add_argument("--image-topic", required=True)
    parser.add_argument("--camera-info-topic", required=True)
    parser.add_argument("--tags-topic", required=True)
    parser.add_argument("--frame-id", default="camera_optical")
    parser.add_argument("--id", type=int, required=True, help="marker id that must be reported")
    parser.add_argument("--distance", type=float, required=True, help="m, expected camera-marker distance")
    parser.add_argument("--side", type=float, required=True, help="m, marker side the detector must use")
    parser.add_argument("--tolerance", type=float, default=0.02, help="m, allowed distance error")
    parser.add_argument("--timeout", type=float, default=60.0, help="s to wait for a tags message with a pose")
    args = parser.parse_args(rospy.myargv()[1:])

    width, height, rgb = read_rgb(args.image)
    info = read_camera_info(args.camera_info)
    if (info.width, info.height) != (width, height):
        print("FAIL: %s is %dx%d, %s is for %dx%d" % (args.image, width, height, args.camera_info, info.width,
                                                     info.height))
        return 1
    image = Image(height=height, width=width, encoding="rgb8", is_bigendian=0, step=3 * width, data=rgb)

    rospy.init_node("photo_tags_check", anonymous=True, disable_signals=True)
    received = []
    last = []
    done = threading.Event()

    def on_tags(msg):
        # A frame processed without its camera_info (the synchronizer's time-out path) has no pose.
        last[:] = [msg]
        if any(t.pose_source != ArucoTag.NONE for t in msg.tags):
            received.append(msg)
            done.set()

    rospy.Subscriber(args.tags_topic, ArucoTagArray, on_tags, queue_size=10)
    image_pub = rospy.Publisher(args.image_topic, Image, queue_size=2)
    info_pub = rospy.Publisher(args.camera_info_topic, CameraInfo, queue_size=2)

    start = rospy.get_rostime()
    sent = 0
    while not done.is_set() and not rospy.is_shutdown():
        if (rospy.get_rostime() - start).to_sec() > args.timeout:
            print("FAIL: no tags message with a pose on %s within %.0f s (%d frames sent to %s, subscribers: %d;"
                  " last tags message: %s)" % (args.tags_topic, args.timeout, sent, args.image_topic,
                                               image_pub.get_num_connections(),
                                               summary_of(last[0]) if last else "none"))
            return 1
        if image_pub.get_num_connections() > 0 and info_pub.get_num_connections() > 0:
            stamp = rospy.Time.now()
            image.header.stamp = info.header.stamp = stamp
            image.header.frame_id = info.header.frame_id = args.frame_id
            info_pub.publish(info)
            image_pub.publish(image)
            sent += 1
        done.wait(0.5)

    msg = received[0]
    summary = summary_of(msg)
    matches = [t for t in msg.tags if t.id == args.id]
    if not matches:
        print("FAIL: id %d not in %s: %s" % (args.id, args.tags_topic, summary))
        return 1
    tag = matches[0]
    position = tag.pose.position
    norm = math.sqrt(position.x ** 2 + position.y ** 2 + position.z ** 2)
    if tag.pose_source != ArucoTag.PNP:
        print("FAIL: id %d has pose source %d, expected PNP (%d): %s" % (args.id, tag.pose_source, ArucoTag.PNP,
                                                                        summary))
        return 1
    if not abs(tag.distance - args.distance) <= args.tolerance or not abs(norm - tag.distance) <= 1e-3:
        print("FAIL: id %d at %.3f m (position norm %.3f m), expected %.3f +- %.3f m"
              % (args.id, tag.distance, norm, args.distance, args.tolerance))
        return 1
    if abs(tag.side_length - args.side) > 1e-6:
        print("FAIL: id %d measured with side %.4f m, expected the configured %.4f m" % (args.id, tag.side_length,
                                                                                     args.side))
        return 1
    if msg.header.frame_id != args.frame_id:
        print("FAIL: tags in frame '%s', expected the image's '%s'" % (msg.header.frame_id, args.frame_id))
        return 1
    print("OK: id %d at %.3f m (x %.3f y %.3f z %.3f) in %s, side %.3f m, after %d frames"
          % (tag.id, tag.distance, position.x, position.y, position.z, msg.header.frame_id, tag.side_length, sent))
    return 0


if __name__ == "__main__":
    sys.exit(main())

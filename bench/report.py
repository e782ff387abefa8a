#!/usr/bin/env python3
"""Prints the benchmark table (markdown) from bench_detect's JSON, adding the nodelet's rows from
bench_nodelet's JSON when given, and writes the merged JSON and the markdown next to them.

    report.py DETECT_JSON [NODELET_JSON] [--out-json FILE] [--out-md FILE]
"""
import argparse
import json
import sys

TARGET_SINGLE, TARGET_SEQUENCE, TARGET_NODELET, TARGET_POSE_US = 4.0, 10.0, 1.1, 50.0


def fmt(x, digits=2):
    return "-" if x is None else f"{x:.{digits}f}"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("detect")
    ap.add_argument("nodelet", nargs="?")
    ap.add_argument("--out-json")
    ap.add_argument("--out-md")
    args = ap.parse_args()

    with open(args.detect) as f:
        results = json.load(f)
    nodelet = None
    if args.nodelet:
        try:
            with open(args.nodelet) as f:
                nodelet = json.load(f)
        except (OSError, ValueError) as e:
            print(f"report: no nodelet results ({e})", file=sys.stderr)
    if nodelet:
        by_name = {s["name"]: s for s in nodelet.get("sets", [])}
        for s in results["sets"]:
            d = by_name.get(s["name"])
            if d:
                s["methods"]["d"] = d["method"]
                s["core_side_by_side"] = d.get("core_side_by_side")
        results["nodelet"] = {k: v for k, v in nodelet.items() if k != "sets"}

    lines = []
    lines.append(f"OpenCV {results['opencv']}, {results['threads']} OpenCV threads on "
                 f"{results['hardware_threads']} hardware threads; times are wall-clock per frame over "
                 f"{results['reps']} passes (the sequence: {max(1, results['reps'] // 2)}), "
                 f"methods interleaved frame by frame.")
    lines.append("")
    lines.append("| frame set | method | median ms | p90 ms | CPU ms | vs (a) | recall | false pos. | corner err p95 px |")
    lines.append("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    misses = []
    for s in results["sets"]:
        a = s["methods"]["a"]
        for key in ("a", "b", "b2", "b3", "c", "d"):
            m = s["methods"].get(key)
            if m is None:
                continue
            ratio = a["median_ms"] / m["median_ms"] if m["median_ms"] > 0 else None
            recall = f"{m['found']}/{m['expected']}" if m.get("expected") is not None else "-"
            name = f"{s['name']}" if key == "a" else ""
            cpu = m.get("cpu_median_ms")
            err = m.get("corner_error_p95_px")
            lines.append(f"| {name} | {m['label']} | {fmt(m['median_ms'])} | {fmt(m['p90_ms'])} | {fmt(cpu)} | "
                         f"{fmt(ratio, 1)}x | {recall} | {m.get('false_positives', '-')} | "
                         f"{'-' if not err else fmt(err)} |")
        b = s["methods"]["b"]
        target = TARGET_SEQUENCE if s["sequence"] else TARGET_SINGLE
        ratio_b = a["median_ms"] / b["median_ms"]
        if ratio_b < target:
            misses.append(f"{s['name']}: (b) is {ratio_b:.1f}x faster than (a), target {target:.0f}x")
        if b["found"] < a["found"]:
            misses.append(f"{s['name']}: (b) recall {b['found']} < (a) {a['found']}")
        d = s["methods"].get("d")
        # (d) against (c) run in the same process, alternating frame by frame (the load on a shared
        # machine changes between the two programs).
        c = s.get("core_side_by_side") or s["methods"]["c"]
        if d is not None:
            s["nodelet_over_core"] = d["median_ms"] / c["median_ms"]
            if d["median_ms"] > TARGET_NODELET * c["median_ms"]:
                misses.append(f"{s['name']}: nodelet {s['nodelet_over_core']:.2f}x of (c), target {TARGET_NODELET}x")
    lines.append("")
    poses = results.get("pose_us", {})
    worst_pose = poses.get("median", 0.0)
    lines.append(f"- Pose (EstimatePoseFromPNP) per tag over {poses.get('count', 0)} tags: median "
                 f"{poses.get('median', 0):.1f} us, p90 {poses.get('p90', 0):.1f} us, mean {poses.get('mean', 0):.1f} us "
                 f"(target < {TARGET_POSE_US:.0f} us); per-set means from {min(s['pose_us_per_tag'] for s in results['sets']):.1f} "
                 f"(50 tags) to {max(s['pose_us_per_tag'] for s in results['sets']):.1f} us (1 tag: the first solve after "
                 f"a detection runs on cold caches).")
    edges = sum(s.get("edge_fits", 0) for s in results["sets"])
    if edges:
        edge_us = sum(s["edge_fit_us_per_tag"] * s["edge_fits"] for s in results["sets"]) / edges
        lines.append(f"- Edge-fit corner refinement (RefineCornersOnEdges, the default; (a) refines nothing): "
                     f"{edge_us:.0f} us per tag on one core, part of (b), (c) and (d).")
    patterns = sum(s.get("pattern_fits", 0) for s in results["sets"])
    if patterns:
        pattern_us = sum(s["pattern_fit_us_per_tag"] * s["pattern_fits"] for s in results["sets"]) / patterns
        lines.append(f"- Whole-pattern fit (RefineCornersOnPattern, markers under pattern_fit_max_side): {pattern_us:.0f} us "
                     f"per tag on one core over {patterns} tags, part of (b), (c) and (d); (b3) is (b) without it.")
    for s in results["sets"]:
        if s["sequence"]:
            lines.append(f"- {s['name']}: {s['tracked_frames']} frames searched by tracking, {s['full_searches']} "
                         f"searched whole; every expected marker found at most {s['worst_new_marker_delay']} "
                         f"frame(s) after it came into view (bound: {results['full_search_interval']} frames).")
    worst_diff = max((s["max_diff_to_full_px"] for s in results["sets"] if s["name"].startswith("real")), default=0)
    differing = sum(s["ids_differing_from_full"] for s in results["sets"] if s["name"].startswith("real"))
    lines.append(f"- Real photos: (b) against the full search (cv::aruco with the same configuration): "
                 f"{differing} ids differ, corners within {worst_diff:.3f} px.")
    if results.get("nodelet"):
        n = results["nodelet"]
        ratios = [s["nodelet_over_core"] for s in results["sets"] if "nodelet_over_core" in s]
        lines.append(f"- (d): {n.get('note', '')}. Against (c) run alongside it in the same process: "
                     f"{min(ratios):.2f}x to {max(ratios):.2f}x (median over sets "
                     f"{sorted(ratios)[len(ratios) // 2]:.2f}x).")
        stream = n.get("stream_30hz")
        if stream and stream.get("answered"):
            lines.append(f"- (d) at 30 Hz (images on the clock, camera_info once, 300 frames of the sequence): "
                         f"{stream['answered']} of {stream['sent']} answered; latency publish to tags median "
                         f"{stream['latency_median_ms']:.2f} ms, p99 {stream['latency_p99_ms']:.2f} ms; the core alone "
                         f"on the same frames median {stream['core_median_ms']:.2f} ms, p99 {stream['core_p99_ms']:.2f} ms "
                         f"({stream['latency_median_ms'] / stream['core_median_ms']:.2f}x, "
                         f"{stream['latency_p99_ms'] / stream['core_p99_ms']:.2f}x).")
    elif not any("d" in s["methods"] for s in results["sets"]):
        lines.append("- (d) nodelet: not measured in this run (see bench/run.sh output).")
    if worst_pose >= TARGET_POSE_US:
        misses.append(f"pose median {worst_pose:.1f} us per tag, target < {TARGET_POSE_US:.0f} us")
    lines.append("- Targets missed: " + ("none" if not misses else "; ".join(misses)) + ".")
    text = "\n".join(lines)
    print(text)
    if args.out_md:
        with open(args.out_md, "w") as f:
            f.write(text + "\n")
    if args.out_json:
        with open(args.out_json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()

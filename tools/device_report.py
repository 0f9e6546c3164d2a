#!/usr/bin/env python3
"""The table of tools/device_check.sh: reads each step's output under --steps, writes
OUT/device_check.json (every figure by name, with the device, the driver and the Vulkan
version) and OUT/device_check.md (one row per figure; with --baseline, an earlier run's
device_check.json, its figure and the ratio beside each). A step's output that is missing
or unreadable is an error: a partial table is never written.

    python3 tools/device_report.py --steps DIR --out DIR [--baseline OTHER/device_check.json]
                                   [--seconds S]
"""
import argparse
import csv
import json
import re
import statistics
import sys
from pathlib import Path


def fail(message):
    sys.exit(f"device_report: {message}")


def read_json(path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        fail(f"cannot read {path}: {e}")


def device_lines(out):
    """The device, its Vulkan version and driver from `vkdr info`'s log ("chosen: NAME
    (TYPE), index I" and "  Vulkan X / driver D")."""
    path = out / "info.log"
    if not path.exists():
        fail(f"no {path}")
    found = {}
    for line in path.read_text().splitlines():
        chosen = re.match(r"chosen: (.*), index \d+$", line)
        if chosen:
            found["device"] = chosen.group(1)
        version = re.match(r"\s+Vulkan (\S+) / driver (.*)$", line)
        if version and "vulkan" not in found:
            found["vulkan"], found["driver"] = version.group(1), version.group(2)
    if "device" not in found:
        fail(f"{path} names no chosen device")
    return found


def figures(out):
    """Every figure of the run: (name, value, unit), in the table's order."""
    rows = []
    add = lambda name, value, unit: rows.append((name, float(value), unit))
    benches = sorted(out.glob("bench_*/bench.json"))
    if not benches:
        fail("no bench_*/bench.json")
    for path in benches:
        size = path.parent.name.removeprefix("bench_")
        for r in read_json(path):
            mesh = f"bench {size}, {r['vertices']} vertices"
            add(f"{mesh}: forward + backward", r["forward_ms"] + r["backward_ms"], "ms")
            add(f"{mesh}: plain render", r["plain_ms"], "ms")
            add(f"{mesh}: dL/dtz error against finite differences", r["dtz_error"], "")
    registers = sorted(out.glob("register_*/bench_register.json"))
    if not registers:
        fail("no register_*/bench_register.json")
    for path in registers:
        r = read_json(path)
        name = f"bench-register {r['width']}x{r['height']}, {r['vertices']} vertices, {'depth' if r['depth'] else 'mask'}"
        if r["batch"] == 1 or not any(f[0].startswith(name + ": one") for f in rows):
            add(f"{name}: one registration ({r['iterations']} iterations + alignment)", r["wall_ms_median"], "ms")
            add(f"{name}: per iteration, device", r["passes_ms"]["total"], "ms")
            add(f"{name}: {r['starts']} starts over one", r["starts_over_one_median"], "x")
            add(f"{name}: error as seen over the oracle", r["seen_m"] / r["oracle_m"], "x")
        add(f"{name}: batch of {r['batch']}, registrations per second", 1e3 * r["batch"] / r["batched_ms"], "1/s")
    cpd = out / "cpd" / "cpd_peers.csv"
    if not cpd.exists():
        fail(f"no {cpd}")
    with open(cpd) as f:
        runs = [r for r in csv.DictReader(f) if r["method"] == "vkdr"]
    if not runs:
        fail(f"{cpd} has no vkdr rows")
    for n in sorted({int(r["points"]) for r in runs}):
        mine = [r for r in runs if int(r["points"]) == n]
        add(f"cpd {n} points: seconds", statistics.median(float(r["seconds"]) for r in mine), "s")
        add(f"cpd {n} points: error (source RMS radii)", statistics.median(float(r["mean_distance"]) for r in mine), "")
    overhead = read_json(out / "overhead.json")
    name = f"python loss_and_grad {overhead['vertices']} vertices, {overhead['size']}^2"
    add(f"{name}: engine", overhead["engine_ms"], "ms")
    add(f"{name}: binding's overhead", overhead["overhead_percent"], "%")
    table = read_json(out / "frames" / "table.json")
    if table["failures"]:
        fail(f"eval-frames had failed units: {table['failures']}")
    by_category = {}
    for r in table["rows"]:
        by_category.setdefault(r["category"], []).append(r)
    for category, units in sorted(by_category.items()):
        mean = lambda f: statistics.mean(f(u) for u in units)
        name = f"eval-frames {category} ({len(units)} units)"
        add(f"{name}: as seen", 1e3 * mean(lambda u: u["pose_noise_seen"]["mean"]), "mm")
        add(f"{name}: known pose", 1e3 * mean(lambda u: u["known_pose"]["mean"]), "mm")
        add(f"{name}: one registration from pose noise", mean(lambda u: u["noise_ms"]), "ms")
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", required=True, type=Path)
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--baseline", type=Path)
    parser.add_argument("--seconds", type=float, help="the whole run's wall time")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    device = device_lines(args.steps)
    rows = figures(args.steps)
    result = {"device": device, "seconds": args.seconds,
              "figures": [{"name": n, "value": v, "unit": u} for n, v, u in rows]}
    (args.out / "device_check.json").write_text(json.dumps(result, indent=1))
    base, base_device = {}, None
    if args.baseline:
        baseline = read_json(args.baseline)
        base = {f["name"]: f["value"] for f in baseline["figures"]}
        base_device = baseline["device"].get("device", "baseline")
    title = device.get("device", "this device")
    md = [f"# vkdr device check\n", f"Device: {title}. " + " ".join(
        f"{k}: {v}." for k, v in device.items() if k != "device")]
    if args.seconds is not None:
        md.append(f"The whole check: {args.seconds:.0f} s.")
    md.append("")
    if base:
        md += [f"| figure | {title} | {base_device} | ratio |", "|---|---|---|---|"]
    else:
        md += [f"| figure | {title} |", "|---|---|"]
    for name, value, unit in rows:
        shown = f"{value:.4g} {unit}".strip()
        if base:
            other = base.get(name)
            md.append(f"| {name} | {shown} | " + (
                f"{other:.4g} {unit}".strip() + f" | {other / value:.3g}" if other and value else "- | -") + " |")
        else:
            md.append(f"| {name} | {shown} |")
    (args.out / "device_check.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    print(f"wrote {args.out / 'device_check.json'} and device_check.md")


if __name__ == "__main__":
    main()

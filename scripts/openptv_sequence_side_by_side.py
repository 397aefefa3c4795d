#!/usr/bin/env python3
"""OpenPTV (optv 0.3.2) and `ptv process-sequence` side by side on 100 real
frame sets (issue 30).

The frame sets are test_cavity's real recording
(`tests/data/openptv/test_cavity_recording`: 4 cameras, 1280x1024 8-bit LZW
TIFFs, frames 10001-10004) repeated: frame `10001 + i` of camera `c` is a
link to `cam<c>.<10001 + i % 4>`. The experiment directory is built under
`--work` (its `cal/` and `parameters/` copied from the recording, its
`sequence.par` set to the 100 frames); nothing outside the repository and
`--work` is read or written.

Each program runs its whole per-frame pipeline with the experiment's own
parameters, as a whole process:

- ptv: `ptv process-sequence --experiment DIR --output OUT` (TIFF read,
  high-pass, detection, correspondences, 3D; it writes particles, `rt_is`
  and `_targets` files per frame);
- OpenPTV: this script's `--worker`, in one Python process, pyptv's
  sequence step per frame: each camera's image read with Pillow,
  `preprocess_image` (the high-pass of pyptv, `lowpass_dim` 25),
  `target_recognition` with `targ_rec.par`, `sort_y`, then `MatchedCoords`,
  `correspondences` with `criteria.par` and `point_positions` of every
  group; it writes each camera's `_targets` file and the particles.

Runs alternate between the programs (so that load from other users of the
machine hits both alike), each pinned with `taskset -c` to `--cpus` (1 core:
`1`; 2 cores: `0,1`; rayon in ptv uses the cores of its affinity mask,
OpenPTV is single-threaded either way). It prints the median wall-clock time
of each, their ratio, the targets and particles each found, and the load
average before and after.

Requirements: a release build of `ptv` (`cargo build --release --bin ptv`)
and a Python with optv 0.3.2, numpy and Pillow::

    python3 -m venv /tmp/optv-venv
    /tmp/optv-venv/bin/pip install optv numpy pillow
    /tmp/optv-venv/bin/python scripts/openptv_sequence_side_by_side.py \\
        --ptv target/release/ptv --cpus 1 --runs 3

Without optv (or Pillow) the OpenPTV side is skipped with a message, and
ptv's time alone is reported.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RECORDING = REPO / "tests" / "data" / "openptv" / "test_cavity_recording"
FIRST = 10001
REAL_FRAMES = 4
CAMERAS = 4
HIGHPASS = 25  # pyptv's DEFAULT_HIGHPASS_FILTER_SIZE


def build_experiment(work: Path, frames: int) -> Path:
    """The experiment directory: the recording's calibration and parameters,
    `frames` frame sets of links to its 4 real ones."""
    experiment = work / "experiment"
    if experiment.exists():
        shutil.rmtree(experiment)
    (experiment / "img").mkdir(parents=True)
    shutil.copytree(RECORDING / "cal", experiment / "cal")
    shutil.copytree(RECORDING / "parameters", experiment / "parameters")
    for i in range(frames):
        for c in range(1, CAMERAS + 1):
            source = RECORDING / "img" / f"cam{c}.{FIRST + i % REAL_FRAMES}"
            os.symlink(source, experiment / "img" / f"cam{c}.{FIRST + i}")
    sequence = experiment / "parameters" / "sequence.par"
    lines = sequence.read_text().splitlines()
    # Four image name patterns, then the first and last frame.
    lines[CAMERAS] = str(FIRST)
    lines[CAMERAS + 1] = str(FIRST + frames - 1)
    sequence.write_text("\n".join(lines) + "\n")
    return experiment


# ------------------------------------------------------------ the worker --
def worker(args: argparse.Namespace) -> None:
    """OpenPTV's per-frame pipeline over the experiment's frames."""
    t_start = time.perf_counter()
    import numpy as np
    from optv.calibration import Calibration
    from optv.correspondences import MatchedCoords, correspondences
    from optv.image_processing import preprocess_image
    from optv.orientation import point_positions
    from optv.parameters import ControlParams, TargetParams, VolumeParams
    from optv.segmentation import target_recognition
    from PIL import Image

    experiment = Path(args.experiment)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    parameters = experiment / "parameters"
    cpar = ControlParams(CAMERAS)
    cpar.read_control_par(str(parameters / "ptv.par"))
    tpar = TargetParams()
    tpar.read(str(parameters / "targ_rec.par"))
    vpar = VolumeParams()
    vpar.read_volume_par(str(parameters / "criteria.par"))
    cals = []
    for c in range(1, CAMERAS + 1):
        cal = Calibration()
        cal.from_file(
            str(experiment / "cal" / f"cam{c}.tif.ori").encode(),
            str(experiment / "cal" / f"cam{c}.tif.addpar").encode(),
        )
        cals.append(cal)
    targets_total = 0
    particles_total = 0
    for frame in range(args.first, args.last + 1):
        targets = []
        for c in range(CAMERAS):
            image = np.asarray(Image.open(experiment / "img" / f"cam{c + 1}.{frame}"))
            filtered = preprocess_image(image, 0, cpar, HIGHPASS)
            found = target_recognition(filtered, tpar, c, cpar)
            found.sort_y()
            found.write(str(out / f"cam{c + 1}.").encode(), frame)
            targets.append(found)
            targets_total += len(found)
        flat = [MatchedCoords(targets[c], cpar, cals[c]) for c in range(CAMERAS)]
        _, corresp, _ = correspondences(targets, flat, cals, vpar, cpar)
        ids = np.concatenate(corresp, axis=1)
        coords = np.full((ids.shape[1], CAMERAS, 2), -1e10)
        for c in range(CAMERAS):
            pos, pnr = flat[c].as_arrays()
            by_pnr = np.empty((len(targets[c]), 2))
            by_pnr[pnr] = pos
            present = ids[c] >= 0
            coords[present, c, :] = by_pnr[ids[c][present]]
        points = point_positions(coords, cpar, cals, vpar)[0] if ids.shape[1] else []
        particles_total += len(points)
        with open(out / f"rt_is.{frame}", "w") as f:
            f.write(f"{len(points)}\n")
            for j, p in enumerate(points):
                f.write(
                    f"{j + 1} {p[0]:.3f} {p[1]:.3f} {p[2]:.3f} "
                    + " ".join(str(int(t)) for t in ids[:, j])
                    + "\n"
                )
    Path(args.summary).write_text(
        json.dumps(
            {
                "targets": targets_total,
                "particles": particles_total,
                "in_process": time.perf_counter() - t_start,
            }
        )
    )


# ---------------------------------------------------------------- timing --
def pinned(command: list[str], cpus: str) -> list[str]:
    if shutil.which("taskset") is None:
        return command
    return ["taskset", "-c", cpus] + command


def timed(command: list[str], stdout: Path) -> tuple[float, float]:
    """The wall-clock and CPU (user + system) times (s) of one whole process;
    its standard output to `stdout`. A failed run stops the script with its
    stderr. On a loaded machine the CPU time is the steadier figure (the
    wall clock also counts the time other processes held the core)."""
    with open(stdout, "w") as out:
        start = time.perf_counter()
        child = subprocess.Popen(command, stdout=out, stderr=subprocess.PIPE)
        stderr = child.stderr.read()
        _, status, usage = os.wait4(child.pid, 0)
        elapsed = time.perf_counter() - start
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        sys.exit(f"{' '.join(command)} failed ({code}):\n" + stderr.decode(errors="replace"))
    return elapsed, usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ptv", default=str(REPO / "target" / "release" / "ptv"))
    parser.add_argument("--work", default="/tmp/ptv-real-side-by-side")
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--runs", type=int, default=3, help="timed runs per program")
    parser.add_argument("--cpus", default="1", help="taskset -c list: 1 core '1', 2 cores '0,1'")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--experiment", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    parser.add_argument("--summary", help=argparse.SUPPRESS)
    parser.add_argument("--first", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--last", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args)
        return

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    experiment = build_experiment(work, args.frames)
    try:
        import optv  # noqa: F401
        import PIL  # noqa: F401

        have_optv = True
    except ImportError:
        have_optv = False
        print(
            f"note: {sys.executable} has no optv or Pillow, so OpenPTV is skipped; run "
            "this script with a Python that has them (python3 -m venv /tmp/optv-venv && "
            "/tmp/optv-venv/bin/pip install optv numpy pillow)",
            file=sys.stderr,
        )
    ptv_cmd = pinned(
        [args.ptv, "process-sequence", "--experiment", str(experiment), "--output",
         str(work / "ptv_out")],
        args.cpus,
    )
    optv_cmd = pinned(
        [sys.executable, __file__, "--worker", "--experiment", str(experiment),
         "--out", str(work / "openptv_out"), "--summary", str(work / "openptv.json"),
         "--first", str(FIRST), "--last", str(FIRST + args.frames - 1)],
        args.cpus,
    )
    load_before = os.getloadavg()
    times: dict[str, list[tuple[float, float]]] = {"ptv": [], "openptv": []}
    for run in range(args.runs):
        order = [("ptv", ptv_cmd), ("openptv", optv_cmd)]
        if run % 2:
            order.reverse()
        for name, command in order:
            if name == "openptv" and not have_optv:
                continue
            times[name].append(timed(command, work / f"{name}.stdout"))
    load_after = os.getloadavg()
    summary = json.loads((work / "ptv.stdout").read_text())
    print(f"{args.frames} real frame sets (test_cavity, 4 x 1280x1024 LZW TIFF), "
          f"taskset -c {args.cpus}, {args.runs} runs each, alternating")
    print(f"load average before {load_before[0]:.2f}, after {load_after[0]:.2f}")
    print()
    print("| program | median wall s | median CPU s | runs wall / CPU (s) | wall per frame set (ms) |")
    print("| --- | ---: | ---: | --- | ---: |")
    medians = {}
    for name, label in (("ptv", "ptv process-sequence"), ("openptv", "OpenPTV (optv 0.3.2)")):
        if not times[name]:
            continue
        wall = statistics.median(t[0] for t in times[name])
        cpu = statistics.median(t[1] for t in times[name])
        medians[name] = (wall, cpu)
        runs = ", ".join(f"{w:.2f}/{c:.2f}" for w, c in times[name])
        print(f"| {label} | {wall:.2f} | {cpu:.2f} | {runs} | {1000 * wall / args.frames:.1f} |")
    if "openptv" in medians:
        (pw, pc), (ow, oc) = medians["ptv"], medians["openptv"]
        print()
        print(f"ptv is {ow / pw:.2f}x OpenPTV's speed by the wall clock, {oc / pc:.2f}x by CPU time")
        theirs = json.loads((work / "openptv.json").read_text())
        print(f"OpenPTV: {theirs['targets']} targets, {theirs['particles']} particles")
    print(f"ptv: targets {json.dumps(summary.get('targets_per_camera'))}, "
          f"particles {json.dumps(summary.get('particles'))}")

if __name__ == "__main__":
    main()

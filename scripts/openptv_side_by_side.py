#!/usr/bin/env python3
"""OpenPTV (optv 0.3.2) and `ptv match` side by side on one simulated frame.

Both programs get the same files (the calibration as OpenPTV's `.ori`,
`.addpar` and `ptv.par`, written by `ptv calibration export-openptv`; the
targets as OpenPTV `_targets` files, which `ptv match` also reads) and the
same band; each run is a whole process, reading its files and writing its
particles, pinned to one core. Their particles are scored against the
simulator's `truth.csv` with the rule of `MatchScore::of`
(`src/photogrammetry/simulate.rs`, used by `benches/correspond.rs` and the
matcher's wide-band tests): a particle is correct when all its targets image
the same true particle, otherwise a ghost.

Requirements
------------
- Python 3.9+ with numpy and optv 0.3.2 (OpenPTV's Python bindings, a
  manylinux wheel on PyPI)::

      python3 -m venv /tmp/optv-venv
      /tmp/optv-venv/bin/pip install optv==0.3.2 numpy

- a release build of `ptv` (`cargo build --release`);
- `taskset` (util-linux) to pin runs to one core (`--cpu`); without it runs
  are not pinned, and the report says so.

Use
---
The benchmark scene of issue 14 (4 cameras, 10,000 particles, 0.1 px noise,
10% dropout; seed 10000 is the scene `benches/correspond.rs` and
`examples/match_once.rs` build in memory)::

    target/release/ptv simulate --cameras 4 --particles 10000 --drop 0.1 \\
        --noise 0.1 --no-images --seed 10000 --out /tmp/scene
    /tmp/optv-venv/bin/python scripts/openptv_side_by_side.py \\
        --scene /tmp/scene --ptv target/release/ptv --runs 9

It writes its files under `--work` (default `SCENE/side_by_side`), prints a
Markdown table (correct / ghosts per band for both programs; median
whole-process time of each and their ratio; OpenPTV's own stages, timed
inside its process) and the load average before and after, and writes the
figures as JSON (`--json`). Runs alternate between the programs, so that
load from other users of the machine hits both alike.

What OpenPTV runs is pyptv's processing of one frame: `read_targets` per
camera, `MatchedCoords` (pixel -> metric -> flat, x-sorted),
`correspondences` (quadruplets, triplets and, where liboptv allows them,
pairs), then `point_positions` of every group (its 3D intersection). Only the
gathering of each group's flat coordinates is vectorised with numpy instead
of pyptv's `get_by_pnrs` (a Python loop per target, which would dominate the
time). OpenPTV's band is `eps0` in mm on the sensor: the band in pixels times
the pixel size. Its volume is the depth range of the simulated volume (OpenPTV
bounds only the depth, linearly in x); the criteria `cn`, `cnx`, `cny`,
`csumg` (0.02) and `corrmin` (33) are test_cavity's `criteria.par` (the
simulated targets all have the same size and brightness, so they only pass
or fail together). `ptv match` gets the volume box `ptv simulate` prints
(`--volume`), or with `--ptv-depth-only` OpenPTV's semantics (x and y
unbounded).

This script reads nothing outside the scene directory it is given.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

FRAME = 10000  # the frame number in the _targets file names (camN.10000_targets)
DEFAULT_BANDS = (0.5, 2.0, 4.0, 10.0)
# test_cavity's criteria.par (tests/data/openptv/test_cavity/parameters).
CN = CNX = CNY = CSUMG = 0.02
CORRMIN = 33.0


# ---------------------------------------------------------------- worker --
def worker(args: argparse.Namespace) -> None:
    """One whole OpenPTV run: read files, match, intersect, write CSV.

    Stage times (s, from `time.perf_counter`) go to `--timings` as JSON.
    """
    t_start = time.perf_counter()
    import numpy as np
    from optv.calibration import Calibration
    from optv.correspondences import MatchedCoords, correspondences
    from optv.orientation import point_positions
    from optv.parameters import ControlParams, VolumeParams
    from optv.tracking_framebuf import read_targets

    t_import = time.perf_counter()
    openptv = Path(args.openptv_dir)
    cpar = ControlParams(args.cameras)
    cpar.read_control_par(str(openptv / "ptv.par"))
    vpar = VolumeParams()
    vpar.set_X_lay([args.volume[0], args.volume[1]])
    vpar.set_Zmin_lay([args.volume[4], args.volume[4]])
    vpar.set_Zmax_lay([args.volume[5], args.volume[5]])
    vpar.set_cn(CN)
    vpar.set_cnx(CNX)
    vpar.set_cny(CNY)
    vpar.set_csumg(CSUMG)
    vpar.set_corrmin(CORRMIN)
    pixel = cpar.get_pixel_size()[0]
    vpar.set_eps0(args.band * pixel)
    cals = []
    for c in range(args.cameras):
        cal = Calibration()
        name = f"cam{c + 1}"
        cal.from_file(
            str(openptv / f"{name}.ori").encode(), str(openptv / f"{name}.addpar").encode()
        )
        cals.append(cal)
    targets = [
        read_targets(str(Path(args.targets_dir) / f"cam{c + 1}."), FRAME)
        for c in range(args.cameras)
    ]
    t_read = time.perf_counter()

    flat = [MatchedCoords(targets[c], cpar, cals[c]) for c in range(args.cameras)]
    t_flat = time.perf_counter()
    sorted_pos, sorted_corresp, _ = correspondences(targets, flat, cals, vpar, cpar)
    t_corresp = time.perf_counter()

    # Each group's flat coordinates (COORD_UNUSED where a camera has none),
    # by target number, as pyptv's py_determination_proc_c gathers them.
    ids = np.concatenate(sorted_corresp, axis=1)  # (cameras, groups)
    coords = np.full((ids.shape[1], args.cameras, 2), -1e10)
    for c in range(args.cameras):
        pos, pnr = flat[c].as_arrays()
        by_pnr = np.empty((len(targets[c]), 2))
        by_pnr[pnr] = pos
        present = ids[c] >= 0
        coords[present, c, :] = by_pnr[ids[c][present]]
    if ids.shape[1] > 0:
        points, _ = point_positions(coords, cpar, cals, vpar)
    else:
        points = np.empty((0, 3))
    t_intersect = time.perf_counter()

    with open(args.out, "w") as out:
        out.write("x,y,z,cameras," + ",".join(f"t{c}" for c in range(args.cameras)) + "\n")
        cameras = (ids >= 0).sum(axis=0)
        for j in range(ids.shape[1]):
            p = points[j]
            out.write(
                f"{float(p[0])!r},{float(p[1])!r},{float(p[2])!r},{cameras[j]},"
                + ",".join(str(int(t)) for t in ids[:, j])
                + "\n"
            )
    t_write = time.perf_counter()
    Path(args.timings).write_text(
        json.dumps(
            {
                "import": t_import - t_start,
                "read": t_read - t_import,
                "flat": t_flat - t_read,
                "correspondences": t_corresp - t_flat,
                "intersection": t_intersect - t_corresp,
                "write": t_write - t_intersect,
                "in_process": t_write - t_start,
            }
        )
    )


# ----------------------------------------------------------- preparation --
def write_openptv_targets(scene: Path, work: Path, cameras: int) -> None:
    """Each camera's CSV targets as an OpenPTV `_targets` file, in the same
    order (pnr = row), with OpenPTV's own writer."""
    from optv.tracking_framebuf import TargetArray

    for c in range(cameras):
        with open(scene / f"cam{c + 1}_targets.csv") as f:
            rows = list(csv.DictReader(f))
        array = TargetArray(len(rows))
        for i, row in enumerate(rows):
            t = array[i]
            t.set_pnr(i)
            t.set_pos((float(row["x"]), float(row["y"])))
            t.set_pixel_counts(int(row["n"]), int(row["nx"]), int(row["ny"]))
            t.set_sum_grey_value(int(row["sumg"]))
            t.set_tnr(-1)
        array.write(str(work / f"cam{c + 1}.").encode(), FRAME)


def prepare(args: argparse.Namespace) -> tuple[Path, Path, int]:
    scene = Path(args.scene)
    work = Path(args.work) if args.work else scene / "side_by_side"
    openptv = work / "openptv"
    targets = work / "targets"
    for d in (openptv, targets):
        d.mkdir(parents=True, exist_ok=True)
    cameras = len(sorted(scene.glob("cam*_targets.csv")))
    if cameras < 2:
        sys.exit(f"{scene}: expected camN_targets.csv files of `ptv simulate` (found {cameras})")
    subprocess.run(
        [
            args.ptv,
            "calibration",
            "export-openptv",
            "--calibration",
            str(scene / "calibration.json"),
            "--out-dir",
            str(openptv),
        ],
        check=True,
        stderr=subprocess.DEVNULL,
    )
    write_openptv_targets(scene, targets, cameras)
    return work, targets, cameras


# --------------------------------------------------------------- scoring --
def read_truth(scene: Path, cameras: int) -> tuple[list[dict[int, int]], dict[int, tuple]]:
    """Per camera, target index -> true particle; and particle -> (x, y, z)."""
    source = [dict() for _ in range(cameras)]
    position = {}
    with open(scene / "truth.csv") as f:
        for row in csv.DictReader(f):
            p = int(row["particle"])
            position[p] = (float(row["x"]), float(row["y"]), float(row["z"]))
            for c in range(cameras):
                t = int(row[f"t{c}"])
                if t >= 0:
                    source[c][t] = p
    return source, position


def score(particles: Path, truth, cameras: int) -> dict:
    """`MatchScore::of`: correct when all targets image one true particle."""
    source, position = truth
    correct = ghosts = 0
    by_cameras = [0] * (cameras + 1)
    sum_sq = 0.0
    with open(particles) as f:
        for row in csv.DictReader(f):
            members = [(c, int(row[f"t{c}"])) for c in range(cameras) if int(row[f"t{c}"]) >= 0]
            by_cameras[len(members)] += 1
            origins = {source[c].get(t) for c, t in members}
            if len(origins) == 1 and None not in origins:
                correct += 1
                (p,) = origins
                x, y, z = (float(row[k]) for k in "xyz")
                tx, ty, tz = position[p]
                sum_sq += (x - tx) ** 2 + (y - ty) ** 2 + (z - tz) ** 2
            else:
                ghosts += 1
    rms = (sum_sq / (3 * correct)) ** 0.5 if correct else float("nan")
    return {"correct": correct, "ghosts": ghosts, "by_cameras": by_cameras, "rms_error_mm": rms}


# ---------------------------------------------------------------- timing --
def pinned(command: list[str], cpu: int | None) -> list[str]:
    if cpu is None or shutil.which("taskset") is None:
        return command
    return ["taskset", "-c", str(cpu)] + command


def timed(command: list[str], stdout: Path | None, env: dict | None = None) -> tuple[float, float]:
    """The wall-clock and CPU (user + system) times (s) of one whole process;
    its standard output to `stdout` (or discarded). A failed run stops the
    script with its stderr."""
    with open(stdout, "w") if stdout else open(os.devnull, "w") as out:
        start = time.perf_counter()
        child = subprocess.Popen(command, stdout=out, stderr=subprocess.PIPE, env=env)
        stderr = child.stderr.read()
        _, status, usage = os.wait4(child.pid, 0)
        elapsed = time.perf_counter() - start
        child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode != 0:
        sys.exit(f"{' '.join(command)} failed ({child.returncode}):\n{stderr.decode(errors='replace')}")
    return elapsed, usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", help="the directory `ptv simulate` wrote")
    parser.add_argument("--ptv", default="target/release/ptv", help="the ptv binary")
    parser.add_argument("--work", help="where to write (default SCENE/side_by_side)")
    parser.add_argument(
        "--bands", default=",".join(str(b) for b in DEFAULT_BANDS), help="bands (px), comma-separated"
    )
    parser.add_argument("--runs", type=int, default=9, help="timed runs per program and band")
    parser.add_argument("--cpu", type=int, default=1, help="the core to pin runs to (taskset -c)")
    parser.add_argument(
        "--volume",
        default="-40,40,-40,40,-20,20",
        help="the volume `ptv simulate` printed, as --volume=xmin,xmax,ymin,ymax,zmin,zmax (mm)",
    )
    parser.add_argument(
        "--ptv-depth-only",
        action="store_true",
        help="give ptv match OpenPTV's volume (depth only: x and y unbounded)",
    )
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument(
        "--match-once",
        help="examples/match_once built in release: also time ptv's matching alone, in process",
    )
    # The worker: one OpenPTV process (used by the runs above).
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--openptv-dir", help=argparse.SUPPRESS)
    parser.add_argument("--targets-dir", help=argparse.SUPPRESS)
    parser.add_argument("--cameras", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--band", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    parser.add_argument("--timings", help=argparse.SUPPRESS)
    args = parser.parse_args()
    args.volume = [float(v) for v in args.volume.split(",")]
    if len(args.volume) != 6:
        sys.exit("--volume: six numbers, xmin,xmax,ymin,ymax,zmin,zmax")
    if args.worker:
        worker(args)
        return
    if not args.scene:
        sys.exit("--scene DIR is required (the output of `ptv simulate`)")
    try:
        import optv  # noqa: F401
    except ImportError:
        sys.exit(
            f"{sys.executable} has no optv: run this script with a Python that has "
            "optv 0.3.2 and numpy (python3 -m venv /tmp/optv-venv && "
            "/tmp/optv-venv/bin/pip install optv==0.3.2 numpy)"
        )
    if not Path(args.ptv).is_file():
        sys.exit(f"--ptv {args.ptv}: no such file (cargo build --release)")

    bands = [float(b) for b in args.bands.split(",")]
    work, targets_dir, cameras = prepare(args)
    truth = read_truth(Path(args.scene), cameras)
    v = args.volume
    ptv_volume = (
        f"-inf,inf,-inf,inf,{v[4]},{v[5]}" if args.ptv_depth_only else ",".join(str(x) for x in v)
    )
    load_before = os.getloadavg()
    pinning = "taskset -c %d" % args.cpu if shutil.which("taskset") else "not pinned"
    results = []
    for band in bands:
        tag = f"{band:g}"
        ptv_out = work / f"ptv_{tag}.csv"
        optv_out = work / f"openptv_{tag}.csv"
        optv_timings = work / f"openptv_{tag}.json"
        ptv_cmd = pinned(
            [args.ptv, "match", "--calibration", str(Path(args.scene) / "calibration.json")]
            + [a for c in range(cameras) for a in ("--targets", str(targets_dir / f"cam{c + 1}.{FRAME}_targets"))]
            + ["--tolerance", str(band), f"--volume={ptv_volume}"],
            args.cpu,
        )
        optv_cmd = pinned(
            [sys.executable, os.path.abspath(__file__), "--worker"]
            + ["--openptv-dir", str(work / "openptv"), "--targets-dir", str(targets_dir)]
            + ["--cameras", str(cameras), "--band", str(band), "--out", str(optv_out)]
            + ["--timings", str(optv_timings), "--volume=" + ",".join(str(x) for x in v)],
            args.cpu,
        )
        # numpy's OpenBLAS would start a thread per core that spins on the
        # one core the run is pinned to; OpenPTV's work is single-threaded.
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
        times = {"ptv": [], "openptv": []}
        stages = []
        for run in range(args.runs):
            # Alternate which program goes first.
            order = [("ptv", ptv_cmd, ptv_out), ("openptv", optv_cmd, None)]
            if run % 2:
                order.reverse()
            for name, cmd, out in order:
                times[name].append(timed(cmd, out, env))
                if name == "openptv":
                    stages.append(json.loads(optv_timings.read_text()))
        row = {
            "band_px": band,
            "ptv": score(ptv_out, truth, cameras),
            "openptv": score(optv_out, truth, cameras),
            "ptv_wall_ms": [w * 1e3 for w, _ in times["ptv"]],
            "ptv_cpu_ms": [c * 1e3 for _, c in times["ptv"]],
            "openptv_wall_ms": [w * 1e3 for w, _ in times["openptv"]],
            "openptv_cpu_ms": [c * 1e3 for _, c in times["openptv"]],
            "openptv_stages_ms": {
                k: statistics.median(s[k] for s in stages) * 1e3 for k in stages[0]
            },
        }
        if args.match_once:
            row["ptv_matching_ms"] = match_once(args, band)
        results.append(row)
        print(
            f"band {tag} px: ptv {statistics.median(row['ptv_wall_ms']):.0f} ms, "
            f"OpenPTV {statistics.median(row['openptv_wall_ms']):.0f} ms",
            file=sys.stderr,
        )
    load_after = os.getloadavg()
    report(args, results, pinning, ptv_volume, load_before, load_after)


def match_once(args: argparse.Namespace, band: float) -> float:
    """`examples/match_once`'s median time (ms) of matching alone (in
    process, intersection included) of its scene, the same as `ptv
    simulate --particles N --seed N` with 4 cameras, 0.1 px noise, 10%
    dropout."""
    particles = sum(1 for _ in open(Path(args.scene) / "truth.csv")) - 1
    command = pinned([args.match_once, str(particles), str(args.runs), str(band)], args.cpu)
    text = subprocess.run(command, capture_output=True, check=True, text=True).stdout
    return float(text.split("median ")[1].split(" ms")[0])


def report(args, results, pinning, ptv_volume, load_before, load_after) -> None:
    v = args.volume
    med = statistics.median
    print(f"\nOne core ({pinning}), median of {args.runs} whole-process runs each, alternating;")
    print(
        f"load average before {load_before[0]:.2f} / {load_before[1]:.2f} / {load_before[2]:.2f}, "
        f"after {load_after[0]:.2f} / {load_after[1]:.2f} / {load_after[2]:.2f}."
    )
    print(f"ptv match --volume={ptv_volume}; OpenPTV depth {v[4]:g}..{v[5]:g} mm.\n")
    print(
        "| band (px) | ptv correct / ghosts | OpenPTV correct / ghosts "
        "| ptv wall (CPU) ms | OpenPTV wall (CPU) ms | OpenPTV / ptv, wall (CPU) "
        "| OpenPTV correspondences + intersection ms | ptv matching ms |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for row in results:
        p, o = row["ptv"], row["openptv"]
        pw, pc = med(row["ptv_wall_ms"]), med(row["ptv_cpu_ms"])
        ow, oc = med(row["openptv_wall_ms"]), med(row["openptv_cpu_ms"])
        s = row["openptv_stages_ms"]
        matching = f"{row['ptv_matching_ms']:.0f}" if "ptv_matching_ms" in row else "-"
        print(
            f"| {row['band_px']:g} | {p['correct']:,} / {p['ghosts']:,} | {o['correct']:,} / {o['ghosts']:,} "
            f"| {pw:.0f} ({pc:.0f}) | {ow:.0f} ({oc:.0f}) | {ow / pw:.1f}x ({oc / pc:.1f}x) "
            f"| {s['correspondences']:.0f} + {s['intersection']:.0f} | {matching} |"
        )
    print("\nParticles by camera count (2/3/4), and the 3D RMS error per axis of the correct ones (mm):")
    for row in results:
        p, o = row["ptv"], row["openptv"]
        print(
            f"- {row['band_px']:g} px: ptv {p['by_cameras'][2:]}, {p['rms_error_mm']:.4f}; "
            f"OpenPTV {o['by_cameras'][2:]}, {o['rms_error_mm']:.4f}"
        )
    print("\nOpenPTV's stages inside its process (median ms):")
    for row in results:
        print(
            f"- {row['band_px']:g} px: "
            + ", ".join(f"{k} {t:.0f}" for k, t in row["openptv_stages_ms"].items())
        )
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                {
                    "load_before": load_before,
                    "load_after": load_after,
                    "pinning": pinning,
                    "ptv_volume": ptv_volume,
                    "runs": args.runs,
                    "bands": results,
                },
                indent=2,
            )
        )

if __name__ == "__main__":
    main()

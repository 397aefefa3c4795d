#!/usr/bin/env python3
"""Peak memory of a `ptv serve` process fed hostile images at the largest
sensor (issue 29's "must show"), with one and with two workers.

    python3 scripts/hostile_peaks.py --ptv target/release/ptv [--workers 1 2] [--work DIR]
        [--bomb-gib 8] [--cases plain,preprocessed,iccp,ztxt,itxt,checkerboard,ridges]

Each case starts a fresh server on its own data directory (VmHWM only ever
grows), creates a calibration of two 8192x8192 16-bit cameras and a
sequence, and uploads two frames at once, so that two workers process two
frames together. Camera 0 gets the case's image, camera 1 a blank one.
Bomb cases also send the bomb as the sequence's mask and background (both
refused or decoded; the point is the memory). When every job has ended it
reads the server's VmHWM from /proc/PID/status and prints one row:

    case, workers, idle MiB, peak MiB, peak - idle, jobs' states, seconds

Cases:
- plain: a blank 16-bit PNG (the baseline: the decoded image and a frame
  job's detection);
- preprocessed: the blank PNG, also sent as the sequence's mask and
  background (the bombs' baseline: their frame jobs subtract both);
- iccp / ztxt / itxt: the blank PNG with one ancillary chunk that inflates
  to `--bomb-gib` GiB (a file of ~1 MB per GiB);
- checkerboard: a 1-pixel checkerboard over the whole image, detected with
  threshold 1 and one pixel a target (33.5 M maxima, past the per-camera
  target limit of 2^20, which must stop detection early);
- ridges: a smooth 16-px grid of maxima joined by bright ridges, all above
  the threshold: one connected bright region of 4 M pixels' maxima that
  the splitter must take apart.

Only the standard library; the images are written as PNGs by zlib.
"""

import argparse
import json
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import urllib.request
import zlib

SIDE = 8192


def chunk(kind: bytes, data: bytes) -> bytes:
    return (
        struct.pack(">I", len(data))
        + kind
        + data
        + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    )


def png16(rows, extra: bytes = b"") -> bytes:
    """A SIDE x SIDE 16-bit grey PNG of `rows` (a function y -> row bytes)."""
    c = zlib.compressobj(6)
    parts = []
    for y in range(SIDE):
        parts.append(c.compress(b"\0" + rows(y)))
    parts.append(c.flush())
    ihdr = struct.pack(">IIBBBBB", SIDE, SIDE, 16, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + extra
        + chunk(b"IDAT", b"".join(parts))
        + chunk(b"IEND", b"")
    )


def bomb_chunk(kind: str, gib: int) -> bytes:
    c = zlib.compressobj(9)
    block = b"\0" * (1 << 20)
    z = b"".join(c.compress(block) for _ in range(gib << 10)) + c.flush()
    head = {"iccp": b"icc\0\0", "ztxt": b"Comment\0\0", "itxt": b"Comment\0\x01\0\0\0"}[kind]
    return chunk({"iccp": b"iCCP", "ztxt": b"zTXt", "itxt": b"iTXt"}[kind], head + z)


def images(cases, gib):
    blank_row = b"\0" * (2 * SIDE)
    out = {"blank": png16(lambda y: blank_row)}
    for kind in ("iccp", "ztxt", "itxt"):
        if kind in cases:
            out[kind] = png16(lambda y: blank_row, bomb_chunk(kind, gib))
    if "checkerboard" in cases:
        even = struct.pack(">2H", 1000, 0) * (SIDE // 2)
        odd = struct.pack(">2H", 0, 1000) * (SIDE // 2)
        out["checkerboard"] = png16(lambda y: even if y % 2 == 0 else odd)
    if "ridges" in cases:
        import math

        profile = [math.cos(2 * math.pi * x / 16) for x in range(16)]
        rows = []
        for y in range(16):
            values = [
                int(20000 + 10000 * (profile[x % 16] + profile[y])) for x in range(SIDE)
            ]
            rows.append(struct.pack(f">{SIDE}H", *values))
        out["ridges"] = png16(lambda y: rows[y % 16])
    out["plain"] = out["preprocessed"] = out["blank"]
    return out


def request(method, url, body=None, headers=None):
    req = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=600) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


def post_json(url, value):
    status, body = request(
        "POST", url, json.dumps(value).encode(), {"Content-Type": "application/json"}
    )
    return status, json.loads(body or b"null")


def multipart(fields, files):
    boundary = "ptvprobe" + os.urandom(8).hex()
    parts = []
    for name, value in fields.items():
        parts.append(
            f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"\r\n\r\n{value}\r\n'.encode()
        )
    for name, data in files.items():
        parts.append(
            f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"; '
            f'filename="{name}.png"\r\nContent-Type: image/png\r\n\r\n'.encode()
            + data
            + b"\r\n"
        )
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), {"Content-Type": f"multipart/form-data; boundary={boundary}"}


def vm_hwm_mib(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def calibration():
    def camera(position, angles):
        return {
            "image_size": [SIDE, SIDE],
            "pixel_size": [0.012, 0.012],
            "position": position,
            "angles": angles,
            "principal_distance": 50,
            "media": {
                "walls": [{"n": 1.5, "thickness": 10}],
                "n_object": 1.33,
                "glass_vector": [0, 0, 100],
            },
        }

    return {"cameras": [camera([0, 0, 600], [0, 0, 0]), camera([300, 0, 520], [0, 0.5, 0])]}


def run_case(ptv, work, workers, case, image, blank):
    data = os.path.join(work, f"data-{case}-{workers}")
    shutil.rmtree(data, ignore_errors=True)
    server = subprocess.Popen(
        [ptv, "serve", "--bind", "127.0.0.1:0", "--data-dir", data, "--workers", str(workers)],
        stdout=subprocess.PIPE,
        stderr=open(os.path.join(work, f"server-{case}-{workers}.log"), "w"),
        text=True,
    )
    try:
        address = None
        for line in server.stdout:
            m = re.search(r"http://127\.0\.0\.1:\d+", line)
            if m:
                address = m.group(0)
                break
        if address is None:
            raise SystemExit("the server printed no address")
        api = address + "/api/v1"
        status, body = post_json(api + "/calibrations", calibration())
        assert status == 201, body
        sequence = {"calibration_id": body["id"], "name": case}
        if case in ("checkerboard", "ridges"):
            sequence["detection"] = {"threshold": 1, "min_pixels": 1, "min_snr": 0}
        if case == "ridges":
            sequence["detection"]["highpass_radius"] = 0
        status, body = post_json(api + "/sequences", sequence)
        assert status == 201, body
        seq = body["id"]
        idle = vm_hwm_mib(server.pid)
        started = time.monotonic()
        statuses = []
        if case in ("preprocessed", "iccp", "ztxt", "itxt"):
            for route in ("mask", "background"):
                form, headers = multipart({}, {"cam0": image})
                status, _ = request("POST", f"{api}/sequences/{seq}/{route}", form, headers)
                statuses.append(f"{route} {status}")
        jobs = []
        for frame in (1, 2):
            form, headers = multipart({"frame": frame}, {"cam0": image, "cam1": blank})
            status, body = request("POST", f"{api}/sequences/{seq}/frames", form, headers)
            statuses.append(f"frame {frame} {status}")
            if status == 202:
                jobs.append(json.loads(body)["job_id"])
        states = []
        for job in jobs:
            while True:
                _, body = request("GET", f"{api}/jobs/{job}")
                view = json.loads(body)
                if view["state"] in ("succeeded", "failed"):
                    error = (view.get("error") or "")[:90]
                    states.append(f"{view['state']}({view.get('attempts')}) {error}".strip())
                    break
                if server.poll() is not None:
                    states.append("server died")
                    break
                time.sleep(0.2)
        seconds = time.monotonic() - started
        peak = vm_hwm_mib(server.pid) if server.poll() is None else float("nan")
        return idle, peak, statuses, states, seconds
    finally:
        server.terminate()
        server.wait()
        shutil.rmtree(data, ignore_errors=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ptv", default="target/release/ptv")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--work", default=None)
    parser.add_argument("--bomb-gib", type=int, default=8)
    parser.add_argument("--cases", default="plain,preprocessed,iccp,ztxt,itxt,checkerboard,ridges")
    args = parser.parse_args()
    cases = args.cases.split(",")
    work = args.work or tempfile.mkdtemp(prefix="ptv-hostile-")
    os.makedirs(work, exist_ok=True)
    print(f"making the images ({SIDE}x{SIDE} 16-bit, bombs of {args.bomb_gib} GiB) ...", flush=True)
    made = images(cases, args.bomb_gib)
    for case in cases:
        print(f"  {case}: {len(made[case]):,} bytes", flush=True)
    print("case\tworkers\tidle MiB\tpeak MiB\tpeak-idle\tuploads\tjobs\tseconds", flush=True)
    for workers in args.workers:
        for case in cases:
            idle, peak, statuses, states, seconds = run_case(
                args.ptv, work, workers, case, made[case], made["blank"]
            )
            print(
                f"{case}\t{workers}\t{idle:.0f}\t{peak:.0f}\t{peak - idle:.0f}\t"
                f"{'; '.join(statuses)}\t{' | '.join(states)}\t{seconds:.1f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())

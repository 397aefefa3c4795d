#!/usr/bin/env python3
"""Reads ptv's exports with the readers labs use (issue 34).

    python3 scripts/check_exports.py DIR [DIR ...]

For each directory: every `*.vtp` with VTK's own XML reader
(`vtkXMLPolyDataReader`: its error code must be 0, and its points,
vertices and lines must be the counts the file's `<Piece>` declares, each
point array as long as the points), every `*.pvd` with
`vtkXMLGenericDataObjectReader`'s sibling for collections
(`vtkPVDReader` where VTK has it; otherwise each DataSet's file is read
as above and its timestep checked to be a number), and every `*.h5` with
h5py and pandas: the trajectories table's columns all of one length,
each with `units` and `description` attributes, read into a DataFrame;
and per frame group of `/particles` the same.

A zip of the API's `?format=pvd` is unpacked into a temporary directory
first.

Exit status 0 when every file reads; 1 when one does not (the reason is
printed); 0 with a message "skipped" when `vtk` or `h5py`/`pandas` is not
installed (e.g. `python3 -m venv /tmp/v && /tmp/v/bin/pip install vtk h5py
pandas`), so that a machine without them is not a failure.
"""

import os
import sys
import tempfile
import xml.etree.ElementTree as ET
import zipfile


def declared_counts(path):
    """The `<Piece>` counts a .vtp declares: points, verts, lines."""
    root = ET.parse(path).getroot()
    piece = root.find("PolyData/Piece")
    return tuple(
        int(piece.get(name, "0"))
        for name in ("NumberOfPoints", "NumberOfVerts", "NumberOfLines")
    )


def check_vtp(vtk, path):
    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(path)
    reader.Update()
    if reader.GetErrorCode() != 0:
        raise ValueError(f"VTK's reader error code {reader.GetErrorCode()}")
    data = reader.GetOutput()
    got = (data.GetNumberOfPoints(), data.GetNumberOfVerts(), data.GetNumberOfLines())
    want = declared_counts(path)
    if got != want:
        raise ValueError(f"VTK read points/verts/lines {got}, the file declares {want}")
    arrays = data.GetPointData()
    names = []
    for i in range(arrays.GetNumberOfArrays()):
        array = arrays.GetArray(i)
        names.append(array.GetName())
        if array.GetNumberOfTuples() != got[0]:
            raise ValueError(
                f"point array {array.GetName()} has {array.GetNumberOfTuples()} tuples, "
                f"the points are {got[0]}"
            )
    return f"{got[0]} points, {got[1]} verts, {got[2]} lines; arrays {', '.join(names)}"


def check_pvd(vtk, path):
    root = ET.parse(path).getroot()
    if root.get("type") != "Collection":
        raise ValueError(f"a .pvd of type {root.get('type')!r}, not 'Collection'")
    sets = root.findall("Collection/DataSet")
    if not sets:
        raise ValueError("no DataSet")
    base = os.path.dirname(path)
    steps = []
    for s in sets:
        steps.append(float(s.get("timestep")))
        check_vtp(vtk, os.path.join(base, s.get("file")))
    if steps != sorted(steps):
        raise ValueError("timesteps out of order")
    if hasattr(vtk, "vtkPVDReader"):
        # ParaView's own reader, where this VTK build has it.
        reader = vtk.vtkPVDReader()
        reader.SetFileName(path)
        reader.UpdateInformation()
    return f"{len(sets)} time steps {steps[0]:g}..{steps[-1]:g}, each .vtp read"


def check_h5(h5py, pd, path):
    with h5py.File(path, "r") as f:
        attrs = {k: f.attrs[k] for k in f.attrs}
        table = f["trajectories"]
        lengths = {k: table[k].shape[0] for k in table}
        if len(set(lengths.values())) > 1:
            raise ValueError(f"trajectory columns of different lengths: {lengths}")
        for k in table:
            missing = [a for a in ("units", "description") if a not in table[k].attrs]
            if missing:
                raise ValueError(f"trajectories/{k} has no {', '.join(missing)}")
        t = pd.DataFrame({k: table[k][()] for k in table})
        frames = f["particles/frames"][()]
        particles = 0
        for frame in frames:
            group = f[f"particles/frame_{frame}"]
            p = pd.DataFrame({k: v[()] for k, v in group.items()})
            particles += len(p)
        trajectories = t["trajectory"].nunique() if len(t) else 0
        return (
            f"attrs {sorted(attrs)}; trajectories table {len(t)} rows, {trajectories} "
            f"trajectories, u in {table['u'].attrs['units']!r}; {len(frames)} frames of "
            f"particles, {particles} in all"
        )


def main():
    if len(sys.argv) < 2:
        print(__doc__)
        return 2
    try:
        import vtk
    except ImportError:
        vtk = None
    try:
        import h5py
        import pandas as pd
    except ImportError:
        h5py = pd = None
    if vtk is None and h5py is None:
        print("skipped: neither vtk nor h5py/pandas is installed")
        return 0
    failed = 0
    keep = []
    dirs = []
    for d in sys.argv[1:]:
        if d.endswith(".zip"):
            t = tempfile.TemporaryDirectory()
            keep.append(t)
            with zipfile.ZipFile(d) as z:
                z.extractall(t.name)
            dirs.append(t.name)
        else:
            dirs.append(d)
    for d in dirs:
        for name in sorted(os.listdir(d)):
            path = os.path.join(d, name)
            try:
                if name.endswith(".vtp"):
                    if vtk is None:
                        print(f"{path}: skipped (no vtk)")
                        continue
                    said = check_vtp(vtk, path)
                elif name.endswith(".pvd"):
                    if vtk is None:
                        print(f"{path}: skipped (no vtk)")
                        continue
                    said = check_pvd(vtk, path)
                elif name.endswith(".h5"):
                    if h5py is None:
                        print(f"{path}: skipped (no h5py/pandas)")
                        continue
                    said = check_h5(h5py, pd, path)
                else:
                    continue
                print(f"{path}: ok, {said}")
            except Exception as e:  # every reader's failure is reported
                failed += 1
                print(f"{path}: FAILED: {e}")
    if vtk is not None:
        print(f"vtk {vtk.vtkVersion.GetVTKVersion()}")
    if h5py is not None:
        print(f"h5py {h5py.__version__}, pandas {pd.__version__}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

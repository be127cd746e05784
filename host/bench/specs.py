"""The data ``host report``, ``host realism`` and ``host bench`` measure: the user's own
data specs (CSV manifests or dataset folders, as ``host train --data`` takes) and a
sensor profile, checked before any long work starts.

:func:`check_specs` lists every recording of every spec and raises a
:class:`~host.data.windows.DataError` naming the first missing file (a manifest row's
video or IMU file, a dataset folder's trial, the spec itself); :func:`check_profile`
does the same for the profile. The commands name no recording of their own: the
authors' roboskin clips are measured only through the default specs that
:func:`write_default_specs` builds from the real-data folder
(``python -m host.bench.specs --real-data DIR --out out/specs``, run by ``make bench``).
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from host.data.dataset import DatasetError, atomic_write_text, load_trial, read_index
from host.data.spec_csv import _parse_manifest
from host.data.video import video_frames
from host.data.windows import DataError

__all__ = ["Recording", "recordings", "check_specs", "check_profile", "spec_name",
           "recording_frames", "DEFAULT_SPECS", "write_default_specs"]


@dataclass(frozen=True)
class Recording:
    """One recording a spec lists: a video or image folder (``clip``), a dataset
    trial (``trial``: ``path`` is the folder, ``index`` the trial), an ``.npz`` of
    vectors (``npz``) or a ``sim://`` scene (``sim``)."""

    kind: str
    path: str
    label: str = ""
    start: int = 0
    end: int | None = None
    imu: str | None = None
    index: int = 0

    @property
    def name(self) -> str:
        if self.kind == "trial":
            return f"{Path(self.path).name}/trial {self.index}"
        return self.path if self.kind == "sim" else Path(self.path).name


def recordings(spec, task: str = "texture") -> list[Recording]:
    """The recordings of one data spec, every file checked to exist; a DataError
    names the first that does not (and the manifest row it is on)."""
    p = Path(str(spec)).expanduser()
    if p.suffix.lower() == ".csv":
        if not p.is_file():
            raise DataError(f"no such data spec: {p}")
        return [Recording(r.kind, r.path, r.label, r.start, r.end,
                          None if r.imu_path is None else str(r.imu_path))
                for r in _parse_manifest(p, task)]
    if p.suffix.lower() == ".npz":
        if not p.is_file():
            raise DataError(f"no such data spec: {p}")
        return [Recording("npz", str(p))]
    if p.is_dir():
        if not (p / "dataset.json").is_file():
            raise DataError(f"{p}: a folder spec must be a dataset folder (with dataset.json); "
                            f"to use a folder of videos or images, list them in a CSV "
                            f"manifest (path,label)")
        try:
            index = read_index(p, check_files=True)
        except DatasetError as exc:
            raise DataError(str(exc)) from None
        if not index["trials"]:
            raise DataError(f"{p}: the dataset has no trials")
        return [Recording("trial", str(p), str(e.get("texture") or e.get("scene") or ""),
                          0, int(e["frames"]), None, i) for i, e in enumerate(index["trials"])]
    raise DataError(f"no such data spec: {p} (a .csv manifest or a dataset folder)")


def check_specs(specs, task: str = "texture") -> dict[str, list[Recording]]:
    """{spec: its recordings} for every spec; the first missing file is a DataError."""
    specs = [str(s) for s in specs]
    if not specs:
        raise DataError("no data specs given")
    return {s: recordings(s, task) for s in specs}


def check_profile(profile) -> str:
    """``profile`` (a built-in name or a profile TOML) when it exists and has vision
    parameters; else a DataError naming it."""
    from host.localiser.samples import vision_params_for

    profile = str(profile)
    if profile.endswith(".toml") and not Path(profile).expanduser().is_file():
        raise DataError(f"--profile: no such file: {profile}")
    try:
        vision_params_for(profile)
    except ValueError as exc:
        raise DataError(f"--profile {profile}: {exc}") from None
    return profile


def spec_name(spec) -> str:
    """A short key for a spec: its file or folder name without the suffix."""
    return Path(str(spec)).stem or "data"


def recording_frames(rec: Recording, limit: int | None = None) -> list[np.ndarray]:
    """Frames ``start`` .. ``end`` of a recording (at most ``limit``); an ``.npz`` of
    vectors and a ``sim://`` scene have none here."""
    end = rec.end if limit is None else min(rec.end or rec.start + limit, rec.start + limit)
    if rec.kind == "clip":
        return video_frames(rec.path, end)[rec.start:]
    if rec.kind == "trial":
        frames = load_trial(rec.path, rec.index)["frames"]
        return list(frames[rec.start:end])
    return []


#: the authors' default specs under the real-data folder: spec -> rows
#: (file under roboskin/, label, IMU file or None). The report's two texture
#: sections, the realism pairs and the bench tables' recordings.
DEFAULT_SPECS = {
    "lego-vs-smooth": [("lego_train.avi", "lego", None), ("smooth.avi", "smooth", None)],
    "concrete-vs-smooth": [("concrete.avi", "concrete", None), ("smooth.avi", "smooth", None)],
    "realism": [("smooth.avi", "smooth", None), ("concrete.avi", "concrete", None)],
    "bench": [("smooth.avi", "smooth", None), ("concrete.avi", "concrete", "concrete_gyro.npy")],
}


def write_default_specs(real_data, out_dir) -> dict[str, Path]:
    """Write :data:`DEFAULT_SPECS` as CSV manifests (absolute paths into
    ``real_data``/roboskin) under ``out_dir``; {name: path}. A missing file is a
    DataError naming it."""
    root = (Path(real_data).expanduser() / "roboskin").resolve()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for name, rows in DEFAULT_SPECS.items():
        imu = any(g for _, _, g in rows)
        lines = ["path,label" + (",imu" if imu else "")]
        for clip, label, gyro in rows:
            for f in (clip, gyro):
                if f and not (root / f).is_file():
                    raise DataError(f"--real-data: no such file: {root / f}")
            lines.append(f"{root / clip},{label}"
                         + (f",{root / gyro if gyro else ''}" if imu else ""))
        path = out / f"{name}.csv"
        atomic_write_text(path, "\n".join(lines) + "\n")
        written[name] = path
    return written


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m host.bench.specs",
                                description="write the authors' default data specs (CSV "
                                            "manifests of the roboskin clips)")
    p.add_argument("--real-data", required=True, help="folder holding roboskin/")
    p.add_argument("--out", default="out/specs", help="folder for the CSV manifests")
    args = p.parse_args(argv)
    try:
        written = write_default_specs(args.real_data, args.out)
    except DataError as exc:
        print(f"host.bench.specs: {exc}", file=sys.stderr)
        return 2
    for name, path in written.items():
        print(f"{name}: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Recordings: what a trial or a window was recorded from, and with which sensor profile.

A *recording* is one continuous take of the sensor: a video file, a folder of images,
a simulated run (scene + seed) or a live session. Windows of one recording share its
lighting, exposure, frame rate and lost pins, so a model can learn the recording
instead of the surface; held-out sets and bootstrap intervals group windows by it
(:mod:`host.data.splits`, :mod:`host.learn.metrics`).

Each recording has an ``id``:

* a file or folder: ``"NAME sha256:HEX16"``: its name and the first 16 hex digits of
  the SHA-256 of its content (a folder: of its files' names and contents), so one clip
  copied to two places is one recording, and an edited clip is another;
* a simulated run: ``"simulated:SCENE seed N"``;
* a live camera: ``"live:URL at ISO-TIME"``.

:func:`profile_ref` names a sensor profile with the SHA-256 of its parsed content
(the canonical JSON of its TOML tables, so comments and key order do not change it).
"""
from __future__ import annotations

import hashlib
import json
import sys
import time
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10 on Raspberry Pi OS bookworm
    import tomli as tomllib

__all__ = ["file_sha256", "file_recording", "sim_recording", "live_recording",
           "source_recording", "profile_ref", "recording_id"]

_CHUNK = 1 << 20
_hash_cache: dict[tuple, str] = {}


def file_sha256(path: Path | str) -> str:
    """SHA-256 (hex) of a file's bytes, or of a folder's files (sorted names and
    contents); cached per path, size and modification time."""
    p = Path(path)
    st = p.stat()
    key = (str(p.resolve()), st.st_size, st.st_mtime_ns)
    hit = _hash_cache.get(key)
    if hit is not None:
        return hit
    h = hashlib.sha256()
    files = sorted(f for f in p.iterdir() if f.is_file()) if p.is_dir() else [p]
    for f in files:
        if p.is_dir():
            h.update(f.name.encode() + b"\0")
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(_CHUNK), b""):
                h.update(chunk)
    _hash_cache[key] = h.hexdigest()
    return _hash_cache[key]


def recording_id(name: str, sha256: str) -> str:
    return f"{name} sha256:{sha256[:16]}"


def file_recording(path: Path | str) -> dict:
    """The recording of a video file or an image folder: ``id``, ``file`` (its name)
    and ``sha256``."""
    p = Path(path)
    sha = file_sha256(p)
    return {"id": recording_id(p.name, sha), "file": p.name, "sha256": sha}


def sim_recording(scene: str, seed: int) -> dict:
    """The recording of a simulated run: ``id`` ``simulated:SCENE seed N``."""
    name = Path(str(scene)).stem if str(scene).endswith(".toml") else str(scene)
    return {"id": f"simulated:{name} seed {int(seed)}", "scene": name, "seed": int(seed)}


def live_recording(url: str, t_wall: float | None = None) -> dict:
    """A live camera's recording: one per session, named by the URL and start time."""
    t = time.gmtime(time.time() if t_wall is None else t_wall)
    return {"id": f"live:{url} at {time.strftime('%Y-%m-%dT%H:%M:%SZ', t)}"}


def source_recording(url: str, t_wall: float | None = None) -> dict:
    """The recording behind a camera source string: a file or folder (with its
    checksum), ``sim://SCENE?seed=N``, or a live camera."""
    s = str(url)
    if s.startswith("sim://"):
        parts = urlsplit(s)
        q = dict(parse_qsl(parts.query))
        try:
            seed = int(q.get("seed", 0))
        except ValueError:
            seed = 0
        return sim_recording(parts.netloc + parts.path, seed)
    path = s[len("file://"):] if s.startswith("file://") else s
    path = path.split("?", 1)[0]
    if "://" not in path and Path(path).exists():
        return file_recording(path)
    return live_recording(s, t_wall)


def profile_ref(profile: str | Path) -> dict:
    """``{"name", "sha256"}`` of a sensor profile (a built-in name or a ``.toml``
    path); ``sha256`` is None when the profile cannot be read."""
    from device.profile import PROFILE_DIR
    p = Path(str(profile))
    if p.suffix != ".toml":
        p = PROFILE_DIR / f"{profile}.toml"
    try:
        doc = tomllib.loads(p.read_text())
    except (OSError, tomllib.TOMLDecodeError):
        return {"name": str(profile), "sha256": None}
    canon = json.dumps(doc, sort_keys=True, separators=(",", ":"), default=str).encode()
    return {"name": str(profile), "sha256": hashlib.sha256(canon).hexdigest()}

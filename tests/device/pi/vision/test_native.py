"""device/pi/vision/native.py: the compiled matching kernel gives the numpy
matcher's assignment, builds atomically, and falls back to numpy when it cannot load."""

from __future__ import annotations

import json
import os
import shutil
import stat
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from device.pi.vision import matching, native
from tests.realdata import real_data_dir

needs_cc = pytest.mark.skipif(shutil.which(os.environ.get("CC", "cc")) is None,
                              reason="no C compiler here: the tracker runs on numpy")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """The library built into a private folder (not the package's): its path."""
    if shutil.which(os.environ.get("CC", "cc")) is None:
        pytest.skip("no C compiler here: the tracker runs on numpy")
    return native.build(folder=tmp_path_factory.mktemp("native"))


@pytest.fixture
def loaded(built, monkeypatch):
    """The tracker runs compiled: the package's library when pip built it, else the
    private build (through TACFOOT_NATIVE_DIR, as the developer's build is found)."""
    if not native.active():
        monkeypatch.setenv("TACFOOT_NATIVE_DIR", str(built.parent))
        assert native.load() is not None, native.status()
    yield
    if os.environ.get("TACFOOT_NATIVE_DIR") == str(built.parent):
        monkeypatch.delenv("TACFOOT_NATIVE_DIR")
        native.load()


@pytest.fixture(scope="module")
def compiled(built):
    """The kernel's function, from the library built into a private folder."""
    return native.kernel(built)


def run_c(fn, r, c, gate):
    r = np.ascontiguousarray(r, np.float64).reshape(-1, 2)
    c = np.ascontiguousarray(c, np.float64).reshape(-1, 2)
    idx = np.full(r.shape[0], -1, np.int64)
    assert fn(r.ctypes.data, r.shape[0], c.ctypes.data, c.shape[0], gate * gate, idx.ctypes.data) == 0
    return idx


def run_numpy(r, c, gate, monkeypatch):
    with monkeypatch.context() as mp:
        mp.setattr(native, "_FN", None)
        return matching.match_pins_unchecked(np.asarray(r, np.float64).reshape(-1, 2),
                                             np.asarray(c, np.float64).reshape(-1, 2), gate)


def is_greedy(r, c, gate, idx):
    """One to one, inside the gate, and no free pair shorter than a taken one
    (no blocking pair): what greedy-by-distance gives, whatever its tie order."""
    hit = idx >= 0
    if len(set(idx[hit].tolist())) != int(hit.sum()):
        return False
    if not (r.size and c.size):
        return not hit.any()
    d2 = ((r[:, None, :] - c[None, :, :]) ** 2).sum(-1)
    mine = np.where(hit, d2[np.arange(len(r)), np.maximum(idx, 0)], np.inf)
    used = np.zeros(len(c), bool)
    used[idx[hit]] = True
    theirs = np.full(len(c), np.inf)
    for i in np.flatnonzero(hit):
        theirs[idx[i]] = mine[i]
    within = d2 <= gate * gate
    # a pair (i, j) within the gate that both ends would rather have blocks the answer
    block = within & (d2 < mine[:, None]) & (d2 < theirs[None, :])
    return bool((d2[hit.nonzero()[0], idx[hit]] <= gate * gate).all()) and not block.any()


coords = st.floats(-50, 50, allow_nan=False, allow_infinity=False)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(r=st.lists(st.tuples(coords, coords), max_size=40), c=st.lists(st.tuples(coords, coords), max_size=40),
       gate=st.floats(0.01, 60), grid=st.sampled_from([0, 1, 4]))
def test_the_kernel_gives_the_numpy_assignment(compiled, monkeypatch, r, c, gate, grid):
    """Every pair set up to 40 x 40 points, including points rounded onto a grid
    (exact ties, duplicates): the same idx as the numpy matcher, to the element."""
    r = np.array(r, np.float64).reshape(-1, 2)
    c = np.array(c, np.float64).reshape(-1, 2)
    if grid:
        r, c = np.round(r / grid) * grid, np.round(c / grid) * grid
    np.testing.assert_array_equal(run_c(compiled, r, c, gate), run_numpy(r, c, gate, monkeypatch))


@pytest.mark.parametrize("n", [0, 1, 133, 700, 2000])
def test_large_layouts_match_as_numpy_does(compiled, monkeypatch, n):
    """A jittered hexagonal layout moved by up to a third of a pitch (the tracker's
    case, numpy's cell-grid path above 4096 pairs): the same idx."""
    rng = np.random.default_rng(n)
    side = max(int(np.ceil(np.sqrt(n))), 1)
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n].astype(float)
    g[:, 0] += 0.5 * (g[:, 1] % 2)
    ref = g * 12.0 + 40.0
    cur = ref + rng.normal(0, 2.5, ref.shape)
    cur = cur[rng.permutation(n)][: max(n - n // 20, 0)]          # 5 % missing, shuffled
    for gate in (2.4, 4.8, 12.0, 30.0):
        idx = run_c(compiled, ref, cur, gate)
        np.testing.assert_array_equal(idx, run_numpy(ref, cur, gate, monkeypatch))
        assert is_greedy(ref, cur, gate, idx)


def test_ties_on_a_large_set_still_give_a_greedy_answer(compiled):
    """Integer points on a crowded grid: the tie order is the one freedom the
    contract leaves, so the answer is checked as a greedy answer."""
    rng = np.random.default_rng(3)
    r = rng.integers(0, 30, (150, 2)).astype(float)
    c = rng.integers(0, 30, (150, 2)).astype(float)
    for gate in (1.0, 1.5, 3.0):
        assert is_greedy(r, c, gate, run_c(compiled, r, c, gate))


def test_far_points_and_coordinates_at_the_bound(compiled, monkeypatch):
    """References far outside the current points' box, and points at +-1e6 px."""
    r = np.array([[-1e6, -1e6], [1e6, 1e6], [0.0, 0.0], [5e5, -5e5], [3.0, 4.0]])
    c = np.array([[1e6, 1e6 - 1.0], [-1e6 + 0.5, -1e6], [3.0, 4.5]])
    for gate in (0.1, 1.0, 2.0, 1e7):
        np.testing.assert_array_equal(run_c(compiled, r, c, gate), run_numpy(r, c, gate, monkeypatch))
    np.testing.assert_array_equal(run_c(compiled, r, c, 1.0), [1, 0, -1, -1, 2])


def test_a_broken_or_foreign_library_is_not_loaded(tmp_path, monkeypatch):
    """A file at the library's name that is not a library: load() returns None and
    says why, and match_pins still answers (numpy)."""
    monkeypatch.setenv("TACFOOT_NATIVE_DIR", str(tmp_path))
    native.library_path().write_bytes(b"not a shared object")
    try:
        assert native.load() is None
        assert not native.active()
        assert "does not load" in native.status()
        assert native.refused() == f"{native.library_path()} is not an ELF library (19 bytes)"
        idx = matching.match_pins([[0.0, 0.0], [10.0, 0.0]], [[10.5, 0.0], [0.2, 0.0]], 1.0)
        np.testing.assert_array_equal(idx, [1, 0])
    finally:
        monkeypatch.delenv("TACFOOT_NATIVE_DIR")
        native.load()


def test_disabled_by_the_environment_and_reported(tmp_path):
    env = dict(os.environ, TACFOOT_NATIVE="0")
    run = subprocess.run([sys.executable, "-m", "device.pi.vision.native", "status"],
                         capture_output=True, text=True, env=env, timeout=60)
    assert run.returncode == 1
    assert "disabled by TACFOOT_NATIVE=0" in run.stdout


def test_no_compiler_is_one_clear_error_and_nothing_written(tmp_path):
    with pytest.raises(native.NativeBuildError, match="no C compiler 'no-such-cc-here'"):
        native.build(folder=tmp_path, cc="no-such-cc-here")
    assert list(tmp_path.iterdir()) == []


@needs_cc
def test_a_failed_compile_leaves_no_file(tmp_path):
    fake = tmp_path / "failcc"
    fake.write_text("#!/bin/sh\necho 'broken compiler' >&2\nexit 1\n")
    fake.chmod(0o755)
    out = tmp_path / "lib"
    with pytest.raises(native.NativeBuildError, match="broken compiler"):
        native.build(folder=out, cc=str(fake))
    assert list(out.iterdir()) == []


@needs_cc
def test_build_names_the_library_by_source_and_machine_and_reuses_it(tmp_path):
    path = native.build(folder=tmp_path)
    assert path.parent == tmp_path and path.name.startswith("_match-") and path.suffix == ".so"
    mtime = path.stat().st_mtime_ns
    assert native.build(folder=tmp_path) == path and path.stat().st_mtime_ns == mtime
    assert native.build(folder=tmp_path, force=True) == path


def test_the_marker_pipeline_is_identical_with_and_without_the_kernel(loaded, monkeypatch):
    """A real clip, 150 frames: the same pins, vectors and lost flags to the bit."""
    data = real_data_dir("roboskin/smooth.avi")
    import cv2

    from device.pi.vision.pipeline import MarkerStream
    cap = cv2.VideoCapture(str(Path(data) / "roboskin" / "smooth.avi"))
    frames = []
    while len(frames) < 150:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY))
    assert len(frames) == 150

    def run():
        s = MarkerStream("roboskin")
        return [s.process(f, i / 120.0) for i, f in enumerate(frames)]

    fast = run()
    monkeypatch.setattr(native, "_FN", None)
    slow = run()
    assert sum(int((~r.lost).sum()) for r in fast) > 100 * 149
    for a, b in zip(fast, slow):
        np.testing.assert_array_equal(a.vectors, b.vectors)
        np.testing.assert_array_equal(a.lost, b.lost)
        np.testing.assert_array_equal(a.pins, b.pins)
        assert a.faults == b.faults


def _grow_both(monkeypatch, r, c, pred, gate, grow_rounds=4, min_support=2, matcher="numpy"):
    """match_and_grow compiled, and in numpy: with the numpy matcher too
    (``matcher="numpy"``), or with the compiled matcher (``"compiled"``: the same
    tie order, so only the growth differs)."""
    from device.pi.vision.neighbours import layout_neighbours, match_and_grow
    nb, valid = layout_neighbours(r, 6)
    fin = np.ones(r.shape[0], bool)
    d_fast = np.zeros_like(r)
    fast = match_and_grow(r, fin, c, pred, nb, valid, gate, grow_rounds, min_support, d_fast)
    with monkeypatch.context() as mp:
        mp.setattr(native, "grow_into", lambda *a: None)
        if matcher == "numpy":
            mp.setattr(native, "_FN", None)
        d_slow = np.zeros_like(r)
        slow = match_and_grow(r, fin, c, pred, nb, valid, gate, grow_rounds, min_support, d_slow)
    return fast, d_fast, slow, d_slow


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 160), drop=st.floats(0, 0.6),
       extra=st.integers(0, 30), jump=st.floats(0, 25), noise=st.floats(0, 4),
       pred_kind=st.sampled_from(["zero", "true", "half", "wrong"]), grow_rounds=st.integers(0, 5),
       min_support=st.integers(1, 4), rounded=st.booleans())
def test_the_compiled_growth_gives_numpys_pins_and_vectors(loaded, monkeypatch, seed, n, drop, extra, jump,
                                                           noise, pred_kind, grow_rounds,
                                                           min_support, rounded):
    """match_and_grow compiled (tf_grow) against numpy on random layouts: pins dropped,
    spurious blobs, a common jump (the shift step), noise, good and bad predictions,
    every growth setting. The same idx, n_confident and displacements, to the bit.
    Points rounded to whole pixels tie exactly, and the numpy matcher may take such
    ties in another order (the matching's contract leaves it open), so those are
    compared with the compiled matcher on both sides."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n)))
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n].astype(float)
    g[:, 0] += 0.5 * (g[:, 1] % 2)
    r = g * 12.0 + 100.0
    move = rng.normal(0, 1.5, r.shape) + rng.normal(0, jump, 2)
    cur = r + move + rng.normal(0, noise, r.shape)
    cur = cur[rng.random(n) >= drop]
    cur = np.concatenate([cur, rng.uniform(80, 100 + 12 * side, (extra, 2))])
    cur = cur[rng.permutation(len(cur))]
    if rounded:
        cur, r = np.round(cur), np.round(r)
    pred = {"zero": np.zeros_like(r), "true": move.copy(), "half": 0.5 * move,
            "wrong": rng.normal(0, 6, r.shape)}[pred_kind]
    if len(cur) == 0:
        return
    (i1, c1), d1, (i2, c2), d2 = _grow_both(monkeypatch, r, cur, pred, 0.4 * 12.0, grow_rounds,
                                            min_support, "compiled" if rounded else "numpy")
    np.testing.assert_array_equal(i1, i2)
    assert c1 == c2
    np.testing.assert_array_equal(d1, d2)


def test_the_compiled_growth_falls_back_for_positions_beyond_the_bound(loaded, monkeypatch):
    """A prediction that puts a pin beyond 1e6 px: the kernel declines and numpy answers."""
    r = np.array([[0.0, 0.0], [12.0, 0.0], [6.0, 10.0], [18.0, 10.0]])
    pred = np.zeros_like(r)
    pred[0] = 2e6
    from device.pi.vision.neighbours import layout_neighbours
    nb, valid = layout_neighbours(r, 3)
    assert native.grow_into(r, r.copy(), pred, nb, valid, 4.8, 4, 2, 4, np.zeros_like(r)) is None
    (i1, c1), d1, (i2, c2), d2 = _grow_both(monkeypatch, r, r.copy(), pred, 4.8)
    np.testing.assert_array_equal(i1, i2)
    np.testing.assert_array_equal(d1, d2)
    assert (i1[1:] == [1, 2, 3]).all()


# --- a library that is there but must not be loaded (issue 29, items 1, 9 and 10) ---

def _env(folder, **more) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "TACFOOT_NATIVE"}
    return dict(env, TACFOOT_NATIVE_DIR=str(folder), **more)


def _place(built: Path, folder: Path, data: bytes) -> Path:
    """``data`` at the library's name in ``folder`` (what TACFOOT_NATIVE_DIR names)."""
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / built.name
    out.write_bytes(data)
    return out


def _run_leg(folder: Path, tmp_path: Path):
    """``device.pi run`` on sim:// for 20 frames with the library folder ``folder``:
    the process, its JSON summary (or None) and its status file's tracker block."""
    status = tmp_path / "status.json"
    run = subprocess.run([sys.executable, "-m", "device.pi", "run", "--camera", "sim://walk",
                          "--imu", "sim://walk", "--serial", "loop://", "--frames", "20", "--json",
                          "--status", str(status)],
                         capture_output=True, text=True, env=_env(folder), timeout=120)
    summary = json.loads(run.stdout) if run.returncode == 0 else None
    tracker = json.loads(status.read_text())["tracker"] if status.exists() else None
    return run, summary, tracker


def _other_machine() -> tuple[int, str]:
    """An e_machine this machine is not: aarch64, or x86_64 on an aarch64 machine."""
    return (62, "x86_64") if native._this_machine()[2] == 183 else (183, "aarch64")


def test_every_cut_of_a_real_library_is_refused_without_loading_it(built, tmp_path):
    """The built library cut at every 61st length and at 1,000, 8,192, 20,000 and
    len-1 bytes: check_library gives a one-line reason for each (a structural read:
    loading one of these would kill this process with SIGBUS); the whole file passes."""
    data = built.read_bytes()
    assert native.check_library(built) is None
    cuts = sorted({*range(0, len(data), 61), 1000, 8192, 20000, len(data) - 1})
    for n in cuts:
        cut = _place(built, tmp_path, data[:n])
        why = native.check_library(cut)
        assert why is not None and "\n" not in why, n
        if n >= 64:
            assert why.startswith("is cut short: ") and why.endswith(f"the file has {n} bytes"), why


@pytest.mark.parametrize("cut", [1000, 8192, 20000, -1])
def test_a_cut_library_runs_the_leg_on_numpy_with_one_line(built, tmp_path, cut):
    """A library cut short in TACFOOT_NATIVE_DIR (a build interrupted by a power cut):
    the runtime and `host --help` exit 0 (before: SIGBUS, exit 135, no message); the
    runtime says in one line on stderr that the kernel is not loaded and why, and the
    status file's tracker block carries the reason."""
    data = built.read_bytes()
    n = len(data) + cut if cut < 0 else cut
    folder = tmp_path / "lib"
    lib = _place(built, folder, data[:n])
    run, summary, tracker = _run_leg(folder, tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    assert summary["frames"] == 20
    lines = run.stderr.splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("device.pi run: warning: the tracker's compiled kernel is not loaded: "
                               f"{lib} is cut short: ")
    assert f"the file has {n} bytes; the tracker runs on numpy" in lines[0]
    assert tracker["matcher"] == "numpy"
    assert f"{lib} is cut short: " in tracker["matcher_reason"]
    helped = subprocess.run([sys.executable, "-m", "host", "--help"], capture_output=True, text=True,
                            env=_env(folder), timeout=60)
    assert helped.returncode == 0 and "usage:" in helped.stdout, helped.stderr[-2000:]
    assert lib.read_bytes() == data[:n]                 # reported, not touched


def test_a_cut_library_is_rebuilt_by_native_build(built, tmp_path):
    data = built.read_bytes()
    lib = _place(built, tmp_path, data[:8192])
    run = subprocess.run([sys.executable, "-m", "device.pi.vision.native", "build"],
                         capture_output=True, text=True, env=_env(tmp_path), timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip() == f"built {lib}"
    assert native.check_library(lib) is None and lib.stat().st_size > 8192


def test_a_library_for_another_cpu_says_so(built, tmp_path):
    """The library with its ELF header's e_machine patched to another CPU: refused
    before loading, with both CPUs named (before: no line at start, the status said
    numpy with no reason, and the loader's message was 'No such file or directory')."""
    other, name = _other_machine()
    data = bytearray(built.read_bytes())
    data[18:20] = other.to_bytes(2, sys.byteorder)
    folder = tmp_path / "lib"
    lib = _place(built, folder, bytes(data))
    here = native._machine_name(native._this_machine()[2])
    assert native.check_library(lib) == f"built for {name}, this machine is {here}"
    run, summary, tracker = _run_leg(folder, tmp_path)
    assert run.returncode == 0 and summary["frames"] == 20, run.stderr[-2000:]
    assert run.stderr.splitlines() == [
        f"device.pi run: warning: the tracker's compiled kernel is not loaded: {lib} built for "
        f"{name}, this machine is {here}; the tracker runs on numpy (rebuild: python -m "
        "device.pi.vision.native build)"]
    assert tracker["matcher"] == "numpy"
    assert f"built for {name}, this machine is {here}" in tracker["matcher_reason"]
    assert "No such file" not in run.stderr + tracker["matcher_reason"]


@pytest.mark.parametrize("offset, value, why", [
    (0, b"\x7fELG", "is not an ELF library"),
    (4, bytes([1 if struct.calcsize("P") == 8 else 2]), "-bit library, this Python is "),
    (5, bytes([2 if sys.byteorder == "little" else 1]), "-endian, this machine is "),
    (16, (2).to_bytes(2, sys.byteorder), "is not a shared library (ELF type 2)"),
    (58, (63).to_bytes(2, sys.byteorder), "63-byte section headers"),
])
def test_a_patched_header_is_refused_with_its_reason(built, tmp_path, offset, value, why):
    """Another word size, byte order, file type or header layout: one line, never loaded."""
    data = bytearray(built.read_bytes())
    data[offset:offset + len(value)] = value
    assert why in native.check_library(_place(built, tmp_path, bytes(data)))


def test_what_is_not_a_file_is_refused(tmp_path):
    (tmp_path / "dir.so").mkdir()
    assert native.check_library(tmp_path / "dir.so") == "is not a regular file"
    assert native.check_library(tmp_path / "none.so").startswith("cannot be read (")
    (tmp_path / "empty.so").write_bytes(b"")
    assert native.check_library(tmp_path / "empty.so") == "is empty"


@needs_cc
def test_a_library_of_another_abi_is_refused_and_reported(tmp_path, monkeypatch):
    """A well-formed library at the name whose tf_abi_version is not ours: not used,
    and refused() says which ABI it is (the runtime prints it at start)."""
    src = tmp_path / "old.c"
    src.write_text("int tf_abi_version(void) { return 1; }\n")
    monkeypatch.setenv("TACFOOT_NATIVE_DIR", str(tmp_path))
    lib = native.library_path()
    subprocess.run([os.environ.get("CC", "cc"), "-shared", "-fPIC", "-o", str(lib), str(src)],
                   check=True, timeout=60)
    try:
        assert native.check_library(lib) is None
        assert native.load() is None
        assert native.refused() == f"{lib} is ABI 1, expected {native.ABI_VERSION}"
    finally:
        monkeypatch.delenv("TACFOOT_NATIVE_DIR")
        native.load()


def test_not_built_or_disabled_is_not_a_refusal(tmp_path, monkeypatch):
    """No library, or TACFOOT_NATIVE=0: refused() is None and the runtime says nothing."""
    monkeypatch.setenv("TACFOOT_NATIVE_DIR", str(tmp_path))
    try:
        assert native.load() is None and native.refused() is None
        assert native.status().startswith("not built (")
        monkeypatch.setenv("TACFOOT_NATIVE", "0")
        assert native.load() is None and native.refused() is None
    finally:
        monkeypatch.delenv("TACFOOT_NATIVE_DIR")
        monkeypatch.delenv("TACFOOT_NATIVE")
        native.load()
    run, summary, tracker = _run_leg(tmp_path, tmp_path)
    assert run.returncode == 0 and run.stderr == ""
    assert tracker["matcher_reason"].startswith("not built (")


@needs_cc
def test_the_build_syncs_the_library_before_the_rename_and_the_folder_after(tmp_path, monkeypatch):
    """A power cut cannot leave a library cut short: the compiled file is on disk
    before it takes the library's name, and the rename is on disk before build returns."""
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        st = os.fstat(fd)
        events.append(("fsync", st.st_ino, stat.S_ISDIR(st.st_mode)))
        return real_fsync(fd)

    def replace(a, b):
        events.append(("replace", os.stat(a).st_ino, False))
        return real_replace(a, b)

    monkeypatch.setattr(native.os, "fsync", fsync)
    monkeypatch.setattr(native.os, "replace", replace)
    lib = native.build(folder=tmp_path, force=True)
    ino = lib.stat().st_ino
    assert events == [("fsync", ino, False), ("replace", ino, False),
                      ("fsync", tmp_path.stat().st_ino, True)]


def _build_into(folder) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "device.pi.vision.native", "build"],
                          capture_output=True, text=True, env=_env(folder), timeout=120)


def test_a_build_under_a_file_is_one_line_and_exit_2(tmp_path):
    """TACFOOT_NATIVE_DIR below a regular file (the folder cannot be made): one line
    naming the folder, exit 2, nothing written (before: a NotADirectoryError traceback)."""
    (tmp_path / "file").write_text("x")
    folder = tmp_path / "file" / "sub"
    run = _build_into(folder)
    assert run.returncode == 2
    assert run.stderr.splitlines() == [f"native build: error: cannot write the library into "
                                       f"{folder}: Not a directory; the tracker runs on numpy"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_a_build_into_a_read_only_folder_is_one_line_and_exit_2(tmp_path):
    """A folder the build may not write (before: a PermissionError traceback)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        if os.access(folder, os.W_OK):
            pytest.skip("running as root: chmod 0o555 does not make a folder read-only "
                        "(the folder-under-a-file test covers the path)")
        run = _build_into(folder)
        assert run.returncode == 2
        assert run.stderr.splitlines() == [f"native build: error: cannot write the library into "
                                           f"{folder}: Permission denied; the tracker runs on numpy"]
        assert list(folder.iterdir()) == []
    finally:
        folder.chmod(0o755)


# --- the package's own library (issue 30, item 5: pip compiles it, setup.py) ---

@pytest.fixture
def package(tmp_path, monkeypatch):
    """A package folder of its own: the C files copied there, SOURCE and SOURCES
    naming them, no TACFOOT_NATIVE_DIR; load() again afterwards."""
    folder = tmp_path / "vision"
    folder.mkdir()
    for src in native.SOURCES:
        shutil.copy2(src, folder / src.name)
    monkeypatch.delenv("TACFOOT_NATIVE_DIR", raising=False)
    monkeypatch.delenv("TACFOOT_NATIVE", raising=False)
    monkeypatch.setattr(native, "SOURCE", folder / native.SOURCE.name)
    monkeypatch.setattr(native, "SOURCES", tuple(folder / s.name for s in native.SOURCES))
    yield folder
    monkeypatch.undo()
    native.load()


def test_the_packaged_library_is_found_next_to_the_c_files(built, package, monkeypatch):
    """Without TACFOOT_NATIVE_DIR the loader takes _tacfoot_core-<tag>.so next to the
    C files (where pip put it); with it, that folder's library only."""
    lib = native.packaged_path()
    assert lib.parent == package and lib.name.startswith("_tacfoot_core-")
    assert native.library_path() == lib
    shutil.copy2(built, lib)
    assert native.load() is not None and native.status() == f"compiled ({lib})"
    monkeypatch.setenv("TACFOOT_NATIVE_DIR", str(package / "elsewhere"))
    assert native.load() is None and native.refused() is None
    assert native.status().startswith("not built (_match-")
    assert native.status().endswith("; rebuild: python -m device.pi.vision.native build)")


def test_a_library_of_older_c_files_is_not_loaded_and_says_so(built, package, tmp_path):
    """An editable checkout whose C files changed since its install: the library pip
    built then has another tag; it is not loaded, and refused() names it and the file
    these C files need, so the runtime's start line says to reinstall."""
    shutil.copy2(built, native.packaged_path())
    assert native.load() is not None
    old = native.packaged_path()
    with open(native.SOURCE, "a") as f:
        f.write("/* edited since the install */\n")
    new = native.packaged_path()
    assert new != old and native.load() is None
    assert native.refused() == (f"{old} was built from other C files or for another machine "
                                f"(these need {new.name})")
    assert native.status().endswith("(rebuild: reinstall tacfoot where a C compiler is, e.g. "
                                    "pip install . or make install)")
    old.unlink()
    assert native.load() is None and native.refused() is None
    assert native.status() == (f"not built ({new.name} missing; rebuild: reinstall tacfoot where "
                               "a C compiler is, e.g. pip install . or make install)")


def test_native_build_never_writes_into_the_package(tmp_path):
    """Without TACFOOT_NATIVE_DIR, ``native build`` says that pip builds the package's
    library, in one line, exit 2, and writes nothing next to the C files."""
    before = sorted(p.name for p in native.SOURCE.parent.iterdir())
    env = {k: v for k, v in os.environ.items() if not k.startswith("TACFOOT_NATIVE")}
    run = subprocess.run([sys.executable, "-m", "device.pi.vision.native", "build"],
                         capture_output=True, text=True, env=env, timeout=120)
    assert run.returncode == 2
    assert run.stderr.splitlines() == [
        "native build: error: native build writes only into TACFOOT_NATIVE_DIR, which is not "
        "set; the package's own library is compiled by pip install (pip install . or make install)"]
    assert sorted(p.name for p in native.SOURCE.parent.iterdir()) == before

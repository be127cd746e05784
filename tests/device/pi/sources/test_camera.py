"""Camera sources: video files, image folders, the simulator, V4L2 (error path)."""

from __future__ import annotations

import errno
import sys
import time
import types
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from device.pi.sources import camera
from device.pi.sources.camera import (CameraError, Frame, ImageFolderSource, SimSource,
                                      V4L2Source, VideoFileSource, natural_key, open_camera)
from device.pi.sources.luma import yuv_luma_table
from tests.realdata import real_data_dir


W, H, FPS, N = 64, 48, 25.0, 10


def level(i: int) -> int:
    return 20 + 20 * i


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    """A tiny MJPG AVI: frame i is flat gray level(i) with a white square at x = 4i."""
    path = tmp_path_factory.mktemp("clip") / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
    assert writer.isOpened()
    for i in range(N):
        img = np.full((H, W, 3), level(i), np.uint8)
        img[10:20, 4 * i:4 * i + 8] = 255
        writer.write(img)
    writer.release()
    return path


def check_clip_frames(frames, first=0):
    for k, f in enumerate(frames):
        i = first + k
        assert isinstance(f, Frame)
        assert f.index == i
        assert f.t_s == pytest.approx(i / FPS)
        assert f.image.dtype == np.uint8 and f.image.shape == (H, W, 3)
        assert abs(float(np.median(f.image)) - level(i)) < 4      # JPEG is lossy
        assert f.image[15, 4 * i + 4].min() > 200                 # the square moved


# ------------------------------------------------------------------ video files
@pytest.mark.parametrize("form", ["file_url", "bare"])
def test_video_file_reads_all_frames(clip, form):
    src = f"file://{clip}" if form == "file_url" else str(clip)
    with open_camera(src) as cam:
        assert isinstance(cam, VideoFileSource)
        assert (cam.width, cam.height) == (W, H)
        assert cam.fps == pytest.approx(FPS)
        assert cam.n_frames == N
        frames = list(cam)
        assert cam.read() is None                                  # stays at end
    assert len(frames) == N
    check_clip_frames(frames)
    assert cam.closed


def test_video_file_start_end(clip):
    with open_camera(str(clip)) as cam:
        full = [f.image for f in cam]
    with open_camera(f"file://{clip}", start_frame=3, end_frame=7) as cam:
        assert cam.n_frames == 4
        frames = list(cam)
    assert [f.index for f in frames] == [3, 4, 5, 6]
    check_clip_frames(frames, first=3)
    for f in frames:
        np.testing.assert_array_equal(f.image, full[f.index])


def test_video_file_options_in_query_and_kwargs_win(clip):
    with open_camera(f"file://{clip}?start_frame=8&fps=50") as cam:
        frames = list(cam)
    assert [f.index for f in frames] == [8, 9]
    assert frames[0].t_s == pytest.approx(8 / 50)
    with open_camera(f"file://{clip}?start_frame=8", start_frame=9) as cam:
        assert [f.index for f in cam] == [9]


def test_video_file_start_past_end_is_empty(clip):
    with open_camera(str(clip), start_frame=50) as cam:
        assert cam.read() is None
        assert cam.n_frames == 0


def test_frames_are_independent_arrays(clip):
    with open_camera(str(clip)) as cam:
        a, b = cam.read(), cam.read()
    assert not np.shares_memory(a.image, b.image)
    assert abs(float(np.median(a.image)) - level(0)) < 4


def test_read_after_close_raises(clip):
    cam = open_camera(str(clip))
    cam.close()
    cam.close()                                                    # idempotent
    with pytest.raises(ValueError, match="closed"):
        cam.read()


def test_realtime_paces_reads(clip):
    with open_camera(str(clip), fps=100, realtime=True, end_frame=6) as cam:
        t0 = time.monotonic()
        n = sum(1 for _ in cam)
        dt = time.monotonic() - t0
    assert n == 6
    assert dt >= 0.045                                             # 5 intervals of 10 ms


# ------------------------------------------------------------------ image folders
@pytest.fixture()
def folder(tmp_path) -> Path:
    d = tmp_path / "imgs"
    d.mkdir()
    for n in (10, 2, 1, 100, 21):
        cv2.imwrite(str(d / f"image_{n}.png"), np.full((30, 40), n, np.uint8))
    (d / "targets.csv").write_text("id\n")
    (d / "meta.json").write_text("{}")
    return d


@pytest.mark.parametrize("form", ["bare", "bare_slash", "file_url"])
def test_folder_natural_order_and_gray(folder, form):
    src = {"bare": str(folder), "bare_slash": f"{folder}/", "file_url": f"file://{folder}/"}[form]
    with open_camera(src) as cam:
        assert isinstance(cam, ImageFolderSource)
        assert (cam.width, cam.height, cam.fps, cam.n_frames) == (40, 30, None, 5)
        frames = list(cam)
    assert [int(f.image[0, 0]) for f in frames] == [1, 2, 10, 21, 100]
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert [f.t_s for f in frames] == [0.0, 1.0, 2.0, 3.0, 4.0]        # fps unknown: counts frames
    assert all(f.image.shape == (30, 40) and f.image.dtype == np.uint8 for f in frames)


def test_folder_fps_and_range(folder):
    with open_camera(str(folder), fps=10, start_frame=1, end_frame=3) as cam:
        frames = list(cam)
    assert [int(f.image[0, 0]) for f in frames] == [2, 10]
    assert [f.t_s for f in frames] == pytest.approx([0.1, 0.2])


def test_folder_colour_and_alpha(tmp_path):
    bgra = np.zeros((8, 9, 4), np.uint8)
    bgra[..., 0], bgra[..., 3] = 200, 255
    cv2.imwrite(str(tmp_path / "a_1.png"), bgra)
    with open_camera(str(tmp_path)) as cam:
        f = cam.read()
    assert f.image.shape == (8, 9, 3) and f.image[0, 0].tolist() == [200, 0, 0]


def test_folder_size_mismatch_is_an_error(folder):
    cv2.imwrite(str(folder / "image_500.png"), np.zeros((31, 40), np.uint8))
    with open_camera(str(folder)) as cam:
        with pytest.raises(CameraError, match="image_500.png"):
            list(cam)


def test_folder_16bit_is_an_error(tmp_path):
    cv2.imwrite(str(tmp_path / "deep.png"), np.zeros((4, 4), np.uint16))
    with pytest.raises(CameraError, match="uint16"):
        open_camera(str(tmp_path))


def test_single_image_file(folder):
    with open_camera(f"file://{folder}/image_21.png") as cam:
        frames = list(cam)
    assert len(frames) == 1 and int(frames[0].image[0, 0]) == 21


def test_empty_folder_is_an_error(tmp_path):
    with pytest.raises(CameraError, match="no image files") as ei:
        open_camera(str(tmp_path))
    assert str(tmp_path) in str(ei.value)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, 10**12), min_size=1, max_size=30, unique=True))
def test_natural_key_orders_by_number(nums):
    names = [f"image_{n}.png" for n in nums]
    assert sorted(names, key=natural_key) == [f"image_{n}.png" for n in sorted(nums)]


def test_natural_key_mixed_names():
    names = ["b10.png", "a2.png", "a10.png", "A3.png", "b9.png"]
    assert sorted(names, key=natural_key) == ["a2.png", "A3.png", "a10.png", "b9.png", "b10.png"]


# ------------------------------------------------------------------ errors
@pytest.mark.parametrize("src", ["rtsp://cam.local/stream", "http://x/y.avi", "gst://videotestsrc"])
def test_unknown_scheme(src):
    with pytest.raises(ValueError, match="unknown camera source") as ei:
        open_camera(src)
    assert src in str(ei.value)


@pytest.mark.parametrize("src", ["", "   ", None, 3])
def test_empty_or_non_string_source(src):
    with pytest.raises(ValueError, match="camera source"):
        open_camera(src)


@pytest.mark.parametrize("form", ["bare", "file_url"])
def test_missing_file(tmp_path, form):
    p = tmp_path / "nope.avi"
    src = str(p) if form == "bare" else f"file://{p}"
    with pytest.raises(CameraError) as ei:
        open_camera(src)
    assert isinstance(ei.value, OSError)
    assert ei.value.errno == errno.ENOENT
    assert ei.value.filename == str(p)
    assert str(p) in str(ei.value)


def test_missing_folder(tmp_path):
    p = tmp_path / "no_such_dir"
    with pytest.raises(CameraError, match="no_such_dir"):
        open_camera(f"file://{p}/")


def test_not_a_video(tmp_path):
    p = tmp_path / "fake.avi"
    p.write_bytes(b"this is not a video" * 10)
    with pytest.raises(CameraError, match="fake.avi"):
        open_camera(str(p))


def test_unknown_and_bad_options(clip):
    with pytest.raises(ValueError, match="'strat_frame'"):
        open_camera(str(clip), strat_frame=2)
    with pytest.raises(ValueError, match="start_frame.*'two'"):
        open_camera(f"file://{clip}?start_frame=two")
    with pytest.raises(ValueError, match="start_frame.*-1"):
        open_camera(str(clip), start_frame=-1)
    with pytest.raises(ValueError, match="end_frame.*2"):
        open_camera(str(clip), start_frame=5, end_frame=2)
    with pytest.raises(ValueError, match="fps.*-3"):
        open_camera(str(clip), fps=-3)
    with pytest.raises(ValueError, match="realtime.*'maybe'"):
        open_camera(str(clip), realtime="maybe")


# ------------------------------------------------------------------ V4L2
def test_v4l2_missing_device():
    dev = "/dev/video_tacfoot_missing"
    with pytest.raises(CameraError) as ei:
        open_camera(f"v4l2://{dev}?width=640&height=480&fps=120&fourcc=MJPG")
    assert ei.value.errno == errno.ENOENT
    assert dev in str(ei.value)


def test_v4l2_bad_options():
    with pytest.raises(ValueError, match="fourcc.*'MJPEG'"):
        open_camera("v4l2:///dev/video0?fourcc=MJPEG")
    with pytest.raises(ValueError, match="'exposure'"):
        open_camera("v4l2:///dev/video0", exposure=3)
    with pytest.raises(ValueError, match="device"):
        open_camera("v4l2://")


class FakeCapture:
    """Records what V4L2Source asks of cv2.VideoCapture."""

    instances: list = []

    def __init__(self, device, api=None, frames=3, opened=True):
        self.device, self.api, self.calls, self.props = device, api, [], {}
        self.frames, self.opened, self.released = frames, opened, False
        FakeCapture.instances.append(self)

    def isOpened(self):
        return self.opened

    def set(self, prop, value):
        self.calls.append((prop, value))
        self.props[prop] = value
        return True

    def get(self, prop):
        return float(self.props.get(prop, 0))

    def grab(self):
        if self.frames <= 0:
            return False
        self.frames -= 1
        return True

    def retrieve(self):
        h, w = int(self.props[cv2.CAP_PROP_FRAME_HEIGHT]), int(self.props[cv2.CAP_PROP_FRAME_WIDTH])
        return True, np.zeros((h, w, 3), np.uint8)

    def release(self):
        self.released = True


def test_v4l2_sets_properties_and_stamps_monotonic(tmp_path, monkeypatch):
    dev = tmp_path / "video7"
    dev.touch()                                   # stands in for the device node
    FakeCapture.instances = []
    monkeypatch.setattr(camera.cv2, "VideoCapture", FakeCapture)
    before = time.monotonic()
    cam = open_camera(f"v4l2://{dev}?width=640&height=480&fps=120&fourcc=MJPG")
    cap = FakeCapture.instances[-1]
    assert isinstance(cam, V4L2Source)
    assert cap.device == str(dev) and cap.api == cv2.CAP_V4L2
    props = [p for p, _ in cap.calls]
    assert props == [cv2.CAP_PROP_FOURCC, cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT,
                     cv2.CAP_PROP_FPS, cv2.CAP_PROP_BUFFERSIZE]
    assert cap.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter_fourcc(*"MJPG")
    assert cap.props[cv2.CAP_PROP_BUFFERSIZE] == 1
    assert (cam.width, cam.height, cam.fps, cam.fourcc, cam.n_frames) == (640, 480, 120.0, "MJPG", None)
    f0, f1 = cam.read(), cam.read()
    assert (f0.index, f1.index) == (0, 1)
    assert before <= f0.t_s <= f1.t_s <= time.monotonic()
    assert f0.image.shape == (480, 640, 3)
    cam.read()
    with pytest.raises(CameraError, match="grab failed"):         # unplugged: not end of stream
        cam.read()
    cam.close()
    assert cap.released


def test_v4l2_cannot_open(tmp_path, monkeypatch):
    dev = tmp_path / "video9"
    dev.touch()
    monkeypatch.setattr(camera.cv2, "VideoCapture", lambda d, api: FakeCapture(d, api, opened=False))
    with pytest.raises(CameraError, match="video9"):
        open_camera(f"v4l2://{dev}")


# ------------------------------------------------------------------ simulator
class StubSimulator:
    def __init__(self, scene, seed=0):
        self.scene, self.seed = scene, seed
        self.n_frames, self.fps, self.width, self.height = 5, 100.0, 32, 24
        self.truth = {"t_s": np.arange(5) / 100.0, "contact": np.array([0, 1, 1, 1, 0], bool)}

    def render(self, i, out=None):
        if not 0 <= i < self.n_frames:
            raise IndexError(i)
        return np.full((self.height, self.width), i * 10 + self.seed, np.uint8)


@pytest.fixture()
def stub_sim(monkeypatch):
    mod = types.ModuleType("device.sim")
    mod.load_scene = lambda name: {"name": name}
    mod.Simulator = StubSimulator
    monkeypatch.setitem(sys.modules, "device.sim", mod)
    return mod


def test_sim_source_wiring(stub_sim):
    with open_camera("sim://walk?seed=3") as cam:
        assert isinstance(cam, SimSource)
        assert cam.sim.scene == {"name": "walk"} and cam.sim.seed == 3
        assert (cam.width, cam.height, cam.fps, cam.n_frames) == (32, 24, 100.0, 5)
        frames = list(cam)
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert [f.t_s for f in frames] == pytest.approx([0, 0.01, 0.02, 0.03, 0.04])
    assert [int(f.image[0, 0]) for f in frames] == [3, 13, 23, 33, 43]
    assert cam.truth["contact"].tolist() == [False, True, True, True, False]


def test_sim_source_path_and_kwargs(stub_sim):
    with open_camera("sim://scenes/custom.toml", seed=5, start_frame=2, end_frame=4) as cam:
        assert cam.sim.scene == {"name": "scenes/custom.toml"}
        assert [(f.index, int(f.image[0, 0])) for f in cam] == [(2, 25), (3, 35)]
    with pytest.raises(ValueError, match="seed.*'x'"):
        open_camera("sim://walk?seed=x")
    with pytest.raises(ValueError, match="scene"):
        open_camera("sim://")


def test_sim_source_real_simulator():
    with open_camera("sim://walk?seed=1", end_frame=3) as cam:
        frames = list(cam)
        assert cam.n_frames == 3
        sim = cam.sim
    assert len(frames) == 3
    for f in frames:
        assert f.image.dtype == np.uint8 and f.image.shape == (sim.height, sim.width)
        assert f.t_s == pytest.approx(f.index / sim.fps)
        np.testing.assert_array_equal(f.image, sim.render(f.index))


# ------------------------------------------------------------------ real recordings
@pytest.mark.real
def test_real_smooth_avi():
    path = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    with open_camera(f"file://{path}") as cam:
        assert (cam.width, cam.height) == (640, 480)
        assert cam.fps == pytest.approx(200.0)          # declared, not measured
        n, last = 0, None
        for f in cam:
            assert f.index == n
            assert f.image.shape == (480, 640, 3) and f.image.dtype == np.uint8
            n, last = n + 1, f
    assert n == 540
    assert last.t_s == pytest.approx(539 / 200.0)


@pytest.mark.real
def test_real_smooth_avi_window_matches_full_read():
    path = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    with open_camera(str(path), end_frame=12) as cam:
        full = [f.image for f in cam]
    with open_camera(str(path), start_frame=10, end_frame=12) as cam:
        part = list(cam)
    assert [f.index for f in part] == [10, 11]
    for f in part:
        np.testing.assert_array_equal(f.image, full[f.index])


@pytest.mark.real
def test_real_tactip_shear_folder():
    d = real_data_dir("tactip_shear/images") / "tactip_shear" / "images"
    with open_camera(f"file://{d}/") as cam:
        assert (cam.width, cam.height, cam.n_frames) == (445, 440, 400)
        names = [p.name for p in cam.files]
        assert names[:3] == ["image_1.png", "image_16.png", "image_31.png"]
        nums = [int(n[len("image_"):-len(".png")]) for n in names]
        assert nums == sorted(nums)
        first = cam.read()
        assert first.image.shape == (440, 445) and first.image.dtype == np.uint8
        assert set(np.unique(first.image).tolist()) <= {0, 255}         # binarised
        rest = sum(1 for _ in cam)
    assert rest == 399


def test_v4l2_refuses_a_size_the_driver_did_not_take(tmp_path, monkeypatch):
    import cv2

    from device.pi.sources import camera

    class Capture:
        def __init__(self, device, api=None):
            self.props = {}

        def isOpened(self):
            return True

        def set(self, prop, value):
            if prop not in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
                self.props[prop] = value            # the size request is ignored
            return True

        def get(self, prop):
            return {cv2.CAP_PROP_FRAME_WIDTH: 320.0,
                    cv2.CAP_PROP_FRAME_HEIGHT: 240.0}.get(prop, float(self.props.get(prop, 0)))

        def release(self):
            pass

    dev = tmp_path / "video3"
    dev.touch()
    monkeypatch.setattr(camera.cv2, "VideoCapture", Capture)
    with pytest.raises(CameraError, match="320x240, asked for 640x480"):
        open_camera(f"v4l2://{dev}?width=640&height=480&fourcc=YUYV")
    assert open_camera(f"v4l2://{dev}").width == 320          # no size asked: taken as is



def test_a_folder_skips_past_an_unreadable_or_odd_sized_image(tmp_path):
    from device.pi.sources.camera import BadFrameError
    for i in range(5):
        cv2.imwrite(str(tmp_path / f"{i}.png"), np.full((10, 12), 40 * i, np.uint8))
    (tmp_path / "1.png").write_bytes(b"\x89PNG broken")
    cv2.imwrite(str(tmp_path / "3.png"), np.zeros((11, 12), np.uint8))
    cam = open_camera(str(tmp_path))
    got, bad = [], []
    for _ in range(20):                      # bounded: a source that never moves on fails
        try:
            fr = cam.read()
        except BadFrameError as exc:
            bad.append(Path(exc.filename).name)
            continue
        if fr is None:
            break
        got.append((fr.index, int(fr.image[0, 0])))
    assert got == [(0, 0), (2, 80), (4, 160)] and bad == ["1.png", "3.png"]


# ------------------------------------------------------------------ frame-rate bound (issue 21, item 5)
@pytest.mark.parametrize("src", ["sim://walk?fps=1e9", "sim://walk?fps=0.001", "FILE?fps=0.0001",
                                 "v4l2:///dev/video0?fps=5000"])
def test_a_sources_own_frame_rate_has_the_bound_fps_has(clip, src):
    src = src.replace("FILE", f"file://{clip}")
    with pytest.raises(ValueError, match=r"fps must be a finite number in \[1\.0, 1000\.0\]"):
        open_camera(src)
    with pytest.raises(ValueError, match=r"fps.*2000"):
        open_camera(str(clip), fps=2000)            # a keyword too


def _clip_at(path: Path, fps: float) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
    for i in range(3):
        writer.write(np.full((H, W, 3), level(i), np.uint8))
    writer.release()
    return path


def test_a_file_whose_header_rate_is_implausible_is_read_at_the_default(tmp_path, caplog):
    path = _clip_at(tmp_path / "half.avi", 0.5)
    with open_camera(str(path)) as cam:
        assert cam.fps == camera.DEFAULT_FILE_FPS
        frames = list(cam)
    assert frames[2].t_s == pytest.approx(2 / camera.DEFAULT_FILE_FPS)   # not 4 s
    err = "".join(r.getMessage() for r in caplog.records if r.levelname == "WARNING")
    assert err.count("warning") == 1 and "0.5 frames/s" in err and "120 frames/s" in err
    caplog.clear()
    with open_camera(str(path), fps=30) as cam:     # a stated rate: no warning
        assert cam.fps == 30.0
    assert caplog.records == []


def test_a_live_camera_reporting_an_implausible_rate_counts_as_unknown(tmp_path, monkeypatch):
    dev = tmp_path / "video8"
    dev.touch()

    class Odd(FakeCapture):
        def get(self, prop):
            return 1e6 if prop == cv2.CAP_PROP_FPS else super().get(prop)

    monkeypatch.setattr(camera.cv2, "VideoCapture", Odd)
    with open_camera(f"v4l2://{dev}?width=64&height=48") as cam:
        assert cam.fps is None


# ------------------------------------------------------------------ gray from the source
def test_video_file_gray_is_the_pipelines_gray_of_each_frame(clip):
    """gray=True: each frame is HxW uint8, exactly cv2.cvtColor of the frame the colour
    source gives (so the marker pipeline finds the same pins), and a new array."""
    with open_camera(str(clip)) as bgr_cam, open_camera(f"file://{clip}?gray=1") as cam:
        assert cam.gray and not bgr_cam.gray
        frames = list(cam)
        colour = list(bgr_cam)
    assert len(frames) == len(colour) == N
    for f, c in zip(frames, colour):
        assert f.index == c.index and f.t_s == c.t_s
        assert f.image.shape == (H, W) and f.image.dtype == np.uint8
        np.testing.assert_array_equal(f.image, cv2.cvtColor(c.image, cv2.COLOR_BGR2GRAY))
    assert not np.shares_memory(frames[0].image, frames[1].image)
    with open_camera(str(clip), gray=True, start_frame=3, end_frame=5) as cam:
        assert [f.index for f in cam] == [3, 4]
    with pytest.raises(ValueError, match="gray must be a bool"):
        open_camera(f"file://{clip}?gray=maybe")


def test_image_folder_gray(tmp_path):
    rng = np.random.default_rng(3)
    imgs = [rng.integers(0, 256, (12, 16, 3), dtype=np.uint8) for _ in range(3)]
    for i, im in enumerate(imgs):
        cv2.imwrite(str(tmp_path / f"im_{i}.png"), im)
    with open_camera(str(tmp_path) + "/", gray=True) as cam:
        got = [f.image for f in cam]
    assert [g.shape for g in got] == [(12, 16)] * 3
    for g, im in zip(got, imgs):
        np.testing.assert_array_equal(g, cv2.cvtColor(im, cv2.COLOR_BGR2GRAY))


class RawCapture(FakeCapture):
    """A V4L2 capture whose buffers are YUYV / GREY bytes: raw with CONVERT_RGB off,
    decoded to BGR (OpenCV's colour path) with it on."""

    luma = None                    # (h, w) uint8 luma of every frame

    def retrieve(self):
        fourcc = int(self.props[cv2.CAP_PROP_FOURCC])
        y = RawCapture.luma
        h, w = y.shape
        if fourcc == cv2.VideoWriter_fourcc(*"GREY"):
            raw = y.reshape(1, -1).copy()
            bgr = cv2.cvtColor(y, cv2.COLOR_GRAY2BGR)
        else:
            buf = np.empty((h, w, 2), np.uint8)
            buf[:, :, 0] = y
            buf[:, 0::2, 1], buf[:, 1::2, 1] = 125, 131                   # mild chroma
            raw, bgr = buf.reshape(1, -1).copy(), cv2.cvtColor(buf, cv2.COLOR_YUV2BGR_YUYV)
        return True, (raw if self.props.get(cv2.CAP_PROP_CONVERT_RGB, 1) == 0 else bgr)


@pytest.mark.parametrize("fourcc", ["YUYV", "GREY", "MJPG"])
def test_v4l2_gray_hands_over_the_luma_plane(tmp_path, monkeypatch, fourcc):
    """No camera here: a capture that serves synthetic YUYV / GREY buffers. gray=True
    turns OpenCV's colour conversion off for YUYV and GREY and gives the luma plane
    (within a gray level of the colour path's gray, exact for GREY); for MJPG it
    converts the decoded frame."""
    dev = tmp_path / "video3"
    dev.touch()
    RawCapture.luma = np.random.default_rng(4).integers(40, 200, (8, 12), dtype=np.uint8)
    monkeypatch.setattr(camera.cv2, "VideoCapture", RawCapture)
    cam = open_camera(f"v4l2://{dev}?width=12&height=8&fourcc={fourcc}&gray=true")
    cap = FakeCapture.instances[-1]
    colour = cv2.cvtColor(RawCapture.retrieve(types.SimpleNamespace(props={
        **cap.props, cv2.CAP_PROP_CONVERT_RGB: 1}))[1], cv2.COLOR_BGR2GRAY)
    img = cam.read().image
    assert img.shape == (8, 12) and img.dtype == np.uint8
    raw = fourcc != "MJPG"
    assert (cap.props.get(cv2.CAP_PROP_CONVERT_RGB) == 0) == raw
    assert np.abs(img.astype(int) - colour).max() <= (0 if fourcc != "YUYV" else 1)
    if fourcc == "YUYV":                                  # the luma plane, not the colour
        np.testing.assert_array_equal(img, yuv_luma_table()[RawCapture.luma])
    cam.close()
    plain = open_camera(f"v4l2://{dev}?width=12&height=8&fourcc={fourcc}")
    assert plain.read().image.shape == (8, 12, 3)         # without gray: as decoded
    assert cv2.CAP_PROP_CONVERT_RGB not in FakeCapture.instances[-1].props
    plain.close()


def test_v4l2_gray_short_buffer_is_a_camera_error(tmp_path, monkeypatch):
    dev = tmp_path / "video4"
    dev.touch()

    class Short(RawCapture):
        def retrieve(self):
            return True, np.zeros((1, 10), np.uint8)

    monkeypatch.setattr(camera.cv2, "VideoCapture", Short)
    cam = open_camera(f"v4l2://{dev}?width=12&height=8&fourcc=YUYV", gray=True)
    with pytest.raises(CameraError, match=r"raw.shape=\(1, 10\)"):
        cam.read()
    cam.close()


def test_sim_accepts_gray_and_is_gray_already(stub_sim):
    with open_camera("sim://walk?gray=1&end_frame=2") as cam:
        assert [f.image.ndim for f in cam] == [2, 2]

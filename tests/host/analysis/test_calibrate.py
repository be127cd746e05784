"""host calibrate (host/analysis/calibrate.py) fits a [vision] profile that the Pi loads
and that finds the pins."""
from __future__ import annotations

import json

import numpy as np

import pytest

from device.profile import load_pipeline_profile
from host.cli import main


def test_calibrate_on_the_simulated_rest_clip(tmp_path, capsys):
    out = tmp_path / "sim.toml"
    assert main(["calibrate", "sim://no-touch", "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    prof = load_pipeline_profile(out)
    assert prof.name == "sim"
    assert prof.pitch_px == pytest.approx(11.6, rel=0.1)
    assert abs(prof.n_pins - 133) <= 4
    assert prof.dome_px[2] == pytest.approx(145, rel=0.05)
    assert res["fit"]["regular_fraction"] > 0.9


def test_calibrate_on_real_clips(tmp_path):
    from tests.realdata import real_data_dir
    data = real_data_dir("roboskin/smooth.avi", "tactip_shear/images/image_1.png")
    out = tmp_path / "smooth.toml"
    assert main(["calibrate", str(data / "roboskin" / "smooth.avi"), "--out", str(out)]) == 0
    prof = load_pipeline_profile(out)
    assert prof.pitch_px == pytest.approx(11.7, rel=0.1)      # measured by hand: 11.7 px
    assert abs(prof.n_pins - 131) <= 8
    out2 = tmp_path / "shear.toml"
    folder = tmp_path / "one"
    folder.mkdir()
    (folder / "image_1.png").write_bytes((data / "tactip_shear/images/image_1.png").read_bytes())
    assert main(["calibrate", str(folder), "--out", str(out2)]) == 0
    prof2 = load_pipeline_profile(out2)
    assert abs(prof2.n_pins - 331) <= 3 and prof2.pitch_px == pytest.approx(19.2, rel=0.05)


def test_calibrate_on_a_frame_without_pins_is_exit_2(tmp_path, capsys):
    import cv2
    import numpy as np
    folder = tmp_path / "black"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.zeros((100, 100), np.uint8))
    assert main(["calibrate", str(folder), "--out", str(tmp_path / "x.toml")]) == 2
    assert "no dome" in capsys.readouterr().err


def _rest_contact_frames(clip, profile, n_rest):
    from device.pi.vision.encoder import FrameEncoder
    from tests.realdata import read_video
    enc = FrameEncoder(profile, crop_px=None)
    return sum(enc.encode(f).features.contact for f in read_video(clip, 0, n_rest))


def test_a_calibrated_profile_carries_the_rest_layout_and_reads_rest_as_rest(tmp_path):
    """From smooth.avi's leading rest frames: a [layout] of measured pins that the
    frame encoder maps onto, and no more rest frames read as contact than with the
    default profile."""
    from device.pi.vision.encoder import FrameEncoder
    from device.profile import load_layout
    from tests.realdata import real_data_dir
    clip = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    out = tmp_path / "my-sensor.toml"
    assert main(["calibrate", str(clip), "--out", str(out), "--frames", "12"]) == 0
    lay = load_layout(out)
    assert 110 <= len(lay) <= 150 and np.isfinite(lay).all()
    d = np.hypot(*(lay[:, None] - lay[None]).transpose(2, 0, 1)) + np.eye(len(lay)) * 1e9
    assert np.median(d.min(axis=1)) == pytest.approx(11.7, rel=0.1)   # the pin pitch
    enc = FrameEncoder(str(out), crop_px=None)
    assert enc.n_pins == len(lay)
    assert _rest_contact_frames(clip, str(out), 12) <= _rest_contact_frames(clip, "roboskin", 12)


def test_train_takes_a_calibrated_profile(tmp_path, capsys):
    from device.profile import load_layout
    from tests.realdata import real_data_dir
    clips = real_data_dir("roboskin/smooth.avi", "roboskin/concrete.avi") / "roboskin"
    prof = tmp_path / "my-sensor.toml"
    assert main(["calibrate", str(clips / "smooth.avi"), "--out", str(prof)]) == 0
    spec = tmp_path / "tex.csv"
    spec.write_text(f"path,label,start_frame,end_frame\n{clips / 'smooth.avi'},smooth,0,200\n"
                    f"{clips / 'concrete.avi'},concrete,0,200\n")
    capsys.readouterr()
    assert main(["train", "--task", "texture", "--model", "fnn", "--window", "2",
                 "--data", str(spec), "--contact-only", "--profile", str(prof),
                 "--out", str(tmp_path / "m"), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    man = json.loads((tmp_path / "m" / "manifest.json").read_text())
    n = len(load_layout(prof))
    assert man["input"]["shape"][1] >= n * 2 * 2           # T=2 frames of M (x, y) vectors
    assert res["metrics"]["test"]["accuracy"] > 0.6


def test_a_contact_threshold_beyond_the_pin_pitch_is_refused():
    """A profile's contact_px may not pass its pin pitch (device.profile refuses it), so
    calibrate says its frames are not at rest rather than write such a profile."""
    from device.sim import Simulator, load_scene
    from host.analysis.calibrate import rest_contact
    sim = Simulator(load_scene("no-touch"), seed=0)
    grays = [sim.render(i) for i in range(6)]
    vision = {"block": 11, "offset": 14.0, "pitch_px": 11.7, "n_pins": 133}
    assert rest_contact(grays, vision)["contact_px"] <= 11.7
    with pytest.raises(ValueError, match=r"contact threshold these frames need \(1\.0 px of mean "
                                         r"pin travel\) is beyond the pin pitch \(0\.6 px\): "
                                         r"the leading frames are not at rest"):
        rest_contact(grays, dict(vision, pitch_px=0.6))


#: the authors' clips of the one 133-pin sensor (flatSkin is another skin)
SENSOR_133 = ("smooth", "concrete", "lego_train", "north", "east")


@pytest.fixture(scope="module")
def layouts():
    """Each 133-pin clip's calibration from its 16 leading frames (the default)."""
    from host.analysis.calibrate import calibrate
    from tests.realdata import read_video, real_data_dir
    data = real_data_dir(*(f"roboskin/{n}.avi" for n in SENSOR_133)) / "roboskin"
    return {n: calibrate(read_video(data / f"{n}.avi", 0, 16)) for n in SENSOR_133}


#: the clips of one recording set-up (concrete.avi is another session: 120 fps, a
#: brighter exposure; see test_clips_of_one_sensor_give_one_layout)
SAME_SESSION = ("smooth", "lego_train", "north", "east")


def test_clips_of_one_sensor_give_one_layout(layouts):
    """Every layout near 133 pins, the clips within 3 pins of each other, and matched
    pins (after a shift) close. Measured (issue 23, fourth round): 131, 132, 130, 130,
    133 pins (130, 130, 130, 130, 133 before pins on lattice sites seen in half the
    frames were kept); 0-3 apart; all matched pins: median 0.06-0.25 px, max 0.81-1.57 px. The
    worst are pins on the LED glare: 5-10 per clip are loose (a clipped core, or a
    centre that wanders over the rest frames) and left out of the steady figures:
    max 0.42-0.81 px between smooth, lego_train, north and east except lego_train vs
    north/east (1.01, 1.06 px: a pin beside a glare core whose centre is steady in
    each clip), 1.11-1.42 px between concrete and the others (pins beside the glare,
    not clipped there)."""
    from host.analysis.calibrate import loose_flags
    from host.analysis.rest_pins import agreement
    for name, res in layouts.items():
        assert abs(len(res["layout"]) - 133) <= 4, (name, len(res["layout"]))
        assert 0 < len(res["loose"]) <= 0.1 * len(res["layout"]), (name, res["loose"])
    names = list(layouts)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            ag = agreement(np.asarray(layouts[a]["layout"]), np.asarray(layouts[b]["layout"]),
                           11.7, loose_flags(layouts[a]), loose_flags(layouts[b]))
            assert ag["count_difference"] <= 3, (a, b, ag)
            assert ag["matched"] >= 0.92 * min(ag["pins"]), (a, b, ag)
            assert ag["median_px"] <= 0.3 and ag["max_px"] <= 2.0, (a, b, ag)
            assert ag["steady"]["matched"] >= 0.85 * min(ag["pins"]), (a, b, ag)
            same = a in SAME_SESSION and b in SAME_SESSION
            assert ag["steady"]["max_px"] <= (1.1 if same else 1.5), (a, b, ag)
            assert ag["steady"]["max_px"] <= ag["max_px"]


def test_two_rest_windows_of_one_clip_agree_on_their_steady_pins(layouts):
    """east.avi rests for its first 34 frames: its frames 0-15 and 16-31 give layouts
    whose steady pins agree within 0.7 px (measured 0.63 px), while a glare core's
    centroid snaps between plateau modes (all pins: 2.6 px)."""
    from host.analysis.calibrate import calibrate, loose_flags
    from host.analysis.rest_pins import agreement
    from tests.realdata import read_video, real_data_dir
    clip = real_data_dir("roboskin/east.avi") / "roboskin" / "east.avi"
    first = layouts["east"]
    later = calibrate(read_video(clip, 16, 16))
    ag = agreement(np.asarray(first["layout"]), np.asarray(later["layout"]), 11.7,
                   loose_flags(first), loose_flags(later))
    assert ag["steady"]["matched"] >= 110, ag
    assert ag["steady"]["max_px"] <= 0.7 < ag["max_px"], ag


def test_the_printed_count_is_the_written_count_and_start_frames_merge(tmp_path, capsys):
    """--start/--frames pick the rest frames; two clips merge; the printed count is the
    written layout's; the overlay PNG is twice the frame's size."""
    import cv2
    from device.profile import load_layout
    from tests.realdata import real_data_dir
    clips = real_data_dir("roboskin/smooth.avi", "roboskin/north.avi") / "roboskin"
    out, png = tmp_path / "two.toml", tmp_path / "two.png"
    assert main(["calibrate", str(clips / "smooth.avi"), str(clips / "north.avi"), "--start", "2",
                 "--frames", "6", "--out", str(out), "--overlay", str(png)]) == 0
    text = capsys.readouterr().out
    n = len(load_layout(out))
    assert f"{n} pins (" in text and load_pipeline_profile(out).n_pins == n
    assert "steady in both" in text and "loose" in out.read_text()
    assert "smooth.avi: " in text and "north.avi: " in text and "matched" in text
    assert cv2.imread(str(png)).shape == (960, 1280, 3)
    assert main(["calibrate", str(clips / "smooth.avi"), "--start", "2", "--frames", "6",
                 "--out", str(tmp_path / "one.toml"), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["start"] == 2 and res["frames"] == 6 and res["vision"]["n_pins"] == len(res["layout"])
    assert sum(res["blobs"].values()) > res["blobs"]["kept"]          # something rejected
    assert main(["calibrate", str(clips / "smooth.avi"), "--start", "100000", "--out",
                 str(tmp_path / "x.toml")]) == 2


def test_a_skin_without_a_dome_calibrates_at_each_pins_own_size(tmp_path, capsys):
    """flatSkin: no round dome in view, and a wide-angle lens makes its pins about 28 px
    apart in the middle and 10 px at the rim. One pin size found the texture between
    the big pins (842 spots, pitch 10.8 px); each pin at its own size gives a regular
    lattice (measured: 579 pins from frames 0-3, 587 from 20-23; 28 px pitch in the
    middle, 12.5 px overall). The count is stable across windows of the clip, the
    region is the circle around the pins and the profile runs through the pipeline."""
    import cv2
    from device.pi.vision.extract import to_gray
    from host.analysis.calibrate import lattice_regularity
    from host.analysis.rest_pins import Region, find_rest_pins
    from host.analysis.spot_scale import local_pitch_px
    from tests.realdata import read_video, real_data_dir
    video = real_data_dir("roboskin/flatSkin.avi") / "roboskin" / "flatSkin.avi"
    clip = tmp_path / "flat"                        # its first 6 frames, kept short
    clip.mkdir()
    for k, f in enumerate(read_video(video, 0, 6)):
        cv2.imwrite(str(clip / f"f{k:03d}.png"), f)
    out = tmp_path / "flat.toml"
    assert main(["calibrate", str(clip), "--frames", "4", "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    n = res["vision"]["n_pins"]
    assert res["dome_in_view"] is False and res["spot_scale"] == "per-pin"
    assert 450 <= n <= 700 and res["lattice_regularity"] > 0.85
    lay = np.asarray(res["layout"])
    mid = np.hypot(*(lay - np.median(lay, axis=0)).T) < 60
    assert 24 <= np.median(local_pitch_px(lay)[mid]) <= 32     # measured by hand: 28 px
    assert 10 <= res["vision"]["pitch_px"] <= 15                # most pins are at the rim
    later = [to_gray(f) for f in read_video(video, 20, 4)]       # another window of the clip
    rest = find_rest_pins(later, Region(640, 480), 6.0, 9.0, multiscale=True)
    assert abs(len(rest.pins) - n) <= 0.05 * n, (len(rest.pins), n)
    assert lattice_regularity(rest.pins) > 0.85
    assert "no dome in view" in out.read_text()
    jl = tmp_path / "flat.jsonl"
    assert main(["analyse", str(clip), "--profile", str(out), "--out", str(jl)]) == 0
    lines = [json.loads(x) for x in jl.read_text().splitlines()]
    frames = [d for d in lines if "frame" in d and not d.get("summary")]
    assert frames and all("no_dome" not in d["faults"] for d in frames)
    assert np.median([d["pins"] for d in frames]) >= 300


def test_calibrate_writes_the_rest_contrast_the_pipeline_scales_its_offset_by():
    """contrast_ref is the dome's local contrast on the rest frames, measured as the
    pipeline measures it: the calibration's own exposure is not scaled, 0.7 of it
    scales the offset by about 0.7; and it survives the TOML."""
    import tomllib

    from device.pi.vision.pipeline import MarkerStream
    from device.sim import Simulator, load_scene
    from host.analysis.calibrate import calibrate, profile_toml
    from device.profile import parse_pipeline_profile
    sim = Simulator(load_scene("no-touch"))
    frames = [sim.render(i) for i in range(8)]
    res = calibrate(frames, name="sim")
    ref = res["vision"]["contrast_ref"]
    assert 5.0 < ref < 120.0
    prof = parse_pipeline_profile(tomllib.loads(profile_toml(res)))
    assert prof.vision.contrast_ref == ref
    for gain, want in ((1.0, 1.0), (0.7, 0.7)):
        s = MarkerStream(prof)
        for i, f in enumerate(frames):
            s.process(np.clip(np.rint(gain * f.astype(np.float64)), 0, 255).astype(np.uint8),
                      float(i))
        assert s.offset_scale == pytest.approx(want, abs=0.05) and s.reference is not None


def _no_touch(n: int) -> list:
    from device.sim import Simulator, load_scene
    sim = Simulator(load_scene("no-touch"), seed=0)
    return [sim.render(i) for i in range(n)]


def test_calibrate_refuses_frames_whose_pins_move_or_blink():
    """Frames that are not at rest are a NotAtRest naming them, never a profile: pins
    that move 2 px from frame to frame (the pipeline's still test allows 0.75 px), and
    pins hidden at random in 60 % of each frame (7 steady pins of 56 blobs a frame)."""
    import cv2
    from host.analysis.calibrate import NotAtRest, calibrate
    still = _no_touch(8)
    moving = [np.roll(f, 2 * k, axis=1) for k, f in enumerate(still)]
    with pytest.raises(NotAtRest, match=r"^frames 30\.\.37 are not at rest: the pins move "
                                        r"2\.00 px \(median\) from frame 30 to 31"):
        calibrate(moving, start=30)
    lay = np.asarray(calibrate(still)["layout"])
    rng = np.random.default_rng(0)
    blink = []
    for f in still:
        bg, hide = cv2.medianBlur(f, 21), np.zeros_like(f)
        for x, y in lay[rng.random(len(lay)) < 0.6]:
            cv2.circle(hide, (int(round(x)), int(round(y))), 6, 255, -1)
        blink.append(np.where(hide > 0, bg, f))
    with pytest.raises(NotAtRest, match=r"^frames 0\.\.7: only \d+ steady pins of the \d+ "
                                        r"blobs found per frame"):
        calibrate(blink)


def test_without_start_calibrate_takes_the_stillest_run_and_names_it(tmp_path, capsys):
    """A clip whose first 10 frames move: without --start the profile comes from the
    first still run of --frames frames (frames 10..15), and the output says so; with
    --start 0 the same clip is refused in one line, exit 2, and nothing is written."""
    import cv2
    still = _no_touch(8)
    folder = tmp_path / "clip"
    folder.mkdir()
    for k in range(18):
        f = np.roll(still[0], 2 * k, axis=1) if k < 10 else still[k - 10]
        cv2.imwrite(str(folder / f"f{k:02d}.png"), f)
    out = tmp_path / "p.toml"
    assert main(["calibrate", str(folder), "--frames", "6", "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["start"] == 10 and res["frames"] == 6 and res["motion_px"] <= 0.75
    assert abs(load_pipeline_profile(out).n_pins - 133) <= 4
    out.unlink()
    assert main(["calibrate", str(folder), "--start", "0", "--frames", "6",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "frames 0..5 are not at rest" in err[0] and not out.exists()


def test_calibrate_on_a_real_clip_in_contact_is_exit_2_and_writes_nothing(tmp_path, capsys):
    """smooth.avi from frame 250 is being dragged (it gave a 4-pin profile with exit
    0): now one line naming frames 250..265, exit 2, no file. A --start too near the
    end (frames 530..545 of its 540) is refused naming how many there are; the leading
    rest frames still calibrate and the output names them."""
    from tests.realdata import real_data_dir
    clip = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    out = tmp_path / "p.toml"
    assert main(["calibrate", str(clip), "--start", "250", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "frames 250..265 are not at rest" in err[0], err
    assert not out.exists()
    assert main(["calibrate", str(clip), "--start", "530", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ends at frame 539 (10 of them)" in err[0], err
    assert not out.exists()
    assert main(["calibrate", str(clip), "--frames", "8", "--out", str(out)]) == 0
    assert "from frames 0..7 of" in capsys.readouterr().out


def _write_clip(folder, frames):
    import cv2
    folder.mkdir()
    for k, f in enumerate(frames):
        cv2.imwrite(str(folder / f"f{k:02d}.png"), f)
    return folder


def _half_covered(frames):
    """The frames with the dome's left half hidden (about 60 of the 133 pins gone)."""
    import cv2
    out = []
    for f in frames:
        bg = cv2.medianBlur(f, 31)
        g = f.copy()
        g[:, :300] = bg[:, :300]
        out.append(g)
    return out


def test_a_merge_refuses_the_clip_that_disagrees_unless_told_to_drop_it(tmp_path, capsys):
    """Three clips of one sensor, one of them with half the dome covered (about 60
    pins off): the merge is refused in one line naming that clip and its count, and
    nothing is written; with --drop-outliers a one-line warning names it and the
    other two are merged (133 +- 3 pins)."""
    from device.sim import Simulator, load_scene
    clips = []
    for seed in (0, 1):
        sim = Simulator(load_scene("no-touch"), seed=seed)
        clips.append(_write_clip(tmp_path / f"c{seed}", [sim.render(i) for i in range(6)]))
    clips.append(_write_clip(tmp_path / "covered", _half_covered(_no_touch(6))))
    out = tmp_path / "m.toml"
    args = ["calibrate", *map(str, clips), "--frames", "6", "--out", str(out)]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the clips disagree: " in err[0] and not out.exists()
    assert f"{clips[2]} gives " in err[0] and str(clips[0]) + " gives" not in err[0]
    assert "--drop-outliers" in err[0]
    assert main(args + ["--drop-outliers", "--json"]) == 0
    cap = capsys.readouterr()
    warn = cap.err.strip().splitlines()
    assert len(warn) == 1 and warn[0].startswith(f"host calibrate: warning: {clips[2]} gives ")
    res = json.loads(cap.out)
    assert res["clips_merged"] == 2 and abs(res["vision"]["n_pins"] - 133) <= 3
    assert [c["source"] for c in res["clips"]] == [str(clips[0]), str(clips[1])]


def test_clip_outliers_names_both_of_two_clips_that_disagree():
    from host.analysis.calibrate import calibrate, clip_outliers
    full = calibrate(_no_touch(6))
    half = calibrate(_half_covered(_no_touch(6)))
    assert len(half["layout"]) < 100
    assert set(clip_outliers([full, half])) == {0, 1}
    assert clip_outliers([full, full, full]) == {}
    assert set(clip_outliers([full, half, full])) == {1}


def test_pins_refuses_a_layout_off_the_sensors_count(tmp_path, capsys):
    clip = _write_clip(tmp_path / "c", _no_touch(8))
    assert main(["calibrate", str(clip), "--frames", "8", "--pins", "133",
                 "--out", str(tmp_path / "ok.toml")]) == 0
    capsys.readouterr()
    out = tmp_path / "x.toml"
    assert main(["calibrate", str(clip), "--frames", "8", "--pins", "160",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pins found, the sensor has 160 (--pins; more than 5 off)" \
        in err[0] and "frames 0..7" in err[0] and not out.exists()


def test_spots_off_a_lattice_are_refused():
    """Steady bright dots at random places are not a pin lattice (78 % of them at
    the spacing; the authors' clips 93-99 %, the flat skin 90-92 %)."""
    import cv2
    from host.analysis.calibrate import NotAtRest, calibrate
    rng = np.random.default_rng(3)
    img = np.full((480, 640), 30, np.uint8)
    for x, y in rng.uniform([180, 80], [470, 360], (200, 2)):
        cv2.circle(img, (int(x), int(y)), 3, 220, -1)
    with pytest.raises(NotAtRest, match=r"^frames 0\.\.5: only \d+% of the \d+ pins found "
                                        r"are at the lattice spacing \(under 85%\)"):
        calibrate([img] * 6)


@pytest.fixture(scope="module")
def smooth_rest():
    from tests.realdata import read_video, real_data_dir
    clip = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    return read_video(clip, 0, 12)


def test_an_exposure_too_bright_is_refused_and_a_dark_one_finds_the_dome(smooth_rest):
    """smooth.avi's rest frames at 1.6x exposure: 94 of 105 pins clipped at full
    scale, refused (was a 105-pin profile); at 0.2x the dome was not found and the
    whole frame gave 244 pins: now the dome is found on a stretched copy, 133 pins."""
    from host.analysis.calibrate import NotAtRest, calibrate

    def gain(k):
        return [np.clip(f * k, 0, 255).astype(np.uint8) for f in smooth_rest]

    with pytest.raises(NotAtRest, match=r"^frames 0\.\.11: \d+ of the \d+ pins found are "
                                        r"loose, most of them with a core clipped at full "
                                        r"scale"):
        calibrate(gain(1.6))
    dark = calibrate(gain(0.2))
    assert dark["dome_in_view"] and abs(len(dark["layout"]) - 133) <= 3


def test_a_real_clip_at_an_eighth_of_its_rate_is_refused_in_one_line(tmp_path, capsys):
    """Every 8th frame of smooth.avi, written as a clip: its longest still stretch
    is 3 frames; exit 2, one line naming the frames looked at, nothing written. Asked
    for --frames 16 exactly, a stretch of 6 would not do either."""
    import cv2
    from tests.realdata import read_video, real_data_dir
    src = real_data_dir("roboskin/smooth.avi") / "roboskin" / "smooth.avi"
    frames = read_video(src, 0, 200)[::8]
    clip = tmp_path / "slow.avi"
    w = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), 25,
                        (frames[0].shape[1], frames[0].shape[0]))
    for f in frames:
        w.write(f)
    w.release()
    out = tmp_path / "p.toml"
    assert main(["calibrate", str(clip), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no still stretch of 6 (of the 16 wanted) frames in frames " \
        f"0..{len(frames) - 1}" in err[0] and "the longest is frames 8..10" in err[0], err
    assert not out.exists()

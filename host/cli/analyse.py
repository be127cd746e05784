"""``host analyse``, ``calibrate``, ``plot`` and ``realism``: recordings through the
marker pipeline."""
from __future__ import annotations

import json
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np

from device.errors import TacfootError, one_line
from device.pi.sources.camera import CameraError
from device.pi.models.window import RollingWindow
from device.pi.vision.encoder import FrameEncoder
from device.pi.vision.layout import LayoutError
from device.pi.vision.pipeline import STAGES, fault_names
from host.analysis.calibrate import frames_text, calibrate, merge_results, write_profile
from host.analysis.rest_pins import write_overlay
from host.analysis.plots import load_comparison, load_directions, plot_directions
from host.analysis.realism import realism_table, side_by_side_png, spec_realism
from host.analysis.sim2real import (SIM2REAL_TRIALS, real_texture_manifest, sim2real_table,
                                    sim_to_real, stroke_scene)
from host.cli.common import (SEED, UserError, emit, load_localiser, load_regressor, open_source,
                             open_stream, out_file, progress_bar, whole)
from host.cli.export import add_mcap_args

_log = logging.getLogger(__name__)


def _profile_from_models(args) -> None:
    """``args.profile``: the models' own sensor profile (their specs) when
    ``--localiser`` or ``--pressure`` is given, else ``--profile`` (default roboskin).
    A ``--profile`` other than the models', or two models carrying different
    profiles, is a UserError naming both."""
    from device.pi.models.manifest import read_spec
    from host.learn.onnx_io import models_profile

    specs = {}
    for folder in (args.localiser, args.pressure):
        if folder:
            spec, mpath = read_spec(folder)
            specs[str(mpath)] = spec
    if specs:
        args.profile, _ = models_profile(specs, args.profile)
    args.profile = args.profile or "roboskin"


def _open_pipeline(args):
    """(marker stream, frame encoder or None, window or None, pressure model or None).

    With ``--pressure`` the frames go through the runtime's frame encoder into a
    rolling window of the model's T frames, encoded as the model was trained."""
    _profile_from_models(args)
    localiser = load_localiser(args.localiser)
    reg = load_regressor(args.pressure)
    if reg is None:
        return open_stream(args, localiser), None, None, None
    try:
        encoder = FrameEncoder(args.profile, crop_px=None, localiser=localiser)
    except LayoutError as exc:
        raise UserError(f"--pressure needs a profile with a pin layout: {exc}") from None
    window = RollingWindow(reg.T, encoder.n_pins, encoder.profile.grid_n)
    return encoder.stream, encoder, window, reg


def _process(stream, encoder, window, reg, fr):
    """(features, pressure or None) for one camera frame."""
    if encoder is None:
        return stream.process(fr.image, fr.t_s), None
    ef = encoder.encode(fr.image, fr.t_s)
    window.push(vectors=ef.vectors, grid=ef.grid)
    if stream.reference is None:
        return ef.features, None
    return ef.features, reg.predict_window(window)


def frame_line(f, pressure: float | None, localised: bool) -> dict:
    """The JSON line for one frame: the pipeline's summary, the windowed pressure
    and, with a localiser, its pins as ``localised_px`` (px, 2 decimals; null
    on a frame the pipeline could not localise, such as one without a dome)."""
    line = f.summary()
    line["pressure"] = None if pressure is None else round(float(pressure), 5)
    if localised:
        line["localised_px"] = (None if f.localised is None else
                                np.round(np.asarray(f.localised, np.float64), 2).tolist())
    return line


#: ``host analyse --mcap``: each frame's JSON line, beside the leg's channels
ANALYSE_CHANNEL = {"/tacfoot/analyse": {
    "title": "tacfoot.AnalyseFrame", "type": "object", "properties": {
        "frame": {"type": "integer"}, "t": {"type": "number"}, "pins": {"type": "integer"},
        "contact": {"type": "boolean"}, "shear_x": {"type": "number"},
        "shear_y": {"type": "number"}, "magnitude": {"type": "number"},
        "magnitude_sum": {"type": "number"}, "pressure": {"type": "number"},
        "faults": {"type": "array", "items": {"type": "string"}},
        "timings_ms": {"type": "object"}}}}


def mcap_frame(log, f, line: dict, k: int, image, reference, image_every: int) -> None:
    """One analysed frame into an MCAP log at its own time: the image and pins every
    ``image_every``-th frame, the contact grid, the pipeline's time on
    ``/tacfoot/latency`` (no packet: ``latency_ms`` null) and the JSON line."""
    t_ns = max(0, int(round(float(f.t_s) * 1e9)))
    if k % image_every == 0:
        log.image(t_ns, image, f, reference)
    from device.pi.runtime.mcapmsg import grid_doc
    log.write("/tacfoot/grid", t_ns, grid_doc(t_ns, f.grid))
    total = f.timings_ms.get("total")
    log.write("/tacfoot/latency", t_ns, {"frame": line["frame"], "latency_ms": None,
                                         "pipeline_ms": None if total is None
                                         else round(float(total), 4)})
    log.write("/tacfoot/analyse", t_ns, line)


def cmd_analyse(args):
    stream, encoder, window, reg = _open_pipeline(args)
    log = None
    if args.mcap:
        from host.cli.export import open_log
        log = open_log(args.mcap, args.mcap_image_every, channels=ANALYSE_CHANNEL)
        log.prog = "host analyse"                  # its warnings name this command
    try:
        cam = open_source(args.source)
    except BaseException:
        if log is not None:
            log.close()
        raise
    out = open(out_file(args.out), "w") if args.out else sys.stdout
    n = contact = 0
    faults: dict[str, int] = {}
    times = {k: [] for k in STAGES + ("total",)}
    total = getattr(cam, "n_frames", None)
    try:
        with cam, progress_bar(total or 0, "analyse",
                               not args.json and args.out is not None) as bar:
            for fr in cam:
                f, pressure = _process(stream, encoder, window, reg, fr)
                line = frame_line(f, pressure, bool(args.localiser))
                out.write(json.dumps(line) + "\n")
                if log is not None:
                    mcap_frame(log, f, line, n, fr.image, stream.reference,
                               args.mcap_image_every)
                n += 1
                contact += f.contact
                for name in fault_names(f.faults):
                    faults[name] = faults.get(name, 0) + 1
                for k in times:
                    if k in f.timings_ms:
                        times[k].append(f.timings_ms[k])
                bar.update(1)
        summary = {"summary": True, "source": args.source, "profile": stream.profile.name,
                   "frames": n, "contact_frames": contact, "fault_frames": faults,
                   "reference_set": stream.reference is not None,
                   "timings_ms": {k: {"median": float(np.median(v)),
                                      "p99": float(np.percentile(v, 99))}
                                  for k, v in times.items() if v}}
        if log is not None:
            from host.cli.export import close_log
            summary["mcap"], log = close_log(log), None
        out.write(json.dumps(summary) + "\n")
    finally:
        if log is not None:
            log.close()
        if out is not sys.stdout:
            out.close()


def cmd_plot(args):
    stats = []
    try:
        if args.compare:
            inputs = []
            for p in args.inputs:
                panels, st = load_comparison(p)
                inputs += panels
                stats.append(st)
        else:
            inputs = [load_directions(p) for p in args.inputs]
    except OSError as exc:                    # a file that cannot be read: name it
        raise UserError(one_line(exc)) from None
    out = plot_directions(inputs, out_file(args.out), title=args.title or "")
    res = {"out": str(out), "points": [int(len(d["xy"])) for d in inputs]}
    text = f"wrote {out}"
    if args.compare:
        res["comparison"] = stats
        text += "".join(f"\n{st['source']}: vectors {st['vectors_deg']} deg, localiser "
                        f"{st['localised_deg']} deg, median |difference| "
                        f"{st['median_abs_diff_deg']} deg over {st['compared']} frames"
                        for st in stats)
    emit(args, res, text)


def _clip_frames(source: str, start: int = 0):
    """The frames of a clip from frame ``start`` on, read one at a time."""
    with open_source(source) as cam:
        for k, fr in enumerate(cam):
            if k >= start:
                yield fr.image


def _calibrate_clip(source: str, start: int | None, count: int | None, name: str,
                    pins: int | None = None):
    """(the first frame used, its calibration) of one clip. With ``start``: frames
    ``start`` .. ``start + count - 1`` (count default 16), which must be still; too
    few of them is a UserError. Without: the earliest still stretch of ``count``
    frames (:func:`calibrate_clip`), or, with no ``count`` given and no stretch of
    16, the longest of at least 6, said on stderr in one line. Refusals are a
    UserError naming the clip and the frames."""
    from host.analysis.calibrate import NotAtRest
    from host.analysis.still import LEAST_FRAMES, WANT_FRAMES, calibrate_clip
    want = count or WANT_FRAMES
    stream = _clip_frames(source, start or 0)
    try:
        if start is None:
            found = calibrate_clip(stream, want, want if count else LEAST_FRAMES, name=name,
                                   expect_pins=pins)
            if found.note:
                _log.warning("host calibrate: %s: %s", source, found.note)
            return found.frame, found.result
        frames = [f.copy() for _, f in zip(range(want), stream)]
        if not frames:
            raise UserError(f"{source}: no frames to calibrate from (--start {start})")
        if len(frames) < want:
            raise UserError(f"{source}: --start {start} --frames {want} asks for frames "
                            f"{start}..{start + want - 1}, but the clip ends at frame "
                            f"{start + len(frames) - 1} ({len(frames)} of them); choose an "
                            f"earlier --start or fewer --frames")
        return frames[0], calibrate(frames, name=name, start=start, expect_pins=pins)
    except CameraError:                      # names its own file: the main catch says it
        raise
    except (NotAtRest, TacfootError) as exc:
        raise UserError(f"{source}: {one_line(exc)}") from None
    finally:
        stream.close()


def _drop_outliers(results: list, drop: bool) -> list:
    """``results`` (source, frame, calibration) without the clips that disagree with
    the others (:func:`clip_outliers`): a UserError naming them unless ``drop``, then
    a warning line each on stderr; a UserError when fewer than two would agree."""
    from host.analysis.calibrate import clip_outliers
    bad = clip_outliers([r for _, _, r in results])
    if not bad:
        return results
    named = "; ".join(f"{results[i][0]} gives {why}" for i, why in bad.items())
    keep = [r for i, r in enumerate(results) if i not in bad]
    if not drop or len(keep) < 2:
        hint = ("merge without it: --drop-outliers" if len(keep) >= 2 else
                "too few clips agree to tell which is right")
        raise UserError(f"the clips disagree: {named}; calibrate each alone (--overlay) to "
                        f"see why, or {hint}")
    for i, why in bad.items():
        _log.warning("host calibrate: warning: %s gives %s: left out of the merge "
                     "(--drop-outliers)", results[i][0], why)
    return keep


def cmd_calibrate(args):
    out = out_file(args.out)
    name = args.name or out.stem
    results = []
    for source in args.sources:
        frame, res = _calibrate_clip(source, args.start, args.frames, name, args.pins)
        results.append((source, frame, res))
    if len(results) > 1:
        results = _drop_outliers(results, args.drop_outliers)
    source, frame, res = results[0]
    clips = [{"source": s, "start": r["start"], "frames": r["frames"],
              "pins": len(r["layout"]), "loose": len(r["loose"]), "blobs": r["blobs"]}
             for s, _, r in results]
    if len(results) > 1:
        res = merge_results([r for _, _, r in results])
    lay = res["layout"]
    res["out"] = str(write_profile(res, out))
    if args.overlay:
        res["overlay"] = str(write_overlay(args.overlay, frame, results[0][2]["rest"],
                                           results[0][2]["region"]))
    v = res["vision"]
    text = (f"wrote {args.out}: {'dome' if res['dome_in_view'] else 'no dome in view, region'} "
            f"{v['dome_px']}, block {v['block']}, offset {v['offset']}, pin area "
            f"{v['min_area_px']}..{v['max_area_px']} px, pitch {v['pitch_px']} px, "
            f"{len(lay)} pins ({len(res['loose'])} loose: glare-clipped or wandering)")
    if len(results) > 1:
        text += "".join(f"\n  {c['source']}: {c['pins']} pins ({c['loose']} loose) from "
                        f"{frames_text(c['start'], c['frames'])}" for c in clips)
        text += "".join(f"\n  {clips[a['clips'][0]]['source']} vs {clips[a['clips'][1]]['source']}: "
                        f"{a['count_difference']} pins apart, {a['matched']} matched, "
                        f"median {a['median_px']} px, max {a['max_px']} px; "
                        f"{a['steady']['matched']} steady in both, max {a['steady']['max_px']} px"
                        for a in res["agreement"])
    else:
        text += f", from {frames_text(res['start'], res['frames'])} of {source}"
    if args.overlay:
        text += f"\noverlay: {res['overlay']}"
    res["clips"] = clips
    for key in ("rest", "region"):
        res.pop(key, None)
    emit(args, res, text)


REALISM_NO_DATA = ("host realism needs --data SPEC (a CSV manifest path,label[,start_frame,"
                   "end_frame] of your recordings, or a dataset folder); for the authors' "
                   "clips: python -m host.bench.specs --real-data DIR --out out/specs, then "
                   "--data out/specs/realism.csv")


def _frames_of(rec):
    """A loader of a recording's frames (grey for a video)."""
    from host.bench.specs import recording_frames
    from host.data.video import video_frames

    if rec.kind == "clip" and not Path(rec.path).is_dir():
        return lambda: video_frames(rec.path, rec.end, gray=True)[rec.start:]
    return lambda: recording_frames(rec)


def _sim2real(args, found: dict, profile: str, work: str) -> tuple[dict | None, str]:
    """Sim-to-real on the specs' recordings (clips cut to --real-frames), or None and
    the one-line reason it was skipped."""
    labels = sorted({r.label for recs in found.values() for r in recs})
    for label in labels:
        try:
            stroke_scene(label, np.random.default_rng(0))
        except ValueError:
            return None, (f"sim-to-real skipped: label {label!r} is not a simulator surface "
                          f"(device/sim/scene.py PRESETS)")
    if len(labels) < 2:
        return None, f"sim-to-real skipped: it needs two or more labels, the data has {labels}"
    rows = [(r.path, r.label, r.start, r.end) for recs in found.values() for r in recs
            if r.kind == "clip"]
    specs = [s for s, recs in found.items() if any(r.kind == "trial" for r in recs)]
    if rows:
        specs.append(str(real_texture_manifest(rows, Path(work) / "real", args.real_frames)))
    res = sim_to_real(specs, work, n_per_texture=args.sim2real_trials, seed=args.seed,
                      calibrated=not args.uncalibrated, randomise=not args.uncalibrated,
                      real_frames=args.real_frames, progress=not args.json, profile=profile)
    return res, sim2real_table(res)


def cmd_realism(args):
    from host.bench.specs import check_profile, check_specs
    from host.localiser.samples import vision_params_for

    if not args.data:
        raise UserError(REALISM_NO_DATA)
    if args.real_frames is not None and args.real_frames < 20:     # windows of T = 10 need room
        raise UserError(f"--real-frames must be at least 20, got {args.real_frames}")
    profile = check_profile(args.profile)      # every file checked before any long work
    found = check_specs(args.data)
    recs = [r for rs in found.values() for r in rs]
    items = [(r.name, r.label, _frames_of(r)) for r in recs]
    res = spec_realism(items, vision_params_for(profile), seed=args.seed,
                       progress=not args.json)
    if args.png:
        first = next((f for f in (_frames_of(r)() for r in recs) if len(f)), None)
        if first is None:
            raise UserError("--png: no recording of --data has frames")
        res["png"] = side_by_side_png(first[0], recs[0].name, args.png, seed=args.seed)
    res.update(data=[str(d) for d in args.data], profile=str(profile))
    text = realism_table(res) + ("\nall compared figures within 20%: "
                                 f"{'yes' if res['all_within_20pct'] else 'NO'}")
    if args.sim2real_trials:
        with tempfile.TemporaryDirectory(prefix="tacfoot-sim2real-") as tmp:
            try:
                res["sim_to_real"], more = _sim2real(args, found, profile, args.work or tmp)
            except TacfootError as exc:
                raise UserError(f"sim-to-real: {exc}") from None
        text += "\n\n" + more
    emit(args, res, text)
    return 0 if res["all_within_20pct"] else 1


def register(sub) -> None:
    """The sub-commands analyse, calibrate, plot and realism."""
    s = sub.add_parser("analyse", help="run the marker pipeline over a video, image folder "
                                       "or sim://SCENE; one JSON line per frame")
    s.add_argument("source", help="clip.avi, a folder of images, or sim://SCENE")
    s.add_argument("--profile", help="sensor profile name or .toml (default roboskin; with "
                                      "--localiser or --pressure the models' own, another "
                                      "is an error)")
    s.add_argument("--localiser", help="localiser model folder (ONNX + manifest)")
    s.add_argument("--pressure", help="pressure regressor model folder")
    s.add_argument("--out", help="write the JSON lines here instead of stdout")
    add_mcap_args(s)
    s.add_argument("--json", action="store_true", help="(output is always JSON lines)")
    s.set_defaults(func=cmd_analyse)

    s = sub.add_parser("calibrate", help="fit a pipeline profile and the rest pin layout "
                                         "from no-contact frames of one or more clips")
    s.add_argument("sources", nargs="+", metavar="CLIP",
                   help="clip.avi, a folder of images, or sim://SCENE; several clips of one "
                        "sensor are merged (the pins most of them find)")
    s.add_argument("--out", required=True, help="profile .toml to write")
    s.add_argument("--start", type=whole(0, 10_000_000), default=None, metavar="K",
                   help="first rest frame (its index in the clip); these --frames must be "
                        "still. Default: the clip's earliest still stretch, found by itself")
    s.add_argument("--frames", type=whole(2, 100_000), default=None, metavar="N",
                   help="rest frames to use (nothing touching); default 16, or, when no "
                        "clip has a still stretch of 16, its longest of at least 6 (said "
                        "on stderr)")
    s.add_argument("--pins", type=whole(3, 100_000), default=None, metavar="N",
                   help="the sensor's pin count, when known: a layout more than 3%% (at "
                        "least 3 pins) off it is refused")
    s.add_argument("--drop-outliers", action="store_true",
                   help="merge without the clips whose pin count or layout disagrees with "
                        "the others (warned on stderr); default: refuse the merge")
    s.add_argument("--overlay", metavar="PNG",
                   help="also write the first rest frame (of the first clip) at twice its "
                        "size with the pins kept and the blobs rejected, and why")
    s.add_argument("--name", help="profile name (default: the file name)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_calibrate)

    s = sub.add_parser("plot", help="plots: directions (the paper's figure 5)")
    s.add_argument("kind", choices=["directions"])
    s.add_argument("inputs", nargs="+", help="paper-layout .npy files (trials, sensations, "
                                             "pressures, 2) or host analyse JSON lines")
    s.add_argument("--out", required=True, help="PNG to write")
    s.add_argument("--title")
    s.add_argument("--compare", action="store_true",
                   help="inputs are host analyse --localiser JSON lines: plot the tracked "
                        "vectors' directions beside the localiser pins'")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_plot)

    s = sub.add_parser("realism", help="the simulator against your recordings, measured "
                                       "alike; and a sim-trained texture model on them")
    s.add_argument("--data", action="append", metavar="SPEC",
                   help="a CSV manifest (path,label[,start_frame,end_frame]) or a dataset "
                        "folder; repeatable; each label picks the simulator's LABEL-drag "
                        "scene (required; python -m host.bench.specs writes the authors')")
    s.add_argument("--profile", default="roboskin",
                   help="sensor profile name or .toml the frames are measured with")
    s.add_argument("--png", help="also write a real | simulated side-by-side PNG here")
    s.add_argument("--seed", type=SEED, default=0)
    s.add_argument("--sim2real-trials", type=whole(0, 1000), default=SIM2REAL_TRIALS, metavar="N",
                   help="sim-to-real: simulated stroke trials per texture the texture model "
                        f"trains on (default {SIM2REAL_TRIALS}; 0 skips it)")
    s.add_argument("--real-frames", type=whole(1), metavar="F",
                   help="sim-to-real: score only the first F frames of each real video")
    s.add_argument("--uncalibrated", action="store_true",
                   help="sim-to-real with the generic smooth and concrete surfaces and no "
                        "randomisation (the simulator before calibration)")
    s.add_argument("--work", help="keep the sim-to-real trials and model in this folder")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_realism)

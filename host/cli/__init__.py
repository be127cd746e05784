"""The ``host`` command: the tacfoot host toolkit.

Every command that computes a result accepts ``--json``. Bad input (a bad
scene file, a missing source) gives one clear line on stderr and exit status 2.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

EXIT_BAD_INPUT = 2


class UserError(Exception):
    """Bad input from the user: printed as one line, exit status 2."""


def _emit(args, data, text: str | None = None):
    if getattr(args, "json", False):
        print(json.dumps(data, default=_json_default))
    elif text is not None:
        print(text)


def _json_default(o):
    from host.learn.onnx_io import json_default as _plain
    return _plain(o)


def _progress(total: int, desc: str, enabled: bool = True):
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="frame", disable=not enabled or None,
                file=sys.stderr, leave=False)


# -- commands ------------------------------------------------------------------

def cmd_scenes(args):
    from device.sim import builtin_scenes, load_scene
    rows = []
    for name in builtin_scenes():
        sc = load_scene(name)
        rows.append({"name": name, "profile": sc.profile.name, "frames":
                     int(round(sc.duration_s * sc.fps)), "duration_s": round(sc.duration_s, 3),
                     "effects": list(sc.effect_names), "description": sc.description})
    text = "\n".join(f"{r['name']:<15} {r['duration_s']:>5.2f}s  {r['description']}"
                     for r in rows)
    _emit(args, rows, text)


def cmd_simulate(args):
    from host.data.simulate import simulate_to_dataset

    res = simulate_to_dataset(args.scene, Path(args.out), args.seed, args.trials,
                              progress=not args.json)
    _emit(args, res, f"wrote {len(res['trials'])} trial(s), {res['frames']} frames, to {args.out}")


def _frames_and_truth(src: str, seed: int):
    """(frames list, truth dict | None, rest pins | None, fps) for a scene or dataset."""
    from device.sim import Simulator, load_scene
    from host.data.dataset import is_dataset, load_trial

    if is_dataset(src):
        tr = load_trial(src, 0)
        truth = {k: v for k, v in tr.items() if k not in ("frames", "info")}
        return tr["frames"], truth, tr.get("rest_pins_px"), float(tr["info"].get("fps", 30))
    sim = Simulator(load_scene(src), seed=seed)
    frames = [sim.render(i) for i in range(sim.n_frames)]
    return frames, sim.truth, sim.rest_pins_px, sim.fps


def cmd_view(args):
    import numpy as np

    from host.analysis.view import draw_vectors, pick_frames, save_images, truth_caption

    if Path(args.out).suffix.lower() not in (".gif", ".png"):
        raise UserError(f"--out must end in .gif or .png, got {args.out!r}")
    if _is_recording(args.source):
        return _view_pipeline(args)
    frames, truth, rest, fps = _frames_and_truth(args.source, args.seed)
    out = Path(args.out)
    most = args.max_frames or (120 if out.suffix.lower() == ".gif" else 6)
    contact = np.flatnonzero(truth["contact"]) if out.suffix.lower() == ".png" else []
    if len(contact) and not args.max_frames:
        picks = contact[pick_frames(len(contact), most)]   # a contact sheet shows touches
    else:
        picks = pick_frames(len(frames), most)
    images = [draw_vectors(frames[i], rest, truth["pins_px"][i], truth["visible"][i],
                           gain=args.gain, text=truth_caption(truth, i)) for i in picks]
    save_images(images, out, fps=min(fps, 15.0))
    _emit(args, {"out": str(out), "frames": [int(i) for i in picks]},
          f"wrote {out} ({len(picks)} frames)")


def _is_recording(source: str) -> bool:
    """A video, an image folder or sim:// (not a scene name or a dataset folder)."""
    from host.data.dataset import is_dataset
    p = Path(source)
    return (source.startswith(("sim://", "file://", "v4l2://"))
            or (p.is_file() and p.suffix.lower() != ".toml")
            or (p.is_dir() and not is_dataset(p)))


def _view_pipeline(args):
    """Pins and vectors found by the Pi's pipeline drawn over the frames (the
    paper's figure 3)."""
    from device.pi.vision.pipeline import fault_names
    from host.analysis.view import draw_vectors, pick_frames, save_images

    stream = _open_stream(args)
    cam = _open_source(args.source)
    out = Path(args.out)
    most = args.max_frames or (120 if out.suffix.lower() == ".gif" else 6)
    total = getattr(cam, "n_frames", None) or 0
    keep = set(pick_frames(total, most).tolist()) if total else None
    images, picked = [], []
    with cam:
        for fr in cam:
            f = stream.process(fr.image, fr.t_s)
            if stream.reference is None or (keep is not None and f.index not in keep):
                continue
            if keep is None and len(images) >= most:
                break
            ref = stream.reference
            text = f"#{f.index} {'contact' if f.contact else 'no contact'} |v| {f.magnitude:.1f}px"
            if f.faults:
                text += " " + ",".join(fault_names(f.faults))
            images.append(draw_vectors(fr.image, ref, ref + f.vectors, ~f.lost, gain=args.gain,
                                       text=text))
            picked.append(f.index)
    if not images:
        raise UserError(f"{args.source}: no frame had a reference (no dome or no still start)")
    save_images(images, out, fps=15.0)
    _emit(args, {"out": str(out), "frames": picked}, f"wrote {out} ({len(picked)} frames)")


def _gait_plan(scene, sim, stance_load_n: float = 8.0) -> list:
    """What a gait MCU would tell the foot for each frame of a scene: stance while
    the foot is commanded into the ground (expected load: the stance load it
    commands), the commanded drag velocity, swing otherwise."""
    import math

    from device.pi.runtime import protocol as P
    plan, t_end = [], 0.0
    spans = []
    for a in scene.timeline:
        spans.append((t_end, t_end + a.duration_s, a))
        t_end += a.duration_s
    depth = sim.truth["depth_cmd_mm"]
    for i in range(sim.n_frames):
        t = i / sim.fps
        a = next((x for t0, t1, x in spans if t0 <= t < t1), spans[-1][2])
        stance = bool(depth[i] > 0)
        v = (0.0, 0.0, 0.0)
        if stance and a.kind == "drag":
            r = math.radians(a.direction_deg)
            v = (a.speed_mm_s * math.cos(r), a.speed_mm_s * math.sin(r), 0.0)
        plan.append(P.Gait(P.PHASE_STANCE if stance else P.PHASE_SWING,
                           stance_load_n if stance else 0.0, v))
    return plan


def _demo_runtime(scene_name: str, seed: int, out: Path, sim, scene, realtime: bool,
                  progress: bool) -> dict:
    """Run the real runtime (``python -m device.pi run``) on simulated hardware
    with its serial port on a pty; this side plays the gait MCU: it decodes every
    packet (device.pi.runtime.protocol) and answers each SURFACE with the GAIT context."""
    import os
    import select
    import subprocess
    import time

    from device.pi.runtime import protocol as P

    master, slave = os.openpty()
    slave_name = os.ttyname(slave)
    q = f"?seed={seed}" + ("&realtime=1" if realtime else "")
    cmd = [sys.executable, "-m", "device.pi", "run", "--camera", f"sim://{scene_name}{q}",
           "--imu", f"sim://{scene_name}?seed={seed}", "--serial", slave_name,
           "--json-log", str(out / "decisions.jsonl"), "--status", str(out / "status.json"),
           "--json"]
    plan = _gait_plan(scene, sim)
    dec = P.FrameDecoder()
    packets, n_surface, seq, t0 = [], 0, 0, time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with _progress(sim.n_frames, "runtime", progress) as bar:
            while True:
                r, _, _ = select.select([master], [], [], 0.05)
                data = os.read(master, 4096) if r else b""
                for raw in dec.feed(data):
                    msg = P.decode_message(raw)
                    if msg is None:
                        continue
                    d = P.message_dict(msg)
                    d.update(seq=raw.seq, t_ms=raw.t_ms,
                             host_ms=round((time.monotonic() - t0) * 1e3, 2))
                    packets.append(d)
                    if isinstance(msg, P.Surface):
                        n_surface += 1
                        bar.update(1)
                        g = plan[min(n_surface, len(plan) - 1)]
                        os.write(master, g.encode(seq, int((time.monotonic() - t0) * 1e3)))
                        seq = (seq + 1) & 0xFFFF
                if not data and proc.poll() is not None:
                    break
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
        os.close(slave)
    if proc.returncode != 0:
        raise UserError(f"the runtime failed ({proc.returncode}): {stderr.strip()[-500:]}")
    with open(out / "packets.jsonl", "w") as fh:
        for d in packets:
            fh.write(json.dumps(d) + "\n")
    status = json.loads(stdout.strip().splitlines()[-1])
    counts: dict = {}
    for d in packets:
        counts[d["type"]] = counts.get(d["type"], 0) + 1
    return {"command": " ".join(cmd), "packets_file": str(out / "packets.jsonl"),
            "decisions_file": str(out / "decisions.jsonl"), "packets": counts,
            "decoder": dict(dec.counters), "runtime": status}


def _demo_segments(scene, sim, out: Path) -> list:
    """Per step of the scene's timeline: the true surface and what the runtime
    reported most often over the frames in contact."""
    from collections import Counter

    from device.sim import SURFACE_LABELS
    ds = [json.loads(x) for x in (out / "decisions.jsonl").read_text().splitlines()]
    by_index = {d["index"]: d for d in ds}
    rows, t0 = [], 0.0
    for a in scene.timeline:
        i0, i1 = int(round(t0 * sim.fps)), int(round((t0 + a.duration_s) * sim.fps))
        t0 += a.duration_s
        idx = [i for i in range(i0, min(i1, sim.n_frames))
               if sim.truth["contact"][i] and i in by_index]
        truth = Counter(SURFACE_LABELS[int(sim.truth["surface"][i])] for i in idx)
        said = Counter(by_index[i]["class"] for i in idx)
        rows.append({"t_s": round(i0 / sim.fps, 3), "action": a.kind,
                     "truth": truth.most_common(1)[0][0] if truth else "no-touch",
                     "contact_frames": len(idx),
                     "reported": said.most_common(1)[0][0] if said else "no-touch",
                     "share": round(said.most_common(1)[0][1] / len(idx), 3) if idx else None,
                     "slip_frames": sum(bool(by_index[i]["slip"]) for i in idx)})
    return rows


def cmd_demo(args):
    from device.sim import Simulator, load_scene
    from host.analysis.view import draw_vectors, pick_frames, save_images, truth_caption, truth_plot

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(args.scene)
    sim = Simulator(scene, seed=args.seed)
    picks = pick_frames(sim.n_frames, 180)
    images = []
    with _progress(len(picks), f"simulating {scene.name}", not args.json) as bar:
        for i in picks:
            images.append(draw_vectors(sim.render(i), sim.rest_pins_px, sim.truth["pins_px"][i],
                                       sim.truth["visible"][i], text=truth_caption(sim.truth, i)))
            bar.update(1)
    preview = save_images(images, out / "preview.gif", fps=20)
    plot = truth_plot(sim.truth, out / "ground_truth.png",
                      title=f"scene {scene.name}, seed {args.seed}: ground truth")
    t = sim.truth
    res = {"scene": scene.name, "frames": sim.n_frames, "preview": str(preview),
           "ground_truth_plot": str(plot), "contact_frames": int(t["contact"].sum()),
           "slip_frames": int(t["slip"].sum())}
    res.update(_demo_runtime(args.scene, args.seed, out, sim, scene, not args.fast,
                             not args.json))
    res["segments"] = _demo_segments(scene, sim, out)
    rt = res["runtime"]
    lines = [f"simulated {scene.name}: {sim.n_frames} frames, {res['contact_frames']} in "
             f"contact, {res['slip_frames']} slipping",
             f"runtime: {' '.join(res['command'].split()[2:9])} ...",
             f"  {rt['frames']} frames, {rt['packets_sent']} packets sent "
             f"({', '.join(f'{k} {v}' for k, v in sorted(res['packets'].items()))}), "
             f"{rt['packets_dropped']} dropped, latency p50 {rt['latency_ms_p50']} ms",
             f"  {'t_s':>6} {'step':<6} {'truth':<9} {'contact':>7} {'reported':<9} "
             f"{'share':>5} {'slip':>4}"]
    for r in res["segments"]:
        if r["contact_frames"]:
            lines.append(f"  {r['t_s']:>6.2f} {r['action']:<6} {r['truth']:<9} "
                         f"{r['contact_frames']:>7} {r['reported']:<9} {r['share']:>5.2f} "
                         f"{r['slip_frames']:>4}")
    lines += [f"packets:      {res['packets_file']}", f"decisions:    {res['decisions_file']}",
              f"preview:      {preview}", f"ground truth: {plot}"]
    _emit(args, res, "\n".join(lines))


def cmd_bench(args):
    from host.bench import sim as bench
    if args.what == "sim":
        res = bench.bench_sim(repeats=args.repeats)
        _emit(args, res, bench.format_sim(res))
    elif args.what == "pipeline":
        try:
            data = real_data_dir(args.data)
        except UserError:
            data = None
            print("host bench: real recordings not found; timing simulated frames only",
                  file=sys.stderr)
        res = bench.bench_pipeline(data, repeats=max(1, min(args.repeats, 5)))
        _emit(args, res, bench.format_pipeline(res))
    elif args.what == "runtime":
        from host.bench.runtime import bench_runtime, format_runtime
        res = bench_runtime(frames=args.frames)
        _emit(args, res, format_runtime(res))


def _open_stream(args):
    from device.pi.models.artefact import ModelError
    from device.pi.vision.pipeline import MarkerStream
    from device.profile import load_pipeline_profile

    profile = load_pipeline_profile(args.profile)
    loc = pres = None
    try:
        if getattr(args, "localiser", None):
            from device.pi.vision.localiser import Localiser
            loc = Localiser.load(args.localiser)
        if getattr(args, "pressure", None):
            from device.pi.models.regressor import Regressor
            pres = Regressor.load(args.pressure)
    except ModelError as exc:
        raise UserError(str(exc)) from None
    return MarkerStream(profile, localiser=loc, pressure=pres)


def _open_source(source: str):
    from device.pi.sources.camera import CameraError, open_camera
    try:
        return open_camera(source)
    except (CameraError, ValueError) as exc:
        raise UserError(str(exc)) from None


def cmd_analyse(args):
    import numpy as np

    from device.pi.vision.pipeline import STAGES, fault_names

    stream = _open_stream(args)
    cam = _open_source(args.source)
    out = open(args.out, "w") if args.out else sys.stdout
    n = contact = 0
    faults: dict[str, int] = {}
    times = {k: [] for k in STAGES + ("total",)}
    total = getattr(cam, "n_frames", None)
    try:
        with cam, _progress(total or 0, "analyse", not args.json and args.out is not None) as bar:
            for fr in cam:
                f = stream.process(fr.image, fr.t_s)
                out.write(json.dumps(f.summary()) + "\n")
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
        out.write(json.dumps(summary) + "\n")
    finally:
        if out is not sys.stdout:
            out.close()


def cmd_plot(args):
    from host.analysis.plots import load_directions, plot_directions
    try:
        inputs = [load_directions(p) for p in args.inputs]
    except (OSError, ValueError) as exc:
        raise UserError(str(exc)) from None
    out = plot_directions(inputs, args.out, title=args.title or "")
    _emit(args, {"out": str(out), "points": [int(len(d["xy"])) for d in inputs]},
          f"wrote {out}")


def cmd_calibrate(args):
    from host.analysis.calibrate import calibrate, write_profile
    cam = _open_source(args.source)
    frames = []
    with cam:
        for fr in cam:
            frames.append(fr.image.copy())
            if len(frames) >= args.frames:
                break
    if not frames:
        raise UserError(f"{args.source}: no frames to calibrate from")
    try:
        res = calibrate(frames, name=args.name or Path(args.out).stem)
    except ValueError as exc:
        raise UserError(f"{args.source}: {exc}") from None
    res["out"] = str(write_profile(res, args.out))
    v = res["vision"]
    _emit(args, res, f"wrote {args.out}: dome {v['dome_px']}, block {v['block']}, offset "
                     f"{v['offset']}, pin area {v['min_area_px']}..{v['max_area_px']} px, "
                     f"pitch {v['pitch_px']} px, {v['n_pins']} pins")


def _load_windows(args, task: str, window: int, min_classes: int = 2):
    from host.data.specs import DataError, load_specs
    try:
        return load_specs(args.data, task=task, window=window,
                          contact_only=getattr(args, "contact_only", False),
                          profile=args.profile, progress=not args.json,
                          min_classes=min_classes)
    except (DataError, FileNotFoundError) as exc:
        raise UserError(str(exc)) from None


def _jsonable(res: dict) -> dict:
    return {k: v for k, v in res.items() if k not in ("onnx", "estimator", "pipeline")}


def cmd_train(args):
    from host.learn.tasks import TrainError
    ws = _load_windows(args, args.task, args.window)
    try:
        if args.model == "cnn":
            res = _train_cnn(args, ws)
        else:
            from host.learn.train import train_model
            res = train_model(args.task, args.model, ws, cv=args.cv, quantise=args.quantise,
                              seed=args.seed, out_dir=args.out, progress=not args.json)
    except TrainError as exc:
        raise UserError(str(exc)) from None
    res = _jsonable(res)
    m = res.get("metrics", {})
    m = m.get("test", m.get("held_out", m))
    headline = ", ".join(f"held-out {k} {m[k]:.4g}" for k in ("accuracy", "macro_f1", "mae")
                         if isinstance(m.get(k), (int, float)))
    if "int8" in res and isinstance(res["int8"], dict) and "agreement" in res["int8"]:
        headline += f"; int8 agreement {res['int8']['agreement']:.4f}"
    _emit(args, res, f"wrote {args.out}: {headline}")


def _train_cnn(args, ws):
    from host.learn.cnn import quantise_cnn, train_cnn
    from host.data.specs import split_grouped
    from host.learn.tasks import TrainError
    if args.task == "pressure":
        raise TrainError("the CNN classifies; use --model ridge for --task pressure")
    tr, te = split_grouped(ws, test_frac=0.3, seed=args.seed)
    res = train_cnn(ws.subset(tr), ws.subset(te), seed=args.seed, out_dir=args.out,
                    progress=not args.json)
    if args.quantise:
        res["int8"] = quantise_cnn(res["onnx_path"], ws.subset(tr),
                                   Path(args.out) / "model.int8.onnx", seed=args.seed)
    return res


def cmd_eval(args):
    import json as _json

    from device.pi.models.artefact import ModelError, read_manifest
    from host.learn.evaluate import evaluate_model
    try:
        doc, _ = read_manifest(args.model_dir)
    except ModelError as exc:
        raise UserError(str(exc)) from None
    task = doc.get("kind")
    T = int(doc.get("T", doc.get("window", 1)))
    ws = _load_windows(args, task, T, min_classes=1)
    try:
        res = evaluate_model(args.model_dir, ws, variant=args.variant)
    except (ModelError, ValueError) as exc:
        raise UserError(str(exc)) from None
    _emit(args, res, _json.dumps(res, indent=1, default=_json_default))


def cmd_report(args):
    from host.bench.report import build_report
    data = None
    try:
        data = real_data_dir(args.data)
    except UserError:
        print("host report: real recordings not found; simulated data only", file=sys.stderr)
    windows = tuple(int(x) for x in args.windows.split(","))
    cmd = "host report --out " + args.out + (" --quick" if args.quick else "")
    out = build_report(args.out, args.work, data, windows=windows, quick=args.quick,
                       seed=args.seed, progress=not args.json, command=cmd)
    _emit(args, {"out": str(out)}, f"wrote {out}")


def real_data_dir(given: str | None) -> Path:
    import os
    for cand in (given, os.environ.get("TACFOOT_REAL_DATA"),
                 Path(__file__).resolve().parents[1].parent / "shared" / "data"):
        if cand and Path(cand).is_dir():
            return Path(cand)
    raise UserError("real recordings not found: pass --data DIR or set TACFOOT_REAL_DATA")


def cmd_realism(args):
    from host.analysis.realism import realism_table, roboskin_realism, side_by_side_png
    data = real_data_dir(args.data)
    res = roboskin_realism(data, seed=args.seed)
    if args.png:
        res["png"] = side_by_side_png(data, args.png, seed=args.seed)
    _emit(args, res, realism_table(res) + ("\nall compared figures within 20%: "
                                           f"{'yes' if res['all_within_20pct'] else 'NO'}"))
    return 0 if res["all_within_20pct"] else 1


def cmd_deploy(args):
    from host.deploy.release import DeployInputError, options_from_args, run, summary_text
    try:
        opts = options_from_args(args)
        opts.check()
    except DeployInputError as exc:
        raise UserError(str(exc)) from None
    log = (lambda msg: print(msg, file=sys.stderr)) if not args.dry_run or args.json else (
        lambda msg: None)
    res = run(opts, dry_run=args.dry_run, rollback=args.rollback, log=log)
    _emit(args, res, summary_text(res))
    return 0 if res.get("ok") or args.dry_run else 1


def cmd_rig(args):
    from host.rig.trials import load_plan, plan_summary, run, summary_text
    plan = load_plan(args.trials)
    if args.rig_command == "check":
        s = plan_summary(plan)
        _emit(args, s, f"{s['source']}: {s['trials']} trials ({len(s['plates'])} plate(s) x "
                       f"{s['repetitions']} repetitions x {len(s['variants'])} variants), "
                       f"about {s['estimated_s'] / 60:.1f} min")
        return 0
    try:
        s = run(plan, args.rig, args.camera, Path(args.out), resume=args.resume,
                profile=args.profile, progress=not args.json, yes=args.yes, seed=args.seed)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    _emit(args, s, summary_text(s))
    return 1 if s["failed"] or s["remaining"] else 0


def cmd_monitor(args):
    from host.monitor import MonitorError, run_monitor
    if args.bench:
        from host.monitor import bench_link, format_bench
        res = bench_link()
        _emit(args, res, format_bench(res))
        return
    if not args.source:
        raise UserError("give a SERIAL_URL_OR_FILE to monitor (or --bench)")
    if args.count is not None and args.count < 1:
        raise UserError(f"--count must be at least 1, got {args.count}")
    if args.seconds is not None and not args.seconds > 0:
        raise UserError(f"--seconds must be positive, got {args.seconds}")
    try:
        run_monitor(args.source, as_json=args.json, count=args.count, seconds=args.seconds)
    except MonitorError as exc:
        raise UserError(str(exc)) from None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="host", description="tacfoot host toolkit")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("scenes", help="list the built-in simulator scenes")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_scenes)

    s = sub.add_parser("simulate", help="render a scene to a dataset folder")
    s.add_argument("scene", help="built-in scene name or a scene .toml file")
    s.add_argument("--out", required=True, help="dataset folder to write")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--trials", type=int, default=1, help="trials with seeds seed, seed+1, ...")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_simulate)

    s = sub.add_parser("view", help="draw frames with pin vectors to a GIF or PNG")
    s.add_argument("source", help="scene name, scene .toml or dataset folder (true vectors); "
                                  "a video, image folder or sim://SCENE (the pipeline's)")
    s.add_argument("--profile", default="roboskin", help="pipeline profile (recordings)")
    s.add_argument("--out", required=True, help="preview.gif or preview.png")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--max-frames", type=int, default=0)
    s.add_argument("--gain", type=float, default=2.0, help="arrow length per px of travel")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_view)

    s = sub.add_parser("demo", help="the main job on the simulated sensor")
    s.add_argument("--out", default="out/demo")
    s.add_argument("--scene", default="walk")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--fast", action="store_true",
                   help="do not pace the simulated camera at its frame rate (the gait "
                        "context then lags the frames)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_demo)

    s = sub.add_parser("analyse", help="run the marker pipeline over a video, image folder "
                                       "or sim://SCENE; one JSON line per frame")
    s.add_argument("source", help="clip.avi, a folder of images, or sim://SCENE")
    s.add_argument("--profile", default="roboskin", help="sensor profile name or .toml")
    s.add_argument("--localiser", help="localiser model folder (ONNX + manifest)")
    s.add_argument("--pressure", help="pressure regressor model folder")
    s.add_argument("--out", help="write the JSON lines here instead of stdout")
    s.add_argument("--json", action="store_true", help="(output is always JSON lines)")
    s.set_defaults(func=cmd_analyse)

    s = sub.add_parser("calibrate", help="fit a pipeline profile from a no-contact clip")
    s.add_argument("source", help="clip.avi, a folder of images, or sim://SCENE")
    s.add_argument("--out", required=True, help="profile .toml to write")
    s.add_argument("--frames", type=int, default=16, help="leading frames to use (at rest)")
    s.add_argument("--name", help="profile name (default: the file name)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_calibrate)

    s = sub.add_parser("plot", help="plots: directions (the paper's figure 5)")
    s.add_argument("kind", choices=["directions"])
    s.add_argument("inputs", nargs="+", help="paper-layout .npy files (trials, sensations, "
                                             "pressures, 2) or host analyse JSON lines")
    s.add_argument("--out", required=True, help="PNG to write")
    s.add_argument("--title")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_plot)

    s = sub.add_parser("train", help="train a surface/texture/slip/pressure model")
    s.add_argument("--task", required=True, choices=["surface", "texture", "slip", "pressure"])
    s.add_argument("--model", required=True,
                   choices=["rule", "ridge", "fnn", "grid-fnn", "cnn"])
    s.add_argument("--window", type=int, default=3, help="T, frames per window")
    s.add_argument("--data", action="append", required=True,
                   help="CSV manifest, dataset folder or .npz (repeatable)")
    s.add_argument("--cv", type=int, help="also report grouped K-fold CV metrics")
    s.add_argument("--quantise", action="store_true", help="also write an int8 model")
    s.add_argument("--contact-only", action="store_true",
                   help="drop windows without contact instead of labelling them no-touch")
    s.add_argument("--profile", default="roboskin")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True, help="model folder to write")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_train)

    s = sub.add_parser("eval", help="evaluate a model folder on data")
    s.add_argument("model_dir")
    s.add_argument("--data", action="append", required=True)
    s.add_argument("--variant", choices=["float", "int8"])
    s.add_argument("--contact-only", action="store_true")
    s.add_argument("--profile", default="roboskin")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_eval)

    s = sub.add_parser("report", help="what accuracy costs in time: tables + Pareto plots")
    s.add_argument("--out", default="docs/accuracy-vs-time.md")
    s.add_argument("--work", default="out/report", help="simulated data and scratch")
    s.add_argument("--data", help="real recordings folder")
    s.add_argument("--windows", default="1,2,3,5,10", help="window lengths T")
    s.add_argument("--quick", action="store_true", help="fewer simulated trials")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_report)

    s = sub.add_parser("realism", help="simulated roboskin against the real clips")
    s.add_argument("--data", help="real recordings folder (default $TACFOOT_REAL_DATA or "
                                  "../shared/data)")
    s.add_argument("--png", help="also write a real | simulated side-by-side PNG here")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_realism)

    s = sub.add_parser("bench", help="benchmarks (single thread, median and p99)")
    s.add_argument("what", choices=["sim", "pipeline", "runtime"])
    s.add_argument("--data", help="real recordings folder (pipeline)")
    s.add_argument("--frames", type=int, default=600, help="frames to run (runtime)")
    s.add_argument("--repeats", type=int, default=20)
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_bench)

    s = sub.add_parser("deploy", help="install the runtime on a Pi over SSH (systemd, "
                                      "health check, rollback)")
    from host.deploy.release import add_arguments as _deploy_arguments
    _deploy_arguments(s)
    s.set_defaults(func=cmd_deploy)
    s = sub.add_parser("rig", help="data-collection rig: validate and run trial files")
    rig_sub = s.add_subparsers(dest="rig_command", required=True)
    r = rig_sub.add_parser("check", help="validate a trial file (nothing moves)")
    r.add_argument("trials", help="trial file (.toml), see docs/rig.md")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_rig)
    r = rig_sub.add_parser("run", help="run a trial file on the rig and record a dataset")
    r.add_argument("trials", help="trial file (.toml), see docs/rig.md")
    r.add_argument("--rig", required=True, help="serial port or pyserial URL, or sim://")
    r.add_argument("--camera", required=True, help="v4l2:///dev/video0, or sim:// with --rig sim://")
    r.add_argument("--out", required=True, help="dataset folder")
    r.add_argument("--resume", action="store_true", help="run only the trials not yet recorded")
    r.add_argument("--profile", default="roboskin", help="sensor profile of the recordings")
    r.add_argument("--yes", action="store_true", help="do not prompt for plate swaps")
    r.add_argument("--seed", type=int, default=0, help="sim:// noise seed")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_rig)
    s = sub.add_parser("monitor", help="decode surface-link packets: rate, latest state, "
                                       "drops, CRC errors")
    s.add_argument("source", nargs="?", help="serial port, pyserial URL (loop://, "
                                             "socket://host:port), pty path, or a file of "
                                             "captured bytes")
    s.add_argument("--bench", action="store_true",
                   help="time the link instead: packet size, encode/decode, MicroPython")
    s.add_argument("--count", type=int, help="stop after this many messages")
    s.add_argument("--seconds", type=float, help="stop after this many seconds")
    s.add_argument("--json", action="store_true",
                   help="one JSON line per message and a summary line")
    s.set_defaults(func=cmd_monitor)
    return p


def main(argv: list[str] | None = None) -> int:
    from device.config import ConfigError
    from host.data.dataset import DatasetError

    args = build_parser().parse_args(argv)
    try:
        rc = args.func(args)
    except (ConfigError, DatasetError, UserError) as exc:
        print(f"host {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BrokenPipeError:
        return 0
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
